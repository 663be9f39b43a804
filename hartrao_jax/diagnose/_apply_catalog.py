"""Modelling an accepted catalog explanation: the joint step of the panel offsets and shared
parameters, then an instrument parameter shared by all scans, a motion of one scan (or of the
same motion in the other cycles: :mod:`._apply_motion`), or Zernike modes linear in gravity.

Each ``_apply_*`` returns the fields of the :class:`~._state.Finding` it describes. Units:
metres, radians, seconds (estimates in the parameters' own units, :func:`parameter_unit`).
"""

from __future__ import annotations

from collections.abc import Sequence
from typing import Any

import numpy as np

from ..model._model import format_estimate
from ._apply_motion import _apply_motion, _with_twins
from ._explain import _Joint, _Test
from ._options import _Option
from ._panels import _joint_step, _update_panels, _update_shared
from ._signature import _signature, _where_of_signature
from ._state import ZERNIKE_TESTED, _Context, _num, _refit_all, _Scan, _Spec


def _apply_instrument(ctx: _Context, S: Sequence[_Scan], spec: _Spec, joint: _Joint, t: _Test,
                      dz: np.ndarray, expl: str) -> dict[str, Any]:
    """One instrument parameter, one value for all scans (its joint estimate); refit all."""
    k = t.cand.names[0]
    _update_shared(spec, joint, dz)
    spec.shared[k] = float(t.estimate[0])
    spec.shared_sigma[k] = float(t.sigma[0])
    estimate = {k: {"value": float(t.estimate[0]), "sigma": float(t.sigma[0])}}
    sig0 = _signature(ctx, S[0], spec, [k], t.estimate[:1] * 0 + 1.0)
    where = {k2: v for k2, v in _where_of_signature(ctx, S[0], sig0, False).items()
             if k2 in ("covariate", "face_split")}
    extra = {"scan_difference": {"statistic": _num(t.T_diff), "dof": t.dof_diff}}
    _refit_all(ctx, S, spec)
    return {"where": where, "estimate": estimate, "extra": extra,
            "explanation": f"{expl}; {k} = {format_estimate(k, t.estimate[0], t.sigma[0])}, "
                           f"one value for all scans"}


def _apply_gravity(ctx: _Context, S: Sequence[_Scan], spec: _Spec, joint: _Joint, t: _Test,
                   dz: np.ndarray, expl: str) -> dict[str, Any]:
    """Zernike coefficients (m per unit g along x, y, z) linear in gravity; refit all."""
    _update_shared(spec, joint, dz)
    C = t.estimate.reshape(len(ZERNIKE_TESTED), 3)
    spec.zern_C = C
    sg = t.sigma.reshape(len(ZERNIKE_TESTED), 3)
    estimate = {}
    for i, j in enumerate(ZERNIKE_TESTED):
        for a, ax in enumerate("xyz"):
            estimate[f"zern_{j}_per_g{ax}"] = {"value": float(C[i, a]), "sigma": float(sg[i, a])}
    where = {"covariate": "gravity", "positions": sorted({s.meta.position for s in S})}
    extra = {"covariance": t.cov.tolist()}
    _refit_all(ctx, S, spec)
    return {"where": where, "estimate": estimate, "extra": extra,
            "explanation": f"{expl}; Zernike modes {', '.join(map(str, ZERNIKE_TESTED))} "
                           f"linear in g"}


def _apply_catalog(ctx: _Context, S: Sequence[_Scan], spec: _Spec, joint: _Joint, o: _Option,
                   expl: str) -> dict[str, Any]:
    """A catalog test: (a motion with its twins in the other cycles as one candidate,) the
    joint step of the panel offsets, then the family's own modelling."""
    t: _Test = o.payload
    c = t.cand
    if o.family == "motion" and c.info.get("twins"):
        c, t = _with_twins(ctx, joint, o, t)
    dz = _joint_step(joint, t)
    _update_panels(spec, joint, dz)
    part: dict[str, Any] = {}
    if o.family == "instrument":
        part = _apply_instrument(ctx, S, spec, joint, t, dz, expl)
    elif o.family == "motion":
        part = _apply_motion(ctx, S, spec, joint, c, t, dz, expl)
    elif c.effect == "gravity_deformation":
        part = _apply_gravity(ctx, S, spec, joint, t, dz, expl)
    return {"scans": list(c.scans), **part}
