"""The measurement plan of the HartRAO campaign (April 2024) as data.

The paper (sect. 2.2, fig. 3): four scanning tours -- red, green, blue, magenta -- on four
consecutive nights from 6 pm to 11 pm local time (SAST = UTC+2, i.e. 16:00-21:00 UTC), 19 to 24
positions each, 88 in all; every position is a combination of hour angle and declination inside
the mount's limits, and the zenith (HA 0, DEC = latitude) is captured twice in every tour.
Every position is scanned in two cycles of about 3 minutes each (0.63 mrad step), with time
for the move of the telescope, the brake and the scan set-up in between.

The exact positions of fig. 3 are not tabulated in the paper; the tables below are a plausible
plan that keeps the two positions the paper names (``r5`` = HA 35 deg, DEC -25.89 deg and
``r23`` = HA -35 deg, DEC -64 deg) and covers the working range (HA within +-88 deg, DEC -89 ..
+45 deg, elevation at least :data:`MIN_ELEVATION_DEG`): red the east-west band through the zenith
and the southern sky, green the northern sky, blue the south-east/south-west and the pole,
magenta the diagonals in between. Each tour alone spans a wide range of gravity directions, so
every night can calibrate the scanner by itself.

Start times follow from a simple timing model (slew at :data:`SLEW_DEG_S` per axis, settling,
scan set-up, two scans); the air temperature falls exponentially through the night (about 19 C
at 18:00 to 12 C at 23:00 local, a different level each night).

Units: degrees for angles (``_deg``), seconds or minutes as named, Celsius.
"""

from __future__ import annotations

import datetime as dt
import math
from collections.abc import Iterable, Sequence
from dataclasses import asdict, dataclass

LATITUDE_DEG = -25.8897  # HartRAO
LAT = LATITUDE_DEG
HA_LIMIT_DEG = 88.0
DEC_LIMITS_DEG = (-89.0, 45.0)
MIN_ELEVATION_DEG = 10.0

SCAN_S = 180.0  # one cycle at 0.63 mrad (paper: "around 3 minutes per scan")
CYCLE_SETUP_S = 60.0  # between the two cycles: set the horizontal angle range again
SETTLE_S = 240.0  # after a move: brake, settle, check the gimbal, set the scan parameters
SLEW_DEG_S = 0.5  # per axis, both axes move at once
UTC_OFFSET_H = 2  # SAST
TOURS = ("red", "green", "blue", "magenta")
TOUR_PREFIX = {"red": "r", "green": "g", "blue": "b", "magenta": "m"}

# (HA deg, DEC deg) in the order they are visited; the zenith twice per tour.
_Z = (0.0, LAT)
TOUR_POSITIONS: dict[str, tuple[tuple[float, float], ...]] = {
    # east-west band through the zenith, the DEC -45 row and the southern sky (DEC -64 ... -80)
    "red": (
        _Z, (15.0, LAT), (15.0, -45.0), (35.0, -45.0), (35.0, LAT), (55.0, LAT), (55.0, -45.0),
        (75.0, -45.0), (75.0, LAT), (80.0, -10.0), (35.0, -64.0), _Z, (-15.0, LAT),
        (-15.0, -45.0), (-35.0, -45.0), (-35.0, LAT), (-55.0, LAT), (-55.0, -45.0),
        (-75.0, -45.0), (-80.0, -10.0), (-75.0, -80.0), (-60.0, -64.0), (-35.0, -64.0),
    ),
    # the northern sky: meridian to DEC +45, then east and west of it
    "green": (
        _Z, (0.0, -10.0), (0.0, 10.0), (0.0, 30.0), (0.0, 45.0), (20.0, 45.0), (20.0, 25.0),
        (20.0, 5.0), (40.0, 5.0), (40.0, 30.0), _Z, (60.0, 10.0), (70.0, -10.0), (-20.0, 5.0),
        (-20.0, 25.0), (-20.0, 45.0), (-40.0, 30.0), (-40.0, 5.0), (-60.0, 10.0),
        (-70.0, -10.0), (-50.0, -10.0), (-10.0, -10.0),
    ),
    # south-east, the pole, south-west, and the eastern horizon
    "blue": (
        _Z, (10.0, -40.0), (25.0, -55.0), (45.0, -60.0), (65.0, -55.0), (85.0, -50.0),
        (85.0, -75.0), (50.0, -80.0), (0.0, -89.0), (0.0, -55.0), _Z, (-10.0, -40.0),
        (-25.0, -55.0), (-45.0, -60.0), (-65.0, -55.0), (-85.0, -50.0), (-85.0, -75.0),
        (-50.0, -80.0), (-20.0, -85.0), (30.0, -30.0), (60.0, -30.0), (88.0, -30.0),
    ),
    # the diagonals between the other tours, both sides of the meridian
    "magenta": (
        _Z, (30.0, -20.0), (50.0, -35.0), (70.0, -40.0), (88.0, -65.0), (70.0, -85.0),
        (30.0, -75.0), (10.0, -64.0), (45.0, 15.0), (45.0, 35.0), _Z, (-30.0, -20.0),
        (-50.0, -35.0), (-70.0, -40.0), (-88.0, -65.0), (-70.0, -85.0), (-30.0, -75.0),
        (-10.0, -64.0), (-45.0, 15.0), (-45.0, 35.0), (0.0, 20.0),
    ),
}
NIGHTS: dict[str, dt.date] = {
    "red": dt.date(2024, 4, 8), "green": dt.date(2024, 4, 9), "blue": dt.date(2024, 4, 10),
    "magenta": dt.date(2024, 4, 11),
}
# air temperature at the start (18:00 local) and end (23:00 local) of each night, C
NIGHT_TEMPERATURE_C: dict[str, tuple[float, float]] = {
    "red": (19.0, 12.0), "green": (20.0, 13.5), "blue": (18.0, 11.0), "magenta": (19.5, 12.5),
}
COOLING_TIME_H = 2.5  # e-folding time of the night-time cooling


@dataclass(frozen=True)
class PlannedPosition:
    """One telescope position of the plan: pointing, tour, times (UTC) and temperatures."""

    position: str
    tour: str
    index: int  # 1-based within the tour
    ha_deg: float
    dec_deg: float
    elevation_deg: float
    zenith: bool
    start_c1: dt.datetime
    start_c2: dt.datetime
    temperature_c1: float
    temperature_c2: float

    def as_dict(self) -> dict:
        d = asdict(self)
        d["start_c1"] = self.start_c1.isoformat().replace("+00:00", "Z")
        d["start_c2"] = self.start_c2.isoformat().replace("+00:00", "Z")
        return d

    def simulator_position(self) -> dict:
        """The position in the form :func:`hartrao_jax.simulate.simulate_campaign` takes."""
        return {"position": self.position, "ha_deg": self.ha_deg, "dec_deg": self.dec_deg,
                "tour": self.tour, "temperature_c": self.temperature_c1,
                "start": {1: self.start_c1, 2: self.start_c2},
                "temperature": {1: self.temperature_c1, 2: self.temperature_c2}}


def elevation_deg(ha_deg: float, dec_deg: float, latitude_deg: float = LATITUDE_DEG) -> float:
    """Elevation (deg) of the boresight of an HA-DEC mount (spherical astronomy)."""
    h, d, p = (math.radians(a) for a in (ha_deg, dec_deg, latitude_deg))
    s = math.sin(p) * math.sin(d) + math.cos(p) * math.cos(d) * math.cos(h)
    return math.degrees(math.asin(max(-1.0, min(1.0, s))))


def within_limits(ha_deg: float, dec_deg: float, *, min_elevation_deg: float = MIN_ELEVATION_DEG
                  ) -> bool:
    """True if a pointing is inside the mount's limits and high enough to scan."""
    return (abs(ha_deg) <= HA_LIMIT_DEG and DEC_LIMITS_DEG[0] <= dec_deg <= DEC_LIMITS_DEG[1]
            and elevation_deg(ha_deg, dec_deg) >= min_elevation_deg)


def night_temperature_c(tour: str, t: dt.datetime) -> float:
    """Air temperature (C) of the night of ``tour`` at UTC time ``t`` (exponential cooling)."""
    t0 = dt.datetime.combine(NIGHTS[tour], dt.time(18 - UTC_OFFSET_H), tzinfo=dt.UTC)
    T0, T1 = NIGHT_TEMPERATURE_C[tour]
    hours = (t - t0).total_seconds() / 3600.0
    k = 1.0 / COOLING_TIME_H
    frac = (1.0 - math.exp(-k * hours)) / (1.0 - math.exp(-k * 5.0))
    return round(T0 + (T1 - T0) * frac, 2)


def _slew_s(a: tuple[float, float], b: tuple[float, float]) -> float:
    return max(abs(a[0] - b[0]), abs(a[1] - b[1])) / SLEW_DEG_S


def tour_plan(tour: str) -> list[PlannedPosition]:
    """The positions of one tour in visiting order, with start times and temperatures."""
    if tour not in TOUR_POSITIONS:
        raise ValueError(f"unknown tour {tour!r}; known: {', '.join(TOURS)}")
    t = dt.datetime.combine(NIGHTS[tour], dt.time(18 - UTC_OFFSET_H), tzinfo=dt.UTC)
    prev = (0.0, LATITUDE_DEG)  # the telescope waits at the zenith (scanner mounted)
    out = []
    for i, (ha, dec) in enumerate(TOUR_POSITIONS[tour], start=1):
        t = t + dt.timedelta(seconds=_slew_s(prev, (ha, dec)) + SETTLE_S)
        t1 = t
        t2 = t1 + dt.timedelta(seconds=SCAN_S + CYCLE_SETUP_S)
        t = t2 + dt.timedelta(seconds=SCAN_S)
        t1, t2 = (x.replace(second=0, microsecond=0) for x in (t1, t2))
        out.append(PlannedPosition(
            f"{TOUR_PREFIX[tour]}{i}", tour, i, ha, dec, round(elevation_deg(ha, dec), 3),
            (ha, dec) == _Z, t1, t2, night_temperature_c(tour, t1), night_temperature_c(tour, t2)))
        prev = (ha, dec)
    return out


def campaign_plan(tours: Iterable[str] = TOURS) -> list[PlannedPosition]:
    """All positions of the given tours (default: the four, 88 positions)."""
    return [p for tour in tours for p in tour_plan(tour)]


def plan_positions(tours: Iterable[str] = TOURS) -> list[dict]:
    """The plan in the ``positions`` form of ``simulate_campaign`` (dicts)."""
    return [p.simulator_position() for p in campaign_plan(tours)]


def find_position(name: str) -> PlannedPosition:
    for p in campaign_plan():
        if p.position == name:
            return p
    raise KeyError(name)


def check_plan(plan: Sequence[PlannedPosition] | None = None) -> list[str]:
    """Problems of a plan (empty if it satisfies the paper's constraints)."""
    plan = list(plan if plan is not None else campaign_plan())
    msgs = []
    by_tour: dict[str, list[PlannedPosition]] = {}
    for p in plan:
        by_tour.setdefault(p.tour, []).append(p)
        if not within_limits(p.ha_deg, p.dec_deg):
            msgs.append(f"{p.position}: HA {p.ha_deg}, DEC {p.dec_deg} outside the limits "
                        f"(elevation {p.elevation_deg:.1f} deg)")
    for tour, ps in by_tour.items():
        if not 19 <= len(ps) <= 24:
            msgs.append(f"tour {tour}: {len(ps)} positions, expected 19 to 24")
        if sum(p.zenith for p in ps) != 2:
            msgs.append(f"tour {tour}: the zenith is captured {sum(p.zenith for p in ps)} times")
        local = [(p.start_c1.hour + UTC_OFFSET_H, p.start_c2 + dt.timedelta(seconds=SCAN_S))
                 for p in ps]
        end = local[-1][1]
        if local[0][0] < 18 or end.hour + UTC_OFFSET_H + end.minute / 60 > 23.0:
            msgs.append(f"tour {tour}: not within 18:00-23:00 local time")
    return msgs


def plan_table(plan: Sequence[PlannedPosition] | None = None) -> str:
    """The plan as a Markdown table."""
    plan = list(plan if plan is not None else campaign_plan())
    rows = ["| position | tour | HA [deg] | DEC [deg] | elevation [deg] | start c1 (UTC) | "
            "start c2 (UTC) | T [C] |", "|---|---|---:|---:|---:|---|---|---:|"]
    for p in plan:
        rows.append(f"| {p.position}{' (zenith)' if p.zenith else ''} | {p.tour} | "
                    f"{p.ha_deg:.1f} | {p.dec_deg:.2f} | {p.elevation_deg:.1f} | "
                    f"{p.start_c1:%Y-%m-%d %H:%M} | {p.start_c2:%H:%M} | {p.temperature_c1:.1f} |")
    return "\n".join(rows)


# Simulation presets built on the plan (resolution a laptop can process; --step overrides)
CAMPAIGN_STEP_RAD = 0.02
PRESET_TOURS: dict[str, tuple[str, ...]] = {"campaign": TOURS, "tour-red": ("red",)}


__all__ = [
    "CAMPAIGN_STEP_RAD", "DEC_LIMITS_DEG", "HA_LIMIT_DEG", "LATITUDE_DEG", "MIN_ELEVATION_DEG",
    "NIGHTS", "PRESET_TOURS", "PlannedPosition", "TOURS", "TOUR_POSITIONS", "campaign_plan",
    "check_plan", "elevation_deg", "find_position", "night_temperature_c", "plan_positions",
    "plan_table", "tour_plan", "within_limits",
]
