"""What the data cannot determine, said in one line: calibration parameters held because they
are confounded or undetermined, and smooth surface modes whose prior the data hardly shrink
(with the share of the other estimates' variance that prior carries), and two-face parameters
on one-face recordings."""

from __future__ import annotations

from collections.abc import Iterable, Sequence
from dataclasses import dataclass

import numpy as np

from ..model._model import ZERNIKE_PREFIX
from ..physics._catalog import INSTRUMENT, two_face_parameters
from ..solver._identifiable import unidentifiable


@dataclass
class Held:
    """A parameter the data cannot determine: held at ``value`` (its fixed or prior value)."""

    value: float
    note: str
    confounded_with: tuple[str, ...] = ()
    correlation: float | None = None


def hold_note(group, partners, corr, reason, sigmas, elevation_deg, *,
              then: str = "held at the fixed/prior value") -> str:
    """One line saying what the data cannot determine, why, and ``then`` what is done about
    it (``group``, ``partners``, ``corr``, ``reason``: one row of
    :func:`..solver.unidentifiable`; ``sigmas`` by name; ``elevation_deg`` or None)."""
    who = " and ".join(group)
    verb = "is" if len(group) == 1 else "are"
    where = (f"near zenith (elevation {elevation_deg:.1f} deg)" if elevation_deg is not None
             and elevation_deg > 80 else f"at elevation {elevation_deg:.1f} deg"
             if elevation_deg is not None else "")
    if reason == "correlation":
        with_ = ", ".join(partners) if partners else "the other unknowns together"
        text = f"{who} {verb} not separable from {with_} {where} (|correlation| {corr:.4f})"
    else:
        sig = ", ".join(f"{n} {sigmas[n]:.2g}" for n in group)
        text = (f"{who} {verb} not determined {where}: sigma ({sig}) exceeds the typical "
                f"magnitude" + (f"; correlated with {', '.join(partners)}" if partners else ""))
    return text.replace("  ", " ") + f"; {then}"


def hold_parameters(held: dict[str, Held], fixed: dict[str, float], bad, cov, names,
                    elevation) -> None:
    """Add to ``held`` the parameters of each row of ``bad`` (:func:`..solver.unidentifiable`
    on ``cov`` over ``names``), held at their ``fixed`` value or 0, with the note."""
    sig = dict(zip(names, np.sqrt(np.diag(np.asarray(cov)))))
    for group, partners, corr, reason in bad:
        note = hold_note(group, partners, corr, reason, sig, elevation)
        for n_ in group:
            held[n_] = Held(fixed.get(n_, 0.0), note, partners, corr)


def unidentifiable_calibration(cov, names: Sequence[str]) -> list:
    """:func:`..solver.unidentifiable` over the calibration parameters among ``names`` (object
    parameters are never held), each judged against its typical magnitude."""
    names = list(names)
    return unidentifiable(np.asarray(cov), names, [n for n in names if n in INSTRUMENT],
                          typical=typical_magnitudes())


#: What a per-cycle fit does with a parameter it cannot determine (:func:`undetermined_parameters`).
PER_CYCLE_UNDETERMINED = ("not reported: this per-cycle fit estimates it freely (the other "
                          "sigmas include that freedom)")


def undetermined_parameters(cov, names: Sequence[str], elevation_deg: float | None, *,
                            then: str) -> dict[str, str]:
    """The calibration parameters an adjustment estimated freely but its data cannot determine
    (:func:`unidentifiable_calibration`: x6/x7 near the zenith), each with its note ending in
    ``then`` (what is done about it): a per-cycle fit and the diagnosis report them as not
    identifiable instead of as estimates (their other sigmas include that freedom, so they
    stay right)."""
    names = list(names)
    sig = dict(zip(names, np.sqrt(np.maximum(np.diag(np.asarray(cov)), 0.0))))
    out = {}
    for group, partners, corr, reason in unidentifiable_calibration(cov, names):
        out.update(dict.fromkeys(group, hold_note(group, partners, corr, reason, sig,
                                                  elevation_deg, then=then)))
    return out


def one_face_holds(names: Iterable[str], fixed: dict[str, float]) -> dict[str, Held]:
    """The two-face parameters among ``names`` (not already fixed), held at their fixed value
    or 0: one face cannot separate them from the pose and f (``campaign-format.md``, cycle 0)."""
    return {n: Held(fixed.get(n, 0.0), f"{n} flips sign between the faces: a one-face "
                    "recording cannot separate it from the pose and f; held at "
                    f"{fixed.get(n, 0.0):g}")
            for n in two_face_parameters(names) if n not in fixed}


def typical_magnitudes() -> dict[str, float]:
    """Each calibration parameter's typical magnitude (its unit): a sigma above it says the
    data cannot determine the parameter."""
    return {k: p.typical for k, p in INSTRUMENT.items()}


#: Readable names of the smooth modes (Noll index -> aberration).
MODE_NAMES = {5: "astigmatism", 6: "astigmatism", 7: "coma", 8: "coma", 9: "trefoil",
              10: "trefoil", 11: "spherical"}
#: A mode is "not determined by the data" when they reduce its prior variance by less than this.
MODE_DETERMINED_MIN = 0.25
#: An unknown "leans on the modes' prior" when more than this share of its variance is theirs.
MODE_SHARE_NOTE = 0.5


def mode_prior(cov: np.ndarray, names: Sequence[str], ridge: dict | None,
               ridge_var) -> dict[str, dict[str, float]]:
    """What the data say about the smooth modes, and how much the other unknowns lean on them.

    ``cov`` is the adjustment's covariance of all unknowns ``names`` (modes included, m^2 for
    the modes), ``ridge`` maps each mode group to the modes' indices and ``ridge_var`` gives
    each group's prior variance (m^2). Returns ``{"determined": {mode: 1 - posterior var /
    prior var}, "share": {name: part of its variance the modes cause}}``. ``determined`` 0
    means the data add nothing to the prior (a mode that trades with the pose), 1 fully
    determined. ``share``: with the random effects eliminated as in Henderson's equations the
    estimate's response to a mode's true value is ``-C[x, m] / prior[m]``, so the modes'
    part of ``Var(x)`` is ``sum_m C[x, m]^2 / prior[m]`` (the rest is the noise's and the
    cells'). Empty without modes.
    """
    if not ridge:
        return {}
    C = np.asarray(cov, float)
    m_idx = [i for g in ridge.values() for i in g]
    prior = np.asarray([float(np.asarray(ridge_var)[k]) for k, g in enumerate(ridge.values())
                        for _ in g])
    k_idx = [i for i in range(len(names)) if i not in set(m_idx)]
    ok = prior > 0
    Ckm = C[np.ix_(k_idx, m_idx)][:, ok]
    part = np.sum(Ckm**2 / prior[ok], axis=1)
    var = np.diag(C)[k_idx]
    share = np.where(var > 0, part / np.where(var > 0, var, 1.0), 0.0)
    det = 1.0 - np.diag(C)[m_idx] / np.where(ok, prior, np.inf)
    return {"determined": {names[i]: float(np.clip(d, 0.0, 1.0)) for i, d in zip(m_idx, det)},
            "share": {names[i]: float(np.clip(v, 0.0, 1.0)) for i, v in zip(k_idx, share)}}


#: A smooth mode is "not separable" from the other unknowns when its multiple correlation with
#: them exceeds this (the identifiability rule of the calibration parameters).
MODE_CONFOUNDED_CORR = 0.99
#: The coma (or other confounded mode) amplitude the notes quote shifts for (m).
CONFOUNDING_AMPLITUDE_M = 1e-5
#: An estimate is "not separable" from a confounded mode when that amplitude of the mode moves
#: it by more than this many of its sigmas (tz: 0.35, f and calibration < 0.001 at a
#: simulated HartRAO position).
CONFOUNDING_SHIFT_MIN = 0.2


def mode_confounding(Qxx: np.ndarray, names: Sequence[str], ridge: dict | None, ridge_var,
                     noise_var: float) -> dict:
    """The smooth modes the other unknowns can take up, and by how much.

    Computed from an adjustment that carried the modes as a random effect (``Qxx`` its cofactor
    matrix, the modes' prior ``noise_var / ridge_var`` on their diagonal, which is taken out
    again): a mode whose multiple correlation with the other unknowns exceeds
    :data:`MODE_CONFOUNDED_CORR` cannot be told from them by the data (coma from the pose of a
    paraboloid: a rotation about a point near 2f on its axis moves the surface as coma does).
    Where such a mode is not modelled, the other unknowns take it up: their response to its
    true coefficient is ``N_kk^-1 N_km`` (per m; the regression of the mode's
    column on theirs). Returns ``{"modes": [...], "correlation":
    {mode: R}, "response": {name: {mode: d estimate / d coefficient}}}`` (empty without
    confounded modes)."""
    if not ridge:
        return {}
    N = np.linalg.inv(np.asarray(Qxx, float))
    m_idx = [i for g in ridge.values() for i in g]
    prior = np.array([float(np.asarray(ridge_var)[k]) for k, g in enumerate(ridge.values())
                      for _ in g])
    N[m_idx, m_idx] -= float(noise_var) / np.maximum(prior, 1e-300)
    k_idx = [i for i in range(len(names)) if i not in set(m_idx)]
    Nkk, Nkm = N[np.ix_(k_idx, k_idx)], N[np.ix_(k_idx, m_idx)]
    S = np.linalg.solve(Nkk, Nkm)  # (k, m): least squares without the mode takes it up
    explained = np.einsum("km,km->m", Nkm, S)  # N_mk N_kk^-1 N_km
    r2 = np.clip(explained / np.maximum(np.diag(N)[m_idx], 1e-300), 0.0, 1.0)
    weak = [j for j, r in enumerate(np.sqrt(r2)) if r > MODE_CONFOUNDED_CORR]
    if not weak:
        return {}
    modes = [names[m_idx[j]] for j in weak]
    return {"modes": modes,
            "correlation": {names[m_idx[j]]: float(np.sqrt(r2[j])) for j in weak},
            "response": {names[i]: {names[m_idx[j]]: float(S[a, j]) for j in weak}
                         for a, i in enumerate(k_idx)}}


def confounding_shifts(conf: dict, names: Sequence[str], sigma: Sequence[float],
                       amplitude_m: float = CONFOUNDING_AMPLITUDE_M) -> dict[str, float]:
    """Per estimate, the largest shift (in its sigmas) that confounded modes of ``amplitude_m``
    (their coefficients' root sum square) cause where they are not modelled."""
    out = {}
    for n, s in zip(names, sigma):
        r = conf.get("response", {}).get(n)
        if r and s and s > 0:
            out[n] = float(amplitude_m * np.sqrt(sum(v * v for v in r.values())) / s)
    return out


def confounding_note(conf: dict, names: Sequence[str], sigma: Sequence[float],
                     reason: str) -> str:
    """One line: the unknowns a mode that is not modelled moves by more than
    :data:`CONFOUNDING_SHIFT_MIN` sigma per :data:`CONFOUNDING_AMPLITUDE_M` (empty when none
    is)."""
    if not conf:
        return ""
    shifts = {n: v for n, v in confounding_shifts(conf, names, sigma).items()
              if v > CONFOUNDING_SHIFT_MIN}
    if not shifts:
        return ""
    modes = conf["modes"]
    kinds = sorted({MODE_NAMES.get(int(k[len(ZERNIKE_PREFIX):]), k) for k in modes})
    return (f"{', '.join(shifts)} are not separable from {' and '.join(kinds)} of the surface "
            f"({', '.join(modes)}: multiple correlation "
            f"{min(conf['correlation'].values()):.3f}), which one position cannot determine "
            f"and which is not modelled here ({reason}): "
            f"{1e6 * CONFOUNDING_AMPLITUDE_M:.0f} um of it would move them by "
            + ", ".join(f"{v:.1f}" for v in shifts.values())
            + " sigma; their sigmas hold for a surface without it")


def mode_prior_note(mp: dict, modes: dict[str, tuple[float, float]], prior_sd_m: float) -> str:
    """One line naming the modes the data do not determine and the unknowns that lean on their
    prior (empty when there are none)."""
    if not mp:
        return ""
    weak = [k for k, d in mp["determined"].items() if d < MODE_DETERMINED_MIN]
    if not weak:
        return ""
    leaning = {k: v for k, v in mp["share"].items() if v > MODE_SHARE_NOTE}
    kinds = sorted({MODE_NAMES.get(int(k[len(ZERNIKE_PREFIX):]), k) for k in weak})
    sds = ", ".join(f"{1e6 * modes[k][1]:.0f}" for k in weak if k in modes)
    text = (f"smooth modes {', '.join(weak)} ({', '.join(kinds)}) are not determined by "
            f"the data at this position (sd {sds} um against their prior {1e6 * prior_sd_m:.0f} "
            f"um)")
    if leaning:
        text += ("; " + ", ".join(leaning) + " take " + ", ".join(
            f"{100 * v:.0f}" for v in leaning.values()) + " % of their variance from that prior: "
            "their sigmas are as wide as the modes' variance (estimated from the modes the data "
            "show) makes them")
    return text
