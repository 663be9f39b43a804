"""Terminal summaries of joint fits and of the gravity model (the engine returns results;
only the CLI prints)."""

from __future__ import annotations

from ..fit._joint import JointFit
from ..model._model import parameter_unit
from ..surface._gravity import GravityModel


def print_joint_summary(jf: JointFit, console=None) -> None:
    """Shared estimates, precision gain and correlation drop on the terminal."""
    from rich.console import Console
    from rich.table import Table

    console = console or Console()
    t = Table(title=f"shared calibration ({jf.group})")
    for c in ("group", "parameter", "value", "sigma", "sigma joint/per scan", "ideal"):
        t.add_column(c, justify="right")
    gain = jf.precision_gain()
    for g, est in jf.shared_estimates().items():
        for n, (v, s) in est.items():
            scale, unit = (206264.806, '"') if parameter_unit(n) == "rad" else (1e3, " mm")
            gg = gain["shared"][n][g]
            t.add_row(g, n, f"{v * scale:.3f}{unit}", f"{s * scale:.3f}{unit}",
                      f"{gg['gain']:.3f}", f"{gg['ideal_gain']:.3f}")
    console.print(t)
    for h in jf.held.values():
        console.print(f"not identifiable: {h.note}")
    cd = jf.correlation_drop()["max_abs_corr_f_calibration"]
    console.print(f"max |corr(f, calibration)|: per scan median {cd['per_scan']['median']:.3f} "
                  f"(max {cd['per_scan']['max']:.3f}) -> joint median {cd['joint']['median']:.3f} "
                  f"(max {cd['joint']['max']:.3f}); sigma(f) joint/per scan median "
                  f"{gain['f']['gain_median']:.3f}; sigma0 {jf.sigma0:.4f}")


def print_gravity_summary(gm: GravityModel, console=None) -> None:
    from rich.console import Console
    from rich.table import Table

    console = console or Console()
    t = Table(title=f"gravity model over {len(gm.positions)} positions")
    for c in ("term", "value", "sigma", "sigma (scaled)"):
        t.add_column(c, justify="right")
    for n, b, s, ss in zip(gm.focal.names, gm.focal.beta, gm.focal.sigma, gm.focal.sigma_scaled):
        t.add_row(f"f: {n}", f"{b * 1e3:.4f} mm", f"{s * 1e3:.4f} mm", f"{ss * 1e3:.4f} mm")
    for j, z in zip(gm.modes, gm.zernike):
        for n, b, s, ss in zip(z.names[1:], z.beta[1:], z.sigma[1:], z.sigma_scaled[1:]):
            t.add_row(f"Z{j}: {n}", f"{b * 1e6:.1f} um", f"{s * 1e6:.1f} um", f"{ss * 1e6:.1f} um")
    console.print(t)
    te = gm.test
    console.print(f"f depends on g_z only? F = {te['F']:.2f} (dof {te['F_dof']}), "
                  f"p = {te['p_value_F']:.3g}; chi2 difference {te['chi2_difference']:.1f}, "
                  f"p = {te['p_value_chi2']:.3g}")
