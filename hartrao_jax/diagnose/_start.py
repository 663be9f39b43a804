"""The start of a diagnosis: every scan fitted with the start model as ``fit`` does, its
geometry (telescope coordinates, panels, normal scale, faces, incidence angle) frozen into a
:class:`._state._Scan`."""

from __future__ import annotations

import logging
from collections.abc import Sequence

import numpy as np

from .._config import each_in_threads
from ..campaign._campaign import read_scan, require_points
from ..fit._align import mean_heading, scan_heading
from ..fit._fit import finish_scan_fit, prepare_scan, scan_arrays, side_by_side
from ..geometry._geometry import (
    face_of,
    panel_cells,
    paraboloid_normal_scale,
    pointing_gravity,
    rot_z,
)
from ..model._model import make_model, parse_model
from ._state import _adjust, _Context, _Scan

log = logging.getLogger("hartrao_jax")


def _start_scans(ctx: _Context, start: tuple[str, ...], keep,
                 scans: Sequence[str] | None) -> list[_Scan]:
    """Fit every scan with the start model (as ``fit`` does) and freeze its geometry. The
    scans are read, prepared and adjusted in threads (each on its own arrays); the fits are
    finished in order of decreasing tilt, each with the mount heading of those before it."""

    camp = ctx.campaign
    metas = [camp.scan(s) for s in scans] if scans else list(camp.scans)
    tel, site = camp.telescope, camp.site
    tilt = {m.id: np.arccos(np.clip(-pointing_gravity(m, tel, site)[2], -1, 1)) for m in metas}
    order = sorted(metas, key=lambda m: -tilt[m.id])

    def adjusted(meta):
        data = read_scan(camp, meta)
        require_points(len(data), len(parse_model(start)), file=camp.root / meta.file,
                       scan_id=meta.id, what="the start model")  # refused by name
        k = np.asarray(keep(meta, data), bool) if keep is not None else None
        data, g, init, window = prepare_scan(camp, meta, data, keep=k)
        mdl = make_model(start, aperture_radius_m=ctx.aperture, check_separable=False)
        l, c = scan_arrays(data)
        x0 = np.array([init.x.get(n, 0.0) for n in mdl.free])
        return mdl, data, _adjust(ctx, mdl, l, x0, c, window.astype(float)), g, init, window

    # in threads where the files are small enough for two at once (as ``fit``'s faces)
    done = (each_in_threads(adjusted, order, "start-fits") if side_by_side(camp, order)
            else map(adjusted, order))
    fits, headings = {}, []
    for meta, (mdl, data, res, g, init, window) in zip(order, done):
        f = finish_scan_fit(camp, meta, mdl, data, res, g, init, window,
                            heading_hint_rad=mean_heading(headings))
        headings.append(scan_heading(f))
        fits[meta.id] = (f, window)
        log.info("start fit %s: sigma0 %.3f, %d points", meta.id, f.sigma0, f.n_points)

    out = []
    for meta in metas:  # campaign order
        f, window = fits[meta.id]
        X = f.X_tel
        rho = np.hypot(X[:, 0], X[:, 1])
        psi = np.mod(np.arctan2(X[:, 1], X[:, 0]), 2 * np.pi)
        pid, local, _, _ = panel_cells(X, ctx.edges, ctx.counts)
        fval = f.value("f")
        s_rho = paraboloid_normal_scale(rho, fval, np)
        # incidence angle: beam (from the scanner origin, fitted frame) against the normal

        t = np.array([f.value("tx"), f.value("ty"), f.value("tz")]) @ rot_z(
            f.alignment.kappa_rad, np).T
        d = X - t
        nrm = np.column_stack([-X[:, 0] / (2 * fval), -X[:, 1] / (2 * fval), np.ones(len(X))])
        cosi = np.abs(np.sum(d * nrm, 1)) / (np.linalg.norm(d, axis=1) * np.linalg.norm(nrm, axis=1)
                                             + 1e-300)
        window = window | f.used
        n = len(f.data)
        sc = _Scan(
            meta=f.meta, data=f.data, g=np.asarray(f.gravity), init_x=dict(f.init.x),
            window=window, l=np.column_stack([f.data.range_m, f.data.phi_rad,
                                                      f.data.theta_rad]),
            kappa=float(f.alignment.kappa_rad), elevation_deg=float(f.elevation_deg), X_tel=X,
            rho=rho, psi=psi, panel=pid, local=local, s_rho=s_rho, face=face_of(f.data.theta_rad),
            incidence=np.arccos(np.clip(cosi, 0, 1)), known=np.zeros(n), extra_known=np.zeros(n),
            cut=np.zeros(n, bool),
        )
        sc.names, sc.x, sc.cov, sc.sigma0 = f.names, f.x, f.cov, f.sigma0
        sc.v, sc.used, sc.converged = f.v, f.used, f.converged
        out.append(sc)
    return out
