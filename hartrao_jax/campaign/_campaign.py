"""Campaign I/O: `campaign.toml` and its scan tables (Parquet, E57), as `campaign-format.md` says.

Reading validates everything and turns each bad input into a one-line `CampaignError`
``'<file>: <field>: <what was expected, what was found>'``. Input files are never modified.
Angles are radians, lengths metres, times seconds.
"""

from __future__ import annotations

import dataclasses
import datetime as dt
import logging
import math
import os
import pathlib
import re
import tomllib
from collections.abc import Iterator, Mapping, Sequence
from typing import Any

import numpy as np

from ._e57 import iter_e57_columns, write_e57
from ._format import (  # noqa: F401  (re-exported: the campaign API)
    _RANGE_TEXT,
    ANGLE_TOL_RAD,
    COLUMNS,
    DEFAULT_INTENSITY,
    DROP_REASONS,
    FORMAT,
    MAX_RANGE_M,
    PHI_RANGE,
    POINTS_PER_PARAMETER,
    Campaign,
    CampaignError,
    ScanData,
    ScanMeta,
    Scanner,
    Site,
    Telescope,
    _check_angles,
    _concat,
    _first_line,
    _sum_dropped,
    _tuple,
    cartesian_to_raw,
    minimum_points,
    require_points,
)
from ._safeio import write_table

log = logging.getLogger(__name__)



# ----------------------------------------------------------------------------- TOML reading


def _kind(v) -> str:
    """TOML type name of a parsed value, for messages."""
    for t, name in ((bool, "boolean"), (int, "integer"), (float, "float"), (str, "string"),
                    (dt.datetime, "date-time"), (dt.date, "date"), (dt.time, "time"),
                    (list, "array"), (dict, "table")):
        if isinstance(v, t):
            return name
    return type(v).__name__


def _found(v) -> str:
    text = repr(v) if isinstance(v, (str, int, float)) else str(v)
    return f"found {_kind(v)} {text[:60]}"


def _is_number(v) -> bool:
    return isinstance(v, (int, float)) and not isinstance(v, bool)


class _Table:
    """One TOML table with its file and dotted prefix, for typed, checked access."""

    def __init__(self, file, prefix: str, data, note: str = ""):
        self.file, self.prefix, self.note = file, prefix, note
        if not isinstance(data, dict):
            raise CampaignError(file, prefix, f"expected a table, {_found(data)}")
        self.data = data

    def error(self, key: str, message: str) -> CampaignError:
        return CampaignError(self.file, f"{self.prefix}.{key}" if self.prefix else key,
                             message + self.note)

    def get(self, key: str, check, expected: str, required: bool = True, default=None):
        if key not in self.data:
            if required:
                raise self.error(key, f"required key is missing (expected {expected})")
            return default
        v = self.data[key]
        ok, value = check(v)
        if not ok:
            raise self.error(key, f"expected {expected}, {_found(v)}")
        return value

    def number(self, key, required=True, lo=-math.inf, hi=math.inf, unit=""):
        expected = "a number" + (f" in {unit}" if unit else "")
        v = self.get(key, lambda v: (_is_number(v), float(v) if _is_number(v) else v),
                     expected, required)
        if v is not None and not (lo <= v <= hi and math.isfinite(v)):
            raise self.error(key, f"expected a finite number in [{lo:g}, {hi:g}], found {v!r}")
        return v

    def positive(self, key, unit):
        v = self.number(key, unit=unit)
        if v <= 0:
            raise self.error(key, f"expected a positive number in {unit}, found {v!r}")
        return v

    def string(self, key, required=True, default=None):
        return self.get(key, lambda v: (isinstance(v, str), v), "a string", required, default)

    def array(self, key, integer=False, required=False):
        is_int = lambda x: isinstance(x, int) and not isinstance(x, bool)
        ok_item = is_int if integer else _is_number
        conv = int if integer else float
        expected = "an array of integers" if integer else "an array of numbers"
        return self.get(key, lambda v: (isinstance(v, list) and all(map(ok_item, v)),
                                        tuple(conv(x) for x in v) if isinstance(v, list) else v),
                        expected, required)

    def extra(self, known: Sequence[str]) -> dict:
        return {k: v for k, v in self.data.items() if k not in known}


_SITE_KEYS = ("name", "latitude_deg", "longitude_deg")
_TELESCOPE_KEYS = ("name", "mount", "diameter_m", "focal_length_m", "cone_radius_m",
                   "quadrupod_azimuths_deg", "ring_edges_m", "panels_per_ring", "offset_m")
_SCANNER_KEYS = ("sigma_range_m", "sigma_angle_rad", "angular_step_rad", "max_range_m")
_SCAN_KEYS = ("id", "position", "tour", "ha_deg", "dec_deg", "elevation_deg", "azimuth_deg",
              "cycle", "file", "start", "temperature_c")
_TOP_KEYS = ("format", "site", "telescope", "scanner", "scan")


def _site(t: _Table) -> Site:
    return Site(name=t.string("name", required=False, default=""),
                latitude_deg=t.number("latitude_deg", lo=-90, hi=90, unit="degrees"),
                longitude_deg=t.number("longitude_deg", required=False, lo=-360, hi=360),
                extra=t.extra(_SITE_KEYS))


def _telescope(t: _Table) -> Telescope:
    mount = t.string("mount")
    if mount not in ("ha-dec", "alt-az"):
        raise t.error("mount", f'expected "ha-dec" or "alt-az", found {mount!r}')
    edges, panels = t.array("ring_edges_m"), t.array("panels_per_ring", integer=True)
    if (edges is None) != (panels is None):
        missing = "ring_edges_m" if edges is None else "panels_per_ring"
        raise t.error(missing, "required when "
                      f"{'panels_per_ring' if edges is None else 'ring_edges_m'} is given "
                      "(panel keys come together or not at all)")
    if edges is not None:
        if len(edges) < 2 or any(b <= a for a, b in zip(edges, edges[1:])):
            raise t.error("ring_edges_m", f"expected at least 2 strictly increasing radii in m, "
                          f"found {list(edges)}")
        if len(panels) != len(edges) - 1:
            raise t.error("panels_per_ring", f"expected len(ring_edges_m) - 1 = {len(edges) - 1} "
                          f"entries (one per ring), found {len(panels)}")
        if any(p < 1 for p in panels):
            raise t.error("panels_per_ring", f"expected positive integers, found {list(panels)}")
    return Telescope(
        name=t.string("name", required=False, default=""), mount=mount,
        diameter_m=t.positive("diameter_m", "m"), focal_length_m=t.positive("focal_length_m", "m"),
        cone_radius_m=t.number("cone_radius_m", lo=0, unit="m"),
        quadrupod_azimuths_deg=t.array("quadrupod_azimuths_deg"),
        ring_edges_m=edges, panels_per_ring=panels,
        offset_m=t.number("offset_m", required=False, unit="m") or 0.0,
        extra=t.extra(_TELESCOPE_KEYS))


def _scanner(t: _Table) -> Scanner:
    return Scanner(sigma_range_m=t.positive("sigma_range_m", "m"),
                   sigma_angle_rad=t.positive("sigma_angle_rad", "rad"),
                   angular_step_rad=t.positive("angular_step_rad", "rad"),
                   max_range_m=(t.positive("max_range_m", "m") if "max_range_m" in t.data
                                else None),
                   extra=t.extra(_SCANNER_KEYS))


def _scan(t: _Table, mount: str, root: pathlib.Path) -> ScanMeta:
    sid = t.string("id")
    if not sid:
        raise t.error("id", "expected a non-empty string, found an empty one")
    t.note = f" (scan {sid!r})"
    cycle = t.get("cycle", lambda v: (type(v) is int and v in (0, 1, 2), v),
                  "0, 1 or 2 (1: phi in [0, pi), 2: phi in [pi, 2 pi), 0: one-face export)")
    need = ("ha_deg", "dec_deg") if mount == "ha-dec" else ("elevation_deg", "azimuth_deg")
    lims = {"dec_deg": (-90, 90), "elevation_deg": (-90, 90)}
    ang = {k: t.number(k, required=k in need, lo=lims.get(k, (-720, 720))[0],
                       hi=lims.get(k, (-720, 720))[1], unit="degrees")
           for k in ("ha_deg", "dec_deg", "elevation_deg", "azimuth_deg")}
    start = t.get("start", lambda v: (isinstance(v, dt.datetime), v),
                  "an offset date-time such as 2024-04-08T18:42:00Z", required=False)
    file = t.string("file")
    if pathlib.PurePath(file).suffix.lower() not in (".parquet", ".e57"):
        raise t.error("file", f"expected a .parquet or .e57 file, found {file!r}")
    if not (root / file).is_file():
        raise t.error("file", f"expected an existing scan file, {str(root / file)!r} not found")
    return ScanMeta(id=sid, position=t.string("position"), cycle=cycle, file=file, **ang,
                    tour=t.string("tour", required=False), start=start,
                    temperature_c=t.number("temperature_c", required=False, lo=-100, hi=100),
                    extra=t.extra(_SCAN_KEYS))


def load_campaign(path) -> Campaign:
    """Read and validate `campaign.toml` (path: the campaign directory or the TOML file itself).

    Checks everything that needs no scan data, including that every scan file exists.
    """
    p = pathlib.Path(path)
    toml_path = p / "campaign.toml" if p.is_dir() else p
    if not toml_path.is_file():
        raise CampaignError(toml_path, "file", "expected a campaign directory or its "
                            "campaign.toml, not found")
    try:
        doc = tomllib.loads(toml_path.read_bytes().decode("utf-8"))
    except (tomllib.TOMLDecodeError, UnicodeDecodeError) as e:
        raise CampaignError(toml_path, "toml", f"expected valid UTF-8 TOML, {e}") from None
    top = _Table(toml_path, "", doc)
    fmt = top.string("format")
    if fmt != FORMAT:
        raise top.error("format", f"expected {FORMAT!r}, found {fmt!r}")
    sub = {k: _Table(toml_path, k, top.get(k, lambda v: (True, v), "a table")) for k in
           ("site", "telescope", "scanner")}
    site, telescope, scanner = _site(sub["site"]), _telescope(sub["telescope"]), \
        _scanner(sub["scanner"])
    raw_scans = top.get("scan", lambda v: (isinstance(v, list) and len(v) > 0, v),
                        "at least one [[scan]] table")
    scans, seen = [], {}
    for i, s in enumerate(raw_scans):
        meta = _scan(_Table(toml_path, f"scan[{i}]", s), telescope.mount, toml_path.parent)
        if meta.id in seen:
            raise CampaignError(toml_path, f"scan[{i}].id", f"expected unique scan ids, "
                                f"{meta.id!r} is also the id of scan[{seen[meta.id]}]")
        seen[meta.id] = i
        scans.append(meta)
    return Campaign(root=toml_path.parent, site=site, telescope=telescope, scanner=scanner,
                    scans=tuple(scans), extra=top.extra(_TOP_KEYS))


# ----------------------------------------------------------------------------- TOML writing


def _toml_str(s: str) -> str:
    """A TOML basic string with every needed escape."""
    esc = {'"': '\\"', "\\": "\\\\", "\b": "\\b", "\t": "\\t", "\n": "\\n", "\f": "\\f",
           "\r": "\\r"}
    out = (esc.get(c) or (f"\\u{ord(c):04x}" if ord(c) < 0x20 or ord(c) == 0x7F else c)
           for c in s)
    return '"' + "".join(out) + '"'


def _toml_key(k: str) -> str:
    return k if re.fullmatch(r"[A-Za-z0-9_-]+", k) else _toml_str(k)


def _toml_value(v) -> str:
    """One TOML value, inline (arrays and tables included)."""
    if isinstance(v, (bool, np.bool_)):
        return "true" if v else "false"
    if isinstance(v, (int, np.integer)):
        return str(int(v))
    if isinstance(v, (float, np.floating)):
        return repr(float(v))
    if isinstance(v, str):
        return _toml_str(v)
    if isinstance(v, dt.datetime):
        s = v.isoformat()
        return s[:-6] + "Z" if v.utcoffset() == dt.timedelta(0) else s
    if isinstance(v, (dt.date, dt.time)):
        return v.isoformat()
    if isinstance(v, (list, tuple, np.ndarray)):
        return "[" + ", ".join(_toml_value(x) for x in v) + "]"
    if isinstance(v, Mapping):
        return "{" + ", ".join(f"{_toml_key(k)} = {_toml_value(x)}" for k, x in v.items()) + "}"
    raise TypeError(f"cannot write {type(v).__name__} to TOML: {v!r}")


def _is_table_array(v) -> bool:
    return isinstance(v, (list, tuple)) and len(v) > 0 and all(isinstance(x, Mapping) for x in v)


def _toml_table(lines: list[str], path: list[str], d: Mapping, array: bool = False):
    """Append a table: its header, its plain keys, then its sub-tables and arrays of tables."""
    if path:
        name = ".".join(_toml_key(k) for k in path)
        lines += ["", f"[[{name}]]" if array else f"[{name}]"]
    for k, v in d.items():
        if v is not None and not isinstance(v, Mapping) and not _is_table_array(v):
            lines.append(f"{_toml_key(k)} = {_toml_value(v)}")
    for k, v in d.items():
        if isinstance(v, Mapping):
            _toml_table(lines, [*path, k], v)
        elif _is_table_array(v):
            for x in v:
                _toml_table(lines, [*path, k], x, array=True)


def _as_dict(obj, keys: Sequence[str]) -> dict:
    return {**{k: getattr(obj, k) for k in keys if getattr(obj, k) is not None}, **obj.extra}


def campaign_to_toml(campaign: Campaign) -> str:
    """The `campaign.toml` text of a campaign (unknown keys kept, None values left out)."""
    doc: dict[str, Any] = {"format": FORMAT,
                           "site": _as_dict(campaign.site, _SITE_KEYS),
                           "telescope": _as_dict(campaign.telescope, _TELESCOPE_KEYS),
                           "scanner": _as_dict(campaign.scanner, _SCANNER_KEYS),
                           **campaign.extra,
                           "scan": [_as_dict(s, _SCAN_KEYS) for s in campaign.scans]}
    return dumps_toml(doc)


def dumps_toml(doc: Mapping) -> str:
    """TOML text of a document (tables as [headers], lists of tables as [[headers]])."""
    lines: list[str] = []
    _toml_table(lines, [], doc)
    return "\n".join(lines).lstrip("\n") + "\n"


def write_campaign(root, campaign_like: Campaign, scans: Mapping[str, ScanData], *,
                   fmt: str = "parquet", before_toml=None) -> Campaign:
    """Write `campaign.toml` and `scans/<id>.<fmt>` under `root`; return the loaded campaign.

    `campaign_like.root` and its scans' `file` are ignored (files become `scans/<id>.<ext>`).
    Crash-safe: a previous `campaign.toml` is removed first, every scan file is written to a
    temporary name and renamed, `before_toml()` (optional: other files of the campaign, such
    as a simulator's truth) runs next, and `campaign.toml` is written last, so an interrupted
    write never leaves a campaign.toml beside scans it does not describe.
    """
    if fmt not in ("parquet", "e57"):
        raise ValueError(f"fmt must be 'parquet' or 'e57', not {fmt!r}")
    root = pathlib.Path(root)
    (root / "scans").mkdir(parents=True, exist_ok=True)
    if (root / "campaign.toml").is_file():
        (root / "campaign.toml").unlink()
    metas = []
    for meta in campaign_like.scans:
        if not re.fullmatch(r"[A-Za-z0-9_][A-Za-z0-9._-]*", meta.id):
            raise ValueError(f"scan id {meta.id!r} cannot be a file name: use letters, digits, "
                             "'.', '_' and '-'")
        if meta.id not in scans:
            raise ValueError(f"no ScanData given for scan {meta.id!r}")
        file = f"scans/{meta.id}.{fmt}"
        if fmt == "parquet":
            write_scan_parquet(root / file, scans[meta.id])
        else:
            write_scan_e57(root / file, scans[meta.id], meta.cycle)
        metas.append(dataclasses.replace(meta, file=file))
    text = campaign_to_toml(dataclasses.replace(campaign_like, root=root, scans=tuple(metas)))
    if before_toml is not None:
        before_toml()
    tmp = root / "campaign.toml.tmp"
    tmp.write_text(text, encoding="utf-8")
    os.replace(tmp, root / "campaign.toml")
    return load_campaign(root)


def default_campaign(scans: Sequence[ScanMeta] = (), root=".", **extra) -> Campaign:
    """A campaign with the HartRAO 26-m defaults of `campaign-format.md` and the given scans."""
    return Campaign(
        root=pathlib.Path(root),
        site=Site("Hartebeesthoek", -25.8897, 27.6853),
        telescope=Telescope(
            name="HartRAO 26-m", mount="ha-dec", diameter_m=25.9, focal_length_m=10.9816,
            cone_radius_m=1.6, quadrupod_azimuths_deg=(45.0, 135.0, 225.0, 315.0),
            ring_edges_m=(1.6, 3.2, 4.8, 6.4, 8.0, 9.6, 11.2, 12.95),
            panels_per_ring=(15, 24, 30, 36, 42, 48, 60)),
        scanner=Scanner(sigma_range_m=0.0008, sigma_angle_rad=2.0e-5, angular_step_rad=0.003),
        scans=tuple(scans), extra=dict(extra))


# ----------------------------------------------------------------------------- scan tables






def _finish(path, cols: dict[str, np.ndarray], cycle: int, row0: int,
            max_range_m: float = MAX_RANGE_M, stats: dict | None = None) -> ScanData:
    """Drop (and count per reason) rows with a non-finite value or a range outside
    (0, max_range_m], check the angles, and build a ScanData. ``stats`` (optional) collects
    the non-finite count of each column, for messages."""
    n = len(cols["range_m"])
    finite = np.ones(n, dtype=bool)
    for c in COLUMNS:
        ok = np.isfinite(cols[c])
        if stats is not None:
            stats[c] = stats.get(c, 0) + int(n - ok.sum())
        finite &= ok
    r = cols["range_m"]
    with np.errstate(invalid="ignore"):
        nonpos = finite & (r <= 0)
        above = finite & (r > max_range_m)
    keep = finite & ~nonpos & ~above
    row = np.arange(row0, row0 + n, dtype=np.int64)
    n_bad = int(n - finite.sum())
    dropped = {"range_nonpositive": int(nonpos.sum()), "range_above_max": int(above.sum())}
    if not keep.all():
        cols, row = {c: v[keep] for c, v in cols.items()}, row[keep]
    _check_angles(path, cycle, cols["phi_rad"], cols["theta_rad"], row)
    return ScanData(**{c: cols[c] for c in COLUMNS}, row=row, n_dropped_nonfinite=n_bad,
                    dropped=dropped)


def _arrow_errors():
    import pyarrow as pa

    return (pa.ArrowException, OSError, ValueError)




def _parquet_columns(path: pathlib.Path, rows_per_chunk: int | None) -> Iterator[dict]:
    """Yield the validated columns of a Parquet scan (all at once, or in chunks of rows)."""
    import pyarrow as pa
    import pyarrow.parquet as pq

    if not path.is_file():
        raise CampaignError(path, "file", "expected an existing Parquet scan file, not found")
    try:
        pf = pq.ParquetFile(path)
    except _arrow_errors() as e:
        raise CampaignError(path, "file", "expected a Parquet file, could not read it (truncated "
                            f"or not Parquet): {_first_line(e)}") from None
    with pf:
        schema = pf.schema_arrow
        names = schema.names
        for c in COLUMNS:
            if c not in names:
                if c == "intensity":
                    continue
                raise CampaignError(path, c, f"required column is missing (expected float64; "
                                    f"found columns: {', '.join(names) or 'none'})")
            typ = schema.field(c).type
            ok = pa.types.is_floating(typ) if c == "intensity" else pa.types.is_float64(typ)
            if not ok:
                want = "float32 or float64" if c == "intensity" else "float64"
                found = {"float": "float32", "double": "float64", "halffloat": "float16"}
                raise CampaignError(path, c, f"expected column type {want}, "
                                    f"found {found.get(str(typ), str(typ))}")
        have = [c for c in COLUMNS if c in names]
        if "intensity" not in names:
            log.warning("%s: no intensity column, filled with %s", path, DEFAULT_INTENSITY)
        try:
            if rows_per_chunk is None:
                batches = [pf.read(columns=have)]
            else:
                batches = pf.iter_batches(batch_size=rows_per_chunk, columns=have)
            for b in batches:
                with np.errstate(over="ignore"):  # a float64 intensity beyond float32: inf, dropped
                    cols = {c: np.asarray(b.column(c).to_numpy(), dtype=np.float64
                                          if c != "intensity" else np.float32) for c in have}
                if "intensity" not in cols:
                    cols["intensity"] = np.full(b.num_rows, DEFAULT_INTENSITY, np.float32)
                yield cols
        except _arrow_errors() as e:
            raise CampaignError(path, "file", "expected a readable Parquet file, reading failed "
                                f"(truncated or corrupt): {_first_line(e)}") from None


def _file_columns(path: pathlib.Path, cycle: int, rows_per_chunk: int | None) -> Iterator[dict]:
    suffix = path.suffix.lower()
    if suffix == ".parquet":
        return _parquet_columns(path, rows_per_chunk)
    if suffix == ".e57":
        return iter_e57_columns(path, cycle, rows_per_chunk)
    raise CampaignError(path, "file", f"expected a .parquet or .e57 file, found {suffix!r}")


def _iter_chunks(path: pathlib.Path, cycle: int, rows_per_chunk: int | None,
                 max_range_m: float = MAX_RANGE_M) -> Iterator[ScanData]:
    if rows_per_chunk is not None and int(rows_per_chunk) < 1:
        raise ValueError(f"rows_per_chunk must be a positive integer, not {rows_per_chunk!r}")
    if not (max_range_m > 0):
        raise ValueError(f"max_range_m must be positive, not {max_range_m!r}")
    row0, kept, stats = 0, 0, {}
    dropped: dict[str, int] = {}
    for cols in _file_columns(path, cycle, rows_per_chunk):
        chunk = _finish(path, cols, cycle, row0, max_range_m, stats)
        row0 += len(cols["range_m"])
        kept += len(chunk)
        for k, v in chunk.dropped.items():
            dropped[k] = dropped.get(k, 0) + v
        yield chunk
    if kept == 0:  # the error says it all (no warnings before it)
        _no_usable_rows(path, row0, dropped, stats, max_range_m)
    if dropped.get("nonfinite"):
        log.warning("%s: dropped %d rows with NaN/inf values", path, dropped["nonfinite"])
    if dropped.get("range_nonpositive"):
        log.warning("%s: dropped %d rows with range <= 0", path, dropped["range_nonpositive"])
    if dropped.get("range_above_max"):
        log.warning("%s: dropped %d rows with a range above the instrument maximum %g m", path,
                    dropped["range_above_max"], max_range_m)


def _no_usable_rows(path, n_rows: int, dropped: dict, stats: dict, max_range_m: float):
    """Raise the CampaignError of a scan without one usable row, naming the main cause."""
    if n_rows == 0:
        raise CampaignError(path, "rows", "the scan table has no rows, expected at least one "
                            "observation")
    parts = [f"{v} with {DROP_REASONS[k]}" for k, v in dropped.items() if v]
    col = max(COLUMNS, key=lambda c: stats.get(c, 0))
    if stats.get(col, 0) == n_rows:
        field_, what = col, f"all {n_rows} values are NaN, infinite or null"
    else:
        ranges = dropped.get("range_nonpositive", 0) + dropped.get("range_above_max", 0)
        field_ = "range_m" if ranges >= dropped.get("nonfinite", 0) else col
        what = f"none of the {n_rows} rows is usable ({'; '.join(parts)})"
    raise CampaignError(path, field_, f"{what}, expected at least one row with finite values "
                        f"and a range in (0, {max_range_m:g}] m")


def _scan_path(campaign: Campaign, scan: str | ScanMeta) -> tuple[pathlib.Path, ScanMeta]:
    meta = campaign.scan(scan) if isinstance(scan, str) else scan
    return campaign.root / meta.file, meta


def read_scan(campaign: Campaign, scan: str | ScanMeta) -> ScanData:
    """Read one scan (Parquet or E57 by suffix), validated, without its dropped rows
    (non-finite values, range <= 0 or above the scanner's ``max_range_m``; counted in
    ``ScanData.dropped``). A scan without one usable row raises ``CampaignError``."""
    path, meta = _scan_path(campaign, scan)
    return _concat(list(_iter_chunks(path, meta.cycle, None, campaign.scanner.range_limit_m)))


def iter_scan_chunks(campaign: Campaign, scan: str | ScanMeta,
                     rows_per_chunk: int = 2_000_000) -> Iterator[ScanData]:
    """Stream one scan as validated ScanData chunks of at most `rows_per_chunk` file rows."""
    path, meta = _scan_path(campaign, scan)
    yield from _iter_chunks(path, meta.cycle, int(rows_per_chunk),
                            campaign.scanner.range_limit_m)


def read_scan_parquet(path, cycle: int, *, max_range_m: float = MAX_RANGE_M) -> ScanData:
    """Read and validate one Parquet scan file for the given cycle."""
    return _concat(list(_iter_chunks(pathlib.Path(path), cycle, None, max_range_m)))


def read_scan_e57(path, cycle: int, *, max_range_m: float = MAX_RANGE_M) -> ScanData:
    """Read one E57 scan, converting face-1 azimuth/elevation to raw two-face angles."""
    path = pathlib.Path(path)
    if path.suffix.lower() != ".e57":
        raise CampaignError(path, "file", f"expected an .e57 file, found {path.suffix!r}")
    return _concat(list(_iter_chunks(path, cycle, None, max_range_m)))


def write_scan_parquet(path, scan: ScanData) -> None:
    """Write a scan table (float64 columns, float32 intensity); `row` is not written."""
    import pyarrow as pa

    path = pathlib.Path(path)
    table = pa.table({c: pa.array(getattr(scan, c), type=pa.float32() if c == "intensity"
                                  else pa.float64()) for c in COLUMNS})
    tmp = path.with_name(path.name + ".tmp")
    write_table(table, tmp, row_group_size=1_000_000)
    os.replace(tmp, path)


def write_scan_e57(path, scan: ScanData, cycle: int) -> None:
    """Write a scan as E57 (spherical, face-1 form, float64) with intensity and timeStamp."""

    write_e57(pathlib.Path(path), scan, cycle)
