"""North alignment: the rotation ``kappa`` about the paraboloid axis (fitted -> telescope frame).

The adjustment (seed eq. 6) estimates only ``Ry(ry) Rx(rx)``: rotation about the paraboloid's
axis is not observable from a paraboloid of revolution. ``kappa`` brings the fitted frame to the
telescope frame of ``campaign-format.md`` (X north at the zenith): ``X_tel = Rz(kappa) X_fit``.

* Away from the zenith the scanner's z axis (gravity, by its gimbal) has a horizontal component
  in both frames; ``kappa`` is the difference of its azimuths.
* At the zenith gravity is along the axis and says nothing; the quadrupod legs cast shadows at
  known azimuths (telescope frame). Their azimuths in the fitted frame give ``kappa`` modulo the
  legs' symmetry (90 deg for four legs); the remaining ambiguity is resolved with the scanner's
  heading on its mount, which other positions of the campaign determine (:func:`mount_heading`).
"""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np

from ..geometry._geometry import decompose_zyx, rot_x, rot_y, rot_z
from ..preprocess._initial import gimbal_rotation

MIN_TILT_RAD = np.radians(2.0)  # below this zenith angle gravity does not fix kappa well


@dataclass(frozen=True)
class Alignment:
    kappa_rad: float
    source: str  # "gravity" | "quadrupod" | "quadrupod+heading" | "none"
    ambiguity_rad: float = 0.0  # symmetry left unresolved (0: unique)


def _wrap(a):
    return np.mod(np.asarray(a) + np.pi, 2 * np.pi) - np.pi


def kappa_from_gravity(rx: float, ry: float, gravity: np.ndarray) -> float:
    """``kappa`` (rad) from the azimuth of gravity in the fitted and in the telescope frame."""
    g_fit = (rot_y(ry, np) @ rot_x(rx, np))[:, 2]  # scanner z axis in the fitted frame
    g = np.asarray(gravity, float)
    return float(_wrap(np.arctan2(g[1], g[0]) - np.arctan2(g_fit[1], g_fit[0])))


def kappa_from_legs(
    X_fit: np.ndarray,
    leg_azimuths_deg,
    *,
    rho_range_m: tuple[float, float],
    halfwidth_rad: float = np.radians(1.0),
    step_rad: float = np.radians(0.05),
) -> tuple[np.ndarray, float]:
    """Candidate ``kappa`` values (rad) that put the leg shadows where the points are missing.

    Counts reflector points within ``halfwidth_rad`` of each leg azimuth (mapped into the fitted
    frame) for ``kappa`` on a fine grid; the emptiest alignment wins. Returns every equivalent
    candidate (the legs' rotational symmetry) and the contrast (count at the best alignment over
    the median count: near 0 means clear shadows, near 1 means no shadows found).
    """
    legs = np.radians(np.asarray(leg_azimuths_deg, float))
    rho = np.hypot(X_fit[:, 0], X_fit[:, 1])
    sel = (rho >= rho_range_m[0]) & (rho <= rho_range_m[1])
    psi = np.mod(np.arctan2(X_fit[sel, 1], X_fit[sel, 0]), 2 * np.pi)
    nb = int(round(2 * np.pi / step_rad))
    hist = np.bincount(np.minimum((psi / step_rad).astype(int), nb - 1), minlength=nb)
    w = max(1, int(round(halfwidth_rad / step_rad)))
    ext = np.concatenate([hist[-w:], hist, hist[:w]])
    dens = np.convolve(ext, np.ones(2 * w + 1), mode="valid")  # points within +-w bins of bin i
    kap = np.arange(nb) * step_rad
    # legs at azimuth L (telescope) sit at psi_fit = L - kappa
    counts = np.zeros(nb)
    for L in legs:
        j = np.mod(np.round((L - kap) / step_rad).astype(int), nb)
        counts += dens[j]
    best = counts.min()
    med = np.median(counts)
    contrast = float(best / med) if med > 0 else 1.0
    # symmetric candidates: minima within 2 % of the best, separated by > 10 deg; each taken at
    # the middle of its flat bottom (a shadow wider than the counting window leaves a plateau)
    tol = best + 0.02 * max(med - best, 1)
    low = counts <= tol
    cands: list[float] = []
    for i in np.argsort(counts):
        if not low[i]:
            break
        lo = hi = 0
        while lo < nb and low[(i - lo - 1) % nb]:
            lo += 1
        while hi < nb and low[(i + hi + 1) % nb]:
            hi += 1
        k = kap[i] + 0.5 * (hi - lo) * step_rad
        if all(abs(_wrap(k - c)) > np.radians(10) for c in cands):
            cands.append(float(_wrap(k)))
    return np.asarray(cands), contrast


def refine_kappa_from_legs(
    X_fit: np.ndarray, leg_azimuths_deg, kappa0: float, *, rho_range_m: tuple[float, float],
    ring_width_m: float = 0.15, search_rad: float = np.radians(10.0),
) -> float:
    """Refine ``kappa`` to a fraction of the scan's angular step from the leg shadows' gaps.

    In each thin ring of dish radius, the shadow of a leg is the widest gap between consecutive
    point azimuths near where the leg should be; the middle of that gap is the shadow's axis.
    The median over rings and legs of (expected - found) corrects ``kappa0``: the sampling
    phase differs from ring to ring, so the median resolves much finer than one step.
    """
    legs = np.radians(np.asarray(leg_azimuths_deg, float))
    rho = np.hypot(X_fit[:, 0], X_fit[:, 1])
    psi = np.arctan2(X_fit[:, 1], X_fit[:, 0])
    offsets = []
    edges = np.arange(rho_range_m[0], rho_range_m[1], ring_width_m)
    ring = np.digitize(rho, edges)
    for L in legs:
        expect = L - kappa0
        d = _wrap(psi - expect)
        near = np.abs(d) < search_rad
        for k in np.unique(ring[near]):
            if k == 0 or k == len(edges):
                continue
            a = np.sort(d[near & (ring == k)])
            if len(a) < 6:
                continue
            gaps = np.diff(a)
            i = int(np.argmax(gaps))
            if gaps[i] < 3 * np.median(gaps):
                continue  # no clear shadow in this ring
            offsets.append(0.5 * (a[i] + a[i + 1]))
    if len(offsets) < 5:
        return kappa0
    return float(_wrap(kappa0 - np.median(offsets)))


def mount_heading(kappa: float, rx: float, ry: float, gravity: np.ndarray) -> float:
    """Scanner heading on its mount (rad) implied by a scan's ``kappa`` and attitude.

    ``Rz(kappa) Ry(ry) Rx(rx) = R_gimbal(g) Rz(heading)``: the heading is a property of the
    mounting, the same at every position of a campaign.
    """
    R = rot_z(kappa, np) @ rot_y(ry, np) @ rot_x(rx, np)
    Rz_h = gimbal_rotation(gravity).T @ R
    return float(np.arctan2(Rz_h[1, 0], Rz_h[0, 0]))


def scan_heading(fit) -> float | None:
    """Mount heading (rad) of a fitted scan (anything with ``alignment``, ``value(name)`` and
    ``gravity``) whose north alignment came from gravity; None otherwise."""
    if fit.alignment.source != "gravity":
        return None
    return mount_heading(fit.alignment.kappa_rad, fit.value("rx"), fit.value("ry"), fit.gravity)


def mean_heading(headings) -> float | None:
    """Circular mean (rad) of the headings that are not None; None when there are none: the
    hint other positions give a flat one (:func:`north_alignment`'s ``heading_hint_rad``)."""
    hs = [h for h in headings if h is not None]
    return float(np.angle(np.mean(np.exp(1j * np.array(hs))))) if hs else None


def kappa_from_heading(heading: float, gravity: np.ndarray) -> float:
    """``kappa`` (rad) predicted from a known mount heading at a position with gravity ``g``."""
    R = gimbal_rotation(gravity) @ rot_z(heading, np)
    return float(decompose_zyx(R, np)[0])


def north_alignment(
    rx: float,
    ry: float,
    gravity: np.ndarray,
    X_fit: np.ndarray | None = None,
    *,
    used: np.ndarray | None = None,
    leg_azimuths_deg=None,
    rho_range_m: tuple[float, float] = (3.0, 12.0),
    heading_hint_rad: float | None = None,
) -> Alignment:
    """``kappa`` of one scan: from gravity when the dish is tilted, else from the leg shadows.

    ``X_fit`` (n, 3) m: the points in the fitted frame; ``used`` (n,) bool: those to look at
    (default all; taken only where the legs are needed, so that a tilted dish copies none of
    its points: 0.2-0.3 s for a 6.3e6-point scan). ``heading_hint_rad``: the mount heading
    known from other positions (resolves the legs' symmetry at the zenith).
    """
    g = np.asarray(gravity, float)
    tilt = np.arccos(np.clip(-g[2], -1, 1))
    if tilt >= MIN_TILT_RAD:
        return Alignment(kappa_from_gravity(rx, ry, g), "gravity")
    if X_fit is None or leg_azimuths_deg is None or len(leg_azimuths_deg) == 0:
        if heading_hint_rad is not None:
            return Alignment(kappa_from_heading(heading_hint_rad, g), "heading")
        return Alignment(kappa_from_gravity(rx, ry, g), "gravity (weak: near zenith)")
    if used is not None:
        X_fit = X_fit[used]
    cands, contrast = kappa_from_legs(X_fit, leg_azimuths_deg, rho_range_m=rho_range_m)
    if len(cands) == 0 or contrast > 0.8:
        return Alignment(kappa_from_gravity(rx, ry, g), "gravity (weak: no leg shadows)")
    if heading_hint_rad is not None:
        pred = kappa_from_heading(heading_hint_rad, g)
        k = cands[np.argmin(np.abs(_wrap(cands - pred)))]
        k = refine_kappa_from_legs(X_fit, leg_azimuths_deg, float(k), rho_range_m=rho_range_m)
        return Alignment(float(k), "quadrupod+heading")
    k = cands[np.argmin(np.abs(cands))]
    k = refine_kappa_from_legs(X_fit, leg_azimuths_deg, float(k), rho_range_m=rho_range_m)
    amb = 2 * np.pi / len(cands) if len(cands) > 1 else 0.0
    return Alignment(float(k), "quadrupod", float(amb))
