"""The surface random effect of a position adjustment: its smooth modes and variances.

What :func:`._fit.fit_position` carries besides the panels' offsets and tilts (the smooth
Zernike modes gravity produces, :data:`SURFACE_MODE_GROUPS`), whether the data show them
(:func:`_absent_modes`), the start values of the variance components, how each sigma splits
into the noise's part and the surface's (:func:`white_sigmas`), and the campaign's mode
variance lent to positions whose pose takes up a mode they cannot determine
(:func:`positions_for_campaign_prior`). NumPy only; units SI (m^2 for mode variances).
"""

from __future__ import annotations

from collections.abc import Mapping, Sequence

import numpy as np

from ..solver._mixed import ridge_chi2

#: Smooth surface modes (Noll indices) carried as random effects on a centred reflector, one
#: variance per group: astigmatism, coma, trefoil, spherical -- what gravity produces. Piston,
#: tilt and defocus are the pose and f themselves.
SURFACE_MODE_GROUPS: dict[str, tuple[int, ...]] = {"modes": (5, 6, 7, 8, 9, 10, 11)}
SURFACE_MODES: tuple[int, ...] = tuple(j for g in SURFACE_MODE_GROUPS.values() for j in g)
#: Start values of the variance components: offsets (m^2), tilts (rad^2), modes (m^2).
_CELL_VAR0 = (1e-8, 1e-8, 1e-8)
_MODE_VAR0 = 1e-8


#: Level of the test that keeps a group of smooth modes in the random effect (None: keep all).
MODE_TEST_ALPHA: float | None = 0.01


def _absent_modes(rm, ridge: dict | None, tests: dict) -> list[str]:
    """Groups of smooth modes the data do not show: their coefficients, estimated as fixed
    effects with the cells still random, are consistent with zero (chi-square test at
    :data:`MODE_TEST_ALPHA`, :func:`ridge_chi2`). Why: a variance estimated from a handful of
    coefficients that are noise is itself noise, and one of a few times 1e-4 m on coma (nearly a
    pose change) inflates the sigmas of the pose several-fold; modes the data do show (gravity's
    astigmatism) keep their variance. The tests are recorded in ``tests`` (first verdict)."""
    if MODE_TEST_ALPHA is None or not ridge:
        return []
    out = []
    for k, (t, dof, p) in ridge_chi2(rm, ridge).items():
        tests.setdefault(k, {"chi2": t, "dof": dof, "p": p, "carried": p <= MODE_TEST_ALPHA})
        if p > MODE_TEST_ALPHA:
            out.append(k)
    return out


def white_sigmas(response: np.ndarray, cell_var, cov: np.ndarray,
                 mode_part: np.ndarray | None = None) -> np.ndarray:
    """The noise's part of each sigma: ``sqrt(diag(cov) - sum_g R_g diag(cell_var) R_g^T -
    mode_part)`` with ``R_g`` (g, u, k) the estimates' response to each cell (the surface's
    part) and ``mode_part`` the smooth modes' part of each variance (:func:`mode_prior`)."""
    surf = np.einsum("gik,k,gik->i", response, np.asarray(cell_var), response)
    if mode_part is not None:
        surf = surf + mode_part
    return np.sqrt(np.maximum(np.diag(cov) - surf, 0.0))


def mode_variance_parts(mode_prior: Mapping[str, dict], names: Sequence[str],
                        keep: Sequence[int], cov_keep: np.ndarray) -> np.ndarray | None:
    """The smooth modes' part of the variance of each kept unknown (m^2, rad^2, ...), from a
    position's ``SurfaceEffect.mode_prior`` (:func:`._identify.mode_prior`)."""
    share = mode_prior.get("share")
    if not share:
        return None
    return np.array([share.get(names[i], 0.0) for i in keep]) * np.diag(cov_keep)


def _mode_variances(ridge: dict | None, ridge_var) -> dict[str, float]:
    """The smooth modes' variance components: ``modes_m2`` the mean variance per mode (m^2)
    and, with several groups, ``mode_groups_m2`` each group's."""
    if not ridge:
        return {}
    rv = np.asarray(ridge_var, float)
    sizes = np.array([len(v) for v in ridge.values()], float)
    out: dict = {"modes_m2": float(np.sum(rv * sizes) / np.sum(sizes))}
    if len(ridge) > 1:
        out["mode_groups_m2"] = {k: float(v) for k, v in zip(ridge, rv)}
    return out


def surface_components(var: tuple, redundancy: tuple, ridge: dict | None) -> tuple[dict, dict]:
    """``SurfaceEffect.variances`` and ``.redundancy`` from a mixed adjustment's variance
    components ``var = (noise factor, cell variances (k,), ridge variances (r,))`` and their
    redundancy shares in the same order (in-memory and streamed adjustments alike)."""
    noise, cells, modes = var
    r_noise, r_cells, r_modes = redundancy
    cells, r_cells = np.asarray(cells, float), np.asarray(r_cells, float)
    variances = {"noise": float(noise), "offset_m2": float(cells[0]),
                 "tilt_rad2": float(np.mean(cells[1:])), **_mode_variances(ridge, modes)}
    shares = {"noise": float(r_noise), "offset": float(r_cells[0]),
              "tilt": float(np.sum(r_cells[1:])),
              **({"modes": float(np.sum(np.asarray(r_modes)))} if ridge else {})}
    return variances, shares


#: The fewest positions showing the smooth modes whose variances make a campaign's prior.
POOL_MIN_POSITIONS = 2


def pooled_mode_variance(variances: Sequence[float]) -> float | None:
    """The campaign's variance of the smooth modes (m^2): the median of the positions that
    carry them (each estimated from its own data), None from fewer than
    :data:`POOL_MIN_POSITIONS`. Why: coma trades with the pose, so one position cannot
    estimate it; gravity changes all low-order modes together, so the positions that show
    them (astigmatism above all) give its size."""
    v = [float(a) for a in variances if a is not None and a > 0]
    return float(np.median(v)) if len(v) >= POOL_MIN_POSITIONS else None


def positions_for_campaign_prior(variances: Mapping[str, float | None],
                                 confounded: Mapping[str, bool]
                                 ) -> tuple[float | None, list[str]]:
    """The campaign's mode variance (:func:`pooled_mode_variance` of the positions'
    ``variances``, None where they do not carry the modes) and the positions to adjust again
    with it: those whose pose takes up a mode they cannot determine (``confounded``; none
    without a campaign variance). One rule for ``fit``, ``fit-dask`` and ``fit-stream``."""
    prior = pooled_mode_variance(list(variances.values()))
    return prior, [p for p, c in confounded.items() if c and prior is not None]


def takes_campaign_prior(confounding: Mapping | None, modes: Mapping | None) -> bool:
    """Whether a position's adjustment changes with the campaign's mode variance: its pose
    takes up smooth modes it cannot determine (``confounding``, as
    ``SurfaceEffect.mode_confounding`` or a record's ``surface_mode_confounding``) and it
    carries none of them (``modes``): a position carrying some keeps its own variance, and
    adjusting it again would repeat the same adjustment."""
    return bool(confounding) and not modes


def record_mode_variance(rec: dict) -> float | None:
    """:func:`_carried_mode_variance` of a ``positions[]`` record (m^2)."""
    sd = (rec.get("variance_components") or {}).get("modes_m")
    return float(sd) ** 2 if rec.get("surface_modes") and sd else None
