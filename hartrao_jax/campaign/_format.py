"""The campaign format's vocabulary: constants, the one-line `CampaignError`, the metadata and
scan-table classes, and the recording's face rule (raw two-face angles of scanner-frame points).
Readers and writers (Parquet in `_campaign`, E57 in `_e57`) build on it.
"""

from __future__ import annotations

import datetime as dt
import logging
import math
import pathlib
from collections.abc import Sequence
from dataclasses import dataclass, field

import numpy as np

log = logging.getLogger(__name__)

FORMAT = "hartrao-campaign/1"
ANGLE_TOL_RAD = 1e-9
PHI_RANGE = {0: (0.0, 2 * math.pi), 1: (0.0, math.pi), 2: (math.pi, 2 * math.pi)}
_RANGE_TEXT = {0: "[0, 2 pi)", 1: "[0, pi)", 2: "[pi, 2 pi)"}
COLUMNS = ("range_m", "phi_rad", "theta_rad", "intensity", "time_s")
DEFAULT_INTENSITY = 0.5
#: Instrument limit on the range (m) when the campaign's ``[scanner]`` table gives no
#: ``max_range_m``: phase-based and time-of-flight terrestrial scanners measure at most a few
#: hundred metres to about 1 km; a larger range is a corrupt value, never an observation.
MAX_RANGE_M = 1000.0
#: Reasons a row of a scan table is dropped while reading (keys of ``ScanData.dropped``).
DROP_REASONS = {
    "nonfinite": "a NaN, infinite or null value (range, angles, intensity or time)",
    "range_nonpositive": "range <= 0",
    "range_above_max": "range above the instrument maximum (max_range_m)",
}
#: Observations needed per free parameter of a model (see :func:`minimum_points`).
POINTS_PER_PARAMETER = 50


class CampaignError(Exception):
    """One-line, user-facing error: '<file>: <field>: <what was expected, what was found>'."""

    def __init__(self, file, field, message):
        self.file, self.field, self.message = str(file), str(field), str(message)
        super().__init__(f"{self.file}: {self.field}: {self.message}")


# ----------------------------------------------------------------------------- data classes


def _tuple(v):
    return None if v is None else tuple(v)


@dataclass(frozen=True)
class Site:
    name: str
    latitude_deg: float
    longitude_deg: float | None
    extra: dict = field(default_factory=dict)


@dataclass(frozen=True)
class Telescope:
    name: str
    mount: str  # "ha-dec" | "alt-az"
    diameter_m: float
    focal_length_m: float
    cone_radius_m: float
    quadrupod_azimuths_deg: tuple[float, ...] | None
    ring_edges_m: tuple[float, ...] | None
    panels_per_ring: tuple[int, ...] | None
    offset_m: float = 0.0
    extra: dict = field(default_factory=dict)

    def __post_init__(self):
        for k in ("quadrupod_azimuths_deg", "ring_edges_m", "panels_per_ring"):
            object.__setattr__(self, k, _tuple(getattr(self, k)))


@dataclass(frozen=True)
class Scanner:
    sigma_range_m: float
    sigma_angle_rad: float
    angular_step_rad: float
    extra: dict = field(default_factory=dict)
    #: instrument range limit (m); None: :data:`MAX_RANGE_M`. Rows beyond it are dropped.
    max_range_m: float | None = None

    @property
    def range_limit_m(self) -> float:
        return MAX_RANGE_M if self.max_range_m is None else float(self.max_range_m)


@dataclass(frozen=True)
class ScanMeta:
    id: str
    position: str
    cycle: int
    file: str  # relative to the campaign directory, as in the TOML
    ha_deg: float | None = None
    dec_deg: float | None = None
    elevation_deg: float | None = None
    azimuth_deg: float | None = None
    tour: str | None = None
    start: dt.datetime | None = None
    temperature_c: float | None = None
    extra: dict = field(default_factory=dict)


@dataclass(frozen=True)
class Campaign:
    root: pathlib.Path  # the campaign directory
    site: Site
    telescope: Telescope
    scanner: Scanner
    scans: tuple[ScanMeta, ...]
    extra: dict = field(default_factory=dict)

    def __post_init__(self):
        object.__setattr__(self, "root", pathlib.Path(self.root))
        object.__setattr__(self, "scans", tuple(self.scans))

    def scan(self, scan_id: str) -> ScanMeta:
        """The scan with this id; `CampaignError` if there is none."""
        for s in self.scans:
            if s.id == scan_id:
                return s
        known = ", ".join(s.id for s in self.scans[:20]) + (", ..." if len(self.scans) > 20 else "")
        raise CampaignError(self.root / "campaign.toml", "scan.id",
                            f"expected one of the campaign's scan ids ({known}), found {scan_id!r}")

    def positions(self) -> dict[str, list[ScanMeta]]:
        """Position -> its scans, both in file order."""
        out: dict[str, list[ScanMeta]] = {}
        for s in self.scans:
            out.setdefault(s.position, []).append(s)
        return out


@dataclass
class ScanData:
    """One scan's raw observations (NumPy). Rows are those of the file minus dropped rows.

    ``dropped`` counts the rows left out while reading, per reason of :data:`DROP_REASONS`
    (``nonfinite``, ``range_nonpositive``, ``range_above_max``; zero counts omitted);
    ``n_dropped_nonfinite`` is its ``nonfinite`` entry (kept as a field for compatibility: it
    wins over ``dropped["nonfinite"]``) and :attr:`n_dropped` the total.
    """

    range_m: np.ndarray  # float64 (n,) raw range, m
    phi_rad: np.ndarray  # float64 (n,) raw horizontal angle, rad
    theta_rad: np.ndarray  # float64 (n,) raw vertical angle, rad
    intensity: np.ndarray  # float32 (n,) 0..1
    time_s: np.ndarray  # float64 (n,) s since the start of the scan
    row: np.ndarray  # int64 (n,) original row index in the file
    n_dropped_nonfinite: int = 0
    dropped: dict = field(default_factory=dict)

    def __post_init__(self):
        d = {k: int(v) for k, v in (self.dropped or {}).items() if k != "nonfinite" and v}
        self.n_dropped_nonfinite = int(self.n_dropped_nonfinite)
        if self.n_dropped_nonfinite:
            d = {"nonfinite": self.n_dropped_nonfinite, **d}
        self.dropped = d
        for name, dtype in (("range_m", np.float64), ("phi_rad", np.float64),
                            ("theta_rad", np.float64), ("intensity", np.float32),
                            ("time_s", np.float64), ("row", np.int64)):
            setattr(self, name, np.asarray(getattr(self, name), dtype=dtype).reshape(-1))
        n = {len(getattr(self, c)) for c in (*COLUMNS, "row")}
        if len(n) != 1:
            raise ValueError(f"ScanData columns differ in length: {sorted(n)}")

    def __len__(self):
        return len(self.range_m)

    @property
    def n_dropped(self) -> int:
        """Rows of the file dropped while reading, all reasons together."""
        return int(sum(self.dropped.values()))

    def _rows(self, each) -> ScanData:
        """``each`` applied to every column (``row`` too), the drop counts kept."""
        return ScanData(*(each(getattr(self, c)) for c in (*COLUMNS, "row")),
                        n_dropped_nonfinite=self.n_dropped_nonfinite, dropped=dict(self.dropped))

    def subset(self, mask_or_index) -> ScanData:
        """The rows selected by a boolean mask or an index array (keeps `row`)."""
        sel = np.asarray(mask_or_index)
        return self._rows((lambda a: a[sel]) if sel.dtype == bool  # np.take: 2-3x the speed
                          else (lambda a: np.take(a, sel, axis=0)))  # of fancy indexing

    def padded(self, n_pad: int) -> ScanData:
        """These rows followed by copies of the first up to ``n_pad`` rows (none if ``n_pad``
        is not more): the padding of a size bucket (the caller gives the copies weight 0)."""
        extra = n_pad - len(self)
        if extra <= 0:
            return self
        return self._rows(lambda a: np.concatenate([a, np.repeat(a[:1], extra, axis=0)]))


def _sum_dropped(chunks: Sequence[ScanData]) -> dict[str, int]:
    out: dict[str, int] = {}
    for c in chunks:
        for k, v in c.dropped.items():
            out[k] = out.get(k, 0) + int(v)
    return out


def minimum_points(n_free: int) -> int:
    """Usable observations a scan needs for a model with ``n_free`` free parameters:
    :data:`POINTS_PER_PARAMETER` (50) per free parameter (at least one parameter counted).

    The one rule of the project: ``fit`` and ``diagnose`` refuse a scan named alone that has
    fewer (:func:`require_points`); inside a campaign such a scan is left out of every
    average with a note.
    """
    return POINTS_PER_PARAMETER * max(1, int(n_free))


def require_points(n_points: int, n_free: int, *, file, scan_id: str, what: str = "the model"
                   ) -> None:
    """Raise :class:`CampaignError` naming the scan when ``n_points < minimum_points(n_free)``."""
    need = minimum_points(n_free)
    if int(n_points) < need:
        raise CampaignError(file, "points", f"scan {scan_id!r} has {int(n_points)} usable "
                            f"points, expected at least {need} for {what} ({n_free} free "
                            f"parameters, {POINTS_PER_PARAMETER} points each)")


def _concat(chunks: Sequence[ScanData]) -> ScanData:
    if len(chunks) == 1:
        return chunks[0]
    if not chunks:
        return ScanData(*(np.empty(0) for _ in range(6)))
    return ScanData(*(np.concatenate([getattr(c, k) for c in chunks]) for k in (*COLUMNS, "row")),
                    n_dropped_nonfinite=sum(c.n_dropped_nonfinite for c in chunks),
                    dropped=_sum_dropped(chunks))


def cartesian_to_raw(xyz: np.ndarray, cycle: int) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    """Raw two-face ``(r, phi, theta)`` of scanner-frame points, per the spec's face rule.

    A direction of azimuth ``a = atan2(x, y)`` in [0, 2 pi) is recorded in face 1 as
    ``(a, theta0)`` when ``a`` lies in the cycle's phi range (cycle 1: [0, pi), cycle 2:
    [pi, 2 pi)), else in face 2 as ``(a - pi mod 2 pi, 2 pi - theta0)``. Cycle 0 (one-face
    exports) always uses face 1 with phi in [0, 2 pi).
    """
    xyz = np.asarray(xyz, dtype=float)
    x, y, z = xyz[..., 0], xyz[..., 1], xyz[..., 2]
    r = np.sqrt(x * x + y * y + z * z)
    a = np.mod(np.arctan2(x, y), 2 * np.pi)
    theta0 = np.arccos(np.clip(z / np.where(r > 0, r, 1.0), -1.0, 1.0))
    if cycle == 0:
        return r, a, theta0
    lo = 0.0 if cycle == 1 else np.pi
    face1 = (a >= lo) & (a < lo + np.pi)
    phi = np.where(face1, a, np.mod(a - np.pi, 2 * np.pi))
    theta = np.where(face1, theta0, 2 * np.pi - theta0)
    # guard against round-off putting phi on the wrong side of the cycle boundary
    phi = np.where(phi >= lo + np.pi, np.nextafter(lo + np.pi, lo), phi)
    phi = np.where(phi < lo, lo, phi)
    return r, phi, theta


def _check_angles(path, cycle: int, phi: np.ndarray, theta: np.ndarray, row: np.ndarray):
    """Raise if any angle lies outside the cycle's range (tolerance `ANGLE_TOL_RAD`)."""
    lo, hi = PHI_RANGE[cycle]
    t_hi, t_text = (math.pi, "(0, pi)") if cycle == 0 else (2 * math.pi, "[0, 2 pi)")
    for name, v, lo_, hi_, text in (("phi_rad", phi, lo, hi, _RANGE_TEXT[cycle]),
                                    ("theta_rad", theta, 0.0, t_hi, t_text)):
        bad = (v < lo_ - ANGLE_TOL_RAD) | (v >= hi_ + ANGLE_TOL_RAD)
        if bad.any():
            i = int(np.argmax(bad))
            raise CampaignError(path, name, f"expected values in {text} rad for cycle {cycle} "
                                f"(tolerance {ANGLE_TOL_RAD:g} rad), found {int(bad.sum())} rows "
                                f"outside, first at row {int(row[i])}: {float(v[i])!r}")


def _first_line(e: BaseException) -> str:
    return (str(e).strip().splitlines() or [type(e).__name__])[0][:200]
