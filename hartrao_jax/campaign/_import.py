"""Import real recordings (Leica PTX, XYZ text, E57) as a one-face campaign (``cycle = 0``).

``hartrao-jax import FILE --format ptx|xyz|e57 --out CAMPAIGN [--telescope gbt|hartrao|TOML]
[--elevation-deg E --azimuth-deg A]`` (the click command is `import_command`).

What the importer does, and the choices it makes:

* **Frame.** Points are taken in the file's own scanner frame, as written. For PTX that is the
  scanner's local frame: the 4x4 matrix of the header maps local points to a registered frame and
  is *not* applied; it is kept in the scan's ``extra`` as ``ptx_transform`` (as written, rows of
  the file: Leica writes the transpose, the last row holds the translation, so
  ``registered = [x, y, z, 1] @ ptx_transform``), with the header's ``ptx_scanner_position`` and
  ``ptx_scanner_axes``.
* **z axis.** Leica exports have z *up* (the instrument stands upright), while the project's
  scanner frame has z towards the nadir (the HartRAO scanner hangs upside down). Nothing is
  flipped: raw angles follow eq. (2) inverted in the file's own frame, theta measured from the
  file's +z axis (``cartesian_to_raw(xyz, cycle=0)``: ``phi = atan2(x, y)`` in [0, 2 pi),
  ``theta = acos(z / r)`` in (0, pi)). A scanner looking down on a dish sees it at theta > pi/2.
  Each scan records this as ``frame = "file: z up as exported, not flipped to the nadir"``.
* **One face.** Exports are processed points: ``cycle = 0`` (spec "one face only").
* **Time.** PTX grids are column-major (each column one vertical sweep at one horizontal angle):
  ``time_s = col * line_period_s + row / rows * line_period_s`` (nominal ``line_period_s`` =
  `LINE_PERIOD_S`). XYZ: ``time_s = data row * dt_s`` (`XYZ_DT_S`). E57: the file's timeStamp.
* **Intensity.** PTX: the intensity column (0..1); XYZ: the intensity column if there is one,
  else `DEFAULT_INTENSITY`. Values outside [0, 1] are rescaled by their min/max (recorded).
* **Missing returns.** PTX cells ``0 0 0`` are dropped; each kept point keeps its grid
  ``(row, col)`` and cell index ``col * rows + row`` (`ImportedScan.row`). XYZ points at the
  origin are dropped too (counted). Non-finite points are dropped (counted).
* **Scanner a priori** (`LEICA_EXPORT_SCANNER`): ``sigma_range_m = 0.0008`` and
  ``sigma_angle_rad = 1.5e-5`` (3"). Leica's phase/pulse scanners of the P class specify a range
  noise of 0.4-0.5 mm rms at 10-50 m on good targets; a point of a real panelled reflector adds
  its micro-roughness and the export's processing, and on the GBT scan 10 these values give
  sigma0 = 0.94 (with 2 mm / 4e-5 rad sigma0 was 0.37, i.e. far too pessimistic).
  ``angular_step_rad`` is estimated from the data: PTX the median angle between grid neighbours;
  XYZ and E57 the median angle to the nearest neighbour (for a subsampled export this is the
  spacing of the points in the file, larger than the instrument's step);
  `DEFAULT_ANGULAR_STEP_RAD` when it cannot be estimated.
* **Pointing.** Without ``--elevation-deg``, an alt-az scan gets ``elevation_deg = 90`` and
  ``elevation_assumed = true`` in its extra (``azimuth_deg = 0``, ``azimuth_assumed = true``:
  the gravity of an alt-az mount does not depend on the azimuth). An HA-DEC telescope converts a
  given elevation/azimuth to HA/DEC, or assumes the zenith (``ha = 0, dec = latitude``).

Parsing streams the file in blocks of ``chunk_rows`` lines, parsed by NumPy (bounded memory, never
the whole file at once). Every malformed input raises `CampaignError(file, "line N", "expected
..., found ...")` naming the line (1-based). A PTX file that ends before its grid is complete is an
error unless ``allow_truncated=True``, which keeps the cells read and marks ``truncated = true``.
"""

from __future__ import annotations

import dataclasses
import itertools
import logging
import math
import pathlib
import re
import tomllib
from collections.abc import Iterator
from dataclasses import dataclass, field
from typing import BinaryIO

import numpy as np

from ._campaign import (
    Campaign,
    CampaignError,
    ScanData,
    ScanMeta,
    Scanner,
    Site,
    Telescope,
    _scanner,
    _site,
    _Table,
    _telescope,
    read_scan_e57,
    write_campaign,
)
from ._format import cartesian_to_raw

log = logging.getLogger(__name__)

LINE_PERIOD_S = 0.1  # nominal duration of one PTX column (one vertical sweep), s
XYZ_DT_S = 1e-5  # nominal time between two XYZ points, s
DEFAULT_INTENSITY = 0.5
DEFAULT_ANGULAR_STEP_RAD = 5e-4
FORMATS = ("ptx", "xyz", "e57")
FRAME_NOTE = "file: z up as exported, not flipped to the nadir"
TWO_PI = 2 * math.pi

LEICA_EXPORT_SCANNER = Scanner(sigma_range_m=0.0008, sigma_angle_rad=1.5e-5,
                               angular_step_rad=DEFAULT_ANGULAR_STEP_RAD)
"""A priori of one point of a processed Leica export: range 0.8 mm, angle 1.5e-5 rad (3");
the angular step is replaced by the estimate from the data."""

_PRESETS: dict[str, tuple[Site, Telescope]] = {
    "hartrao": (
        Site("Hartebeesthoek", -25.8897, 27.6853),
        Telescope(name="HartRAO 26-m", mount="ha-dec", diameter_m=25.9, focal_length_m=10.9816,
                  cone_radius_m=1.6, quadrupod_azimuths_deg=(45.0, 135.0, 225.0, 315.0),
                  ring_edges_m=(1.6, 3.2, 4.8, 6.4, 8.0, 9.6, 11.2, 12.95),
                  panels_per_ring=(15, 24, 30, 36, 42, 48, 60))),
    # 100-m Green Bank Telescope: an off-axis section of a 208-m parent paraboloid (f = 60 m),
    # aperture centre 54 m from the parent axis; no panel layout, no quadrupod (offset feed arm).
    "gbt": (
        Site("Green Bank", 38.433, -79.84),
        Telescope(name="GBT 100-m", mount="alt-az", diameter_m=100.0, focal_length_m=60.0,
                  cone_radius_m=0.0, quadrupod_azimuths_deg=None, ring_edges_m=None,
                  panels_per_ring=None, offset_m=54.0)),
}


# ----------------------------------------------------------------------------- data


@dataclass
class ImportedScan:
    """One scan of an export, in the file's own frame (metres; see the module docstring)."""

    xyz: np.ndarray  # float64 (n, 3) scanner-frame coordinates as in the file, m
    intensity: np.ndarray  # float32 (n,) 0..1
    time_s: np.ndarray  # float64 (n,) s since the start of the scan (nominal)
    grid: np.ndarray | None  # int64 (n, 2) PTX grid (row, col); None for unordered exports
    header: dict = field(default_factory=dict)  # format-specific facts (see the readers)
    row: np.ndarray | None = None  # int64 (n,) PTX: cell index col*rows+row; XYZ: data row
    n_dropped_nonfinite: int = 0

    def __post_init__(self):
        self.xyz = np.asarray(self.xyz, dtype=np.float64).reshape(-1, 3)
        n = len(self.xyz)
        self.intensity = np.asarray(self.intensity, dtype=np.float32).reshape(-1)
        self.time_s = np.asarray(self.time_s, dtype=np.float64).reshape(-1)
        self.row = (np.arange(n, dtype=np.int64) if self.row is None
                    else np.asarray(self.row, dtype=np.int64).reshape(-1))
        if self.grid is not None:
            self.grid = np.asarray(self.grid, dtype=np.int64).reshape(-1, 2)
        lens = {len(self.intensity), len(self.time_s), len(self.row), n}
        if self.grid is not None:
            lens.add(len(self.grid))
        if len(lens) != 1:
            raise ValueError(f"ImportedScan arrays differ in length: {sorted(lens)}")

    def __len__(self):
        return len(self.xyz)


def to_scan_data(imported: ImportedScan) -> ScanData:
    """Raw one-face polar observations (cycle 0, eq. 2 inverted) in the file's own frame."""
    r, phi, theta = cartesian_to_raw(imported.xyz, cycle=0)
    phi = np.where(phi >= TWO_PI, 0.0, phi)  # mod can round up to exactly 2 pi
    return ScanData(r, phi, theta, imported.intensity, imported.time_s, imported.row,
                    n_dropped_nonfinite=imported.n_dropped_nonfinite)


# ----------------------------------------------------------------------------- line parsing

_WS = np.zeros(256, dtype=bool)
_WS[[9, 10, 11, 12, 13, 32]] = True


class _Lines:
    """A binary text file read line by line or in blocks, counting lines (1-based)."""

    def __init__(self, f: BinaryIO):
        self.f, self.n = f, 0  # n: number of the last line read

    def next_nonblank(self) -> bytes | None:
        for line in self.f:
            self.n += 1
            if line.strip():
                return line
        return None

    def next_raw(self) -> bytes | None:
        line = self.f.readline()
        if not line:
            return None
        self.n += 1
        return line

    def block(self, n: int) -> list[bytes]:
        lines = list(itertools.islice(self.f, n))
        self.n += len(lines)
        return lines


def _show(line: bytes | str, width: int = 60) -> str:
    s = line.decode("latin-1") if isinstance(line, bytes) else line
    s = s.strip()
    return repr(s if len(s) <= width else s[:width] + "...")


def _per_line(buf: np.ndarray, mask: np.ndarray, nl: np.ndarray, n_lines: int) -> np.ndarray:
    """How many positions of `mask` fall on each line (nl: positions of the newlines)."""
    return np.bincount(np.searchsorted(nl, np.flatnonzero(mask)), minlength=n_lines)[:n_lines]


def _number_error(path, lines: list[bytes], first_no: int, sep: bytes | None) -> CampaignError:
    """The first field of a block that NumPy cannot read as a number, as an error."""
    for i, line in enumerate(lines):
        text = line.decode("latin-1")
        fields = text.split(sep.decode()) if sep else text.split()
        for j, tok in enumerate(fields):
            tok = tok.strip()
            try:
                ok = len(np.fromstring(tok, sep=" ")) == 1 if tok else False
            except ValueError:
                ok = False
            if not ok:
                what = "an empty field" if not tok else f"{tok[:40]!r}"
                return CampaignError(path, f"line {first_no + i}",
                                     f"expected a number in field {j + 1}, found {what}")
    return CampaignError(path, f"lines {first_no}-{first_no + len(lines) - 1}",
                         "expected numbers, found text NumPy could not read")


def _parse_block(path, lines: list[bytes], first_no: int,
                 sep: bytes | None = None) -> tuple[np.ndarray, np.ndarray]:
    """Numbers of a block of lines, flat, and the number of fields on each line.

    Vectorised: fields are counted on the bytes, the numbers parsed by one ``np.fromstring``;
    only a failing block is re-read line by line to name the bad line.
    """
    data = b"".join(lines)
    if not data.endswith(b"\n"):
        data += b"\n"
    buf = np.frombuffer(data, dtype=np.uint8)
    nl = np.flatnonzero(buf == 10)
    if sep:
        n_sep = _per_line(buf, buf == sep[0], nl, len(lines))
        data = data.replace(sep, b" ")
        buf = np.frombuffer(data, dtype=np.uint8)
    ws = _WS[buf]
    start = ~ws
    start[1:] &= ws[:-1]
    counts = _per_line(buf, start, nl, len(lines))
    if sep:
        bad = (counts > 0) & (counts != n_sep + 1)
        if bad.any():
            raise _number_error(path, lines[int(np.argmax(bad)):], first_no + int(np.argmax(bad)),
                                sep)
    total = int(counts.sum())
    if total == 0:
        return np.empty(0), counts
    try:
        values = np.fromstring(data.decode("latin-1"), sep=" ")
    except ValueError:
        values = None
    if values is None or len(values) != total:
        raise _number_error(path, lines, first_no, sep)
    return values, counts


def _starts(counts: np.ndarray) -> np.ndarray:
    return np.cumsum(counts) - counts


# ----------------------------------------------------------------------------- estimates


def _unit(xyz: np.ndarray) -> np.ndarray:
    r = np.linalg.norm(xyz, axis=1, keepdims=True)
    return xyz / np.where(r > 0, r, 1.0)


def _raw_angles(xyz: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    """(phi, theta) of eq. (2) in the file's frame."""
    r = np.linalg.norm(xyz, axis=1)
    return (np.arctan2(xyz[:, 0], xyz[:, 1]),
            np.arccos(np.clip(xyz[:, 2] / np.where(r > 0, r, 1.0), -1, 1)))


def _encoder_steps(a: np.ndarray, b: np.ndarray) -> np.ndarray:
    """max(|d theta|, |d phi| wrapped) between point pairs: the step in raw angles."""
    pa, ta = _raw_angles(a)
    pb, tb = _raw_angles(b)
    dphi = np.abs(np.mod(pa - pb + math.pi, TWO_PI) - math.pi)
    return np.maximum(np.abs(ta - tb), dphi)


def grid_angular_step(xyz: np.ndarray, cell: np.ndarray, rows: int,
                      max_pairs: int = 200_000) -> float | None:
    """Median step (rad) in raw angles between grid neighbours: ``|d theta|`` along a column
    (adjacent rows), ``|d phi|`` along a row (adjacent columns), as ``max(|d theta|, |d phi|)``.

    `cell` = col * rows + row, ascending (column-major PTX order); at most `max_pairs` pairs
    of each kind are used. None without neighbour pairs.
    """
    n = len(cell)
    if n < 2:
        return None
    idx = np.arange(0, n, max(1, n // max_pairs))
    out = []
    for d in (1, rows):
        target = cell[idx] + d
        j = np.searchsorted(cell, target)
        ok = j < n
        ok[ok] = cell[j[ok]] == target[ok]
        if d == 1:
            ok &= (cell[idx] % rows) != rows - 1
        if ok.any():
            out.append(_encoder_steps(xyz[idx[ok]], xyz[j[ok]]))
    if not out:
        return None
    a = np.concatenate(out)
    a = a[a > 0]
    return float(np.median(a)) if len(a) else None


def nn_angular_step(xyz: np.ndarray, max_points: int = 200_000) -> float | None:
    """Median step (rad) in raw angles from each point to its nearest neighbour in direction,
    ``max(|d theta|, |d phi|)`` (an unordered export has no grid to follow).

    For a regular grid this is the instrument's step; for a subsampled export it is the spacing
    of the points in the file. Above `max_points`, the points nearest in azimuth to the median
    azimuth are used (a slab at full density, so neighbours are not thinned out). None with
    fewer than 2 points.
    """
    from scipy.spatial import cKDTree

    xyz = np.asarray(xyz, dtype=float)
    xyz = xyz[np.linalg.norm(xyz, axis=1) > 0]
    if len(xyz) < 2:
        return None
    if len(xyz) > max_points:
        a = np.arctan2(xyz[:, 0], xyz[:, 1])
        da = np.abs(np.mod(a - np.median(a) + math.pi, TWO_PI) - math.pi)
        xyz = xyz[np.argpartition(da, max_points)[:max_points]]
    u = _unit(xyz)
    d, j = cKDTree(u).query(u, k=2)
    ok = d[:, 1] > 0
    if not ok.any():
        return None
    return float(np.median(_encoder_steps(xyz[ok], xyz[j[ok, 1]])))


def _normalise_intensity(inten: np.ndarray, header: dict, path) -> np.ndarray:
    finite = inten[np.isfinite(inten)]
    if len(finite) and (finite.min() < 0 or finite.max() > 1):
        lo, hi = float(finite.min()), float(finite.max())
        header["intensity_scaled_from"] = [lo, hi]
        log.info("%s: intensity rescaled from [%g, %g] to [0, 1]", path, lo, hi)
        inten = (inten - lo) / (hi - lo) if hi > lo else np.full_like(inten, DEFAULT_INTENSITY)
    return inten.astype(np.float32)


# ----------------------------------------------------------------------------- PTX

_PTX_WIDTHS = {3: "x y z", 4: "x y z intensity", 7: "x y z intensity r g b"}


def _header_numbers(path, no: int, line: bytes | None, n: int, what: str,
                    integer: bool = False) -> list:
    if line is None:
        raise CampaignError(path, f"line {no}", f"expected {what}, found the end of the file")
    toks = line.split()
    kind = "one positive integer" if integer else f"{n} number{'s' if n > 1 else ''}"
    if len(toks) != n:
        raise CampaignError(path, f"line {no}", f"expected {what} ({kind}), found {len(toks)} "
                            f"field{'s' if len(toks) != 1 else ''}: {_show(line)}")
    out = []
    for j, t in enumerate(toks):
        s = t.decode("latin-1")
        try:
            v = int(s) if integer else float(s)
        except ValueError:
            v = None
        if v is None or (integer and v <= 0) or (not integer and not math.isfinite(v)):
            raise CampaignError(path, f"line {no}", f"expected {what} ({kind}), found "
                                f"{s[:40]!r} in field {j + 1}")
        out.append(v)
    return out


def _ptx_header(path, lines: _Lines, first: bytes, k: int, prev: str) -> dict:
    s = f" of scan {k + 1}" + prev
    cols = _header_numbers(path, lines.n, first, 1, "the number of columns" + s, True)[0]
    rows = _header_numbers(path, lines.n + 1, lines.next_raw(), 1, "the number of rows" + s,
                           True)[0]
    pos = _header_numbers(path, lines.n + 1, lines.next_raw(), 3, "the scanner position")
    axes = [_header_numbers(path, lines.n + 1, lines.next_raw(), 3, f"scanner axis {i + 1}")
            for i in range(3)]
    mat = [_header_numbers(path, lines.n + 1, lines.next_raw(), 4,
                           f"row {i + 1} of the 4x4 transform") for i in range(4)]
    return {"format": "ptx", "scan_index": k, "columns": cols, "rows": rows,
            "scanner_position": pos, "scanner_axes": axes, "transform": mat}


def _ptx_grid(path, lines: _Lines, h: dict, chunk_rows: int, line_period_s: float,
              allow_truncated: bool) -> ImportedScan:
    cols, rows = h["columns"], h["rows"]
    n_cells = cols * rows
    first_no = lines.n + 1
    h["first_data_line"] = first_no
    width = None
    parts: dict[str, list[np.ndarray]] = {"xyz": [], "inten": [], "cell": []}
    n_read = n_missing = n_nonfinite = 0
    while n_read < n_cells:
        block = lines.block(min(chunk_rows, n_cells - n_read))
        if not block:
            msg = (f"expected grid point {n_read + 1} of {n_cells} ({cols} columns x {rows} rows) "
                   f"of scan {h['scan_index'] + 1}, found the end of the file (truncated)")
            if not allow_truncated:
                raise CampaignError(path, f"line {lines.n + 1}",
                                    msg + "; --allow-truncated (allow_truncated=True) keeps "
                                    "the points read")
            log.warning("%s: line %d: %s; keeping the %d cells read", path, lines.n + 1, msg,
                        n_read)
            h["truncated"] = True
            break
        no0 = lines.n - len(block) + 1
        values, counts = _parse_block(path, block, no0)
        st = _starts(counts)
        # a cell is missing when its first three numbers are zero (lines of 3 fields: "0 0 0")
        has3 = counts >= 3
        s3 = np.where(has3, st, 0)
        if len(values):
            x, y, z = values[s3], values[np.minimum(s3 + 1, len(values) - 1)], \
                values[np.minimum(s3 + 2, len(values) - 1)]
        else:
            x = y = z = np.zeros(len(block))
        missing = has3 & (x == 0) & (y == 0) & (z == 0)
        point = ~missing & has3  # lines of fewer than 3 fields fail the check below
        if width is None and point.any():
            width = int(counts[int(np.argmax(point))])
            if width not in _PTX_WIDTHS:
                i = int(np.argmax(point))
                raise CampaignError(path, f"line {no0 + i}", "expected 3 (x y z), 4 (x y z "
                                    "intensity) or 7 (x y z intensity r g b) numbers per grid "
                                    f"point, found {width}: {_show(block[i])}")
            h["fields"] = _PTX_WIDTHS[width]
        ok_missing = np.isin(counts, (3, width) if width else tuple(_PTX_WIDTHS))
        # without a width yet, every line that is not a missing cell has fewer than 3 fields
        bad = np.where(missing, ~ok_missing, counts != width if width else True)
        if bad.any():
            i = int(np.argmax(bad))
            c = int(counts[i])
            want = width or 4
            detail = f": {_show(block[i])}" if c else ""
            what = ("an empty line" if c == 0 else f"{c} (short row){detail}" if c < want
                    else f"{c}{detail}")
            raise CampaignError(path, f"line {no0 + i}", f"expected {want} numbers per grid "
                                f"point ({_PTX_WIDTHS.get(want, 'x y z intensity')}) or '0 0 0' "
                                f"for a missing return, found {what}")
        keep = ~missing
        cell = n_read + np.flatnonzero(keep)
        sk = st[keep]
        xyz = np.stack([values[sk], values[sk + 1], values[sk + 2]], axis=1)
        inten = values[sk + 3] if width and width >= 4 else np.full(len(sk), DEFAULT_INTENSITY)
        fin = np.isfinite(xyz).all(axis=1) & np.isfinite(inten)
        n_nonfinite += int((~fin).sum())
        parts["xyz"].append(xyz[fin])
        parts["inten"].append(inten[fin])
        parts["cell"].append(cell[fin])
        n_missing += int(missing.sum())
        n_read += len(block)
    xyz = np.concatenate(parts["xyz"]) if parts["xyz"] else np.empty((0, 3))
    cell = np.concatenate(parts["cell"]) if parts["cell"] else np.empty(0, np.int64)
    inten = np.concatenate(parts["inten"]) if parts["inten"] else np.empty(0)
    col, row = np.divmod(cell, rows)
    h.update(n_cells=n_cells, n_cells_read=n_read, n_missing=n_missing, n_points=len(xyz),
             n_dropped_nonfinite=n_nonfinite, line_period_s=line_period_s,
             last_data_line=lines.n)
    h.setdefault("truncated", False)
    h.setdefault("fields", "x y z intensity")
    h["angular_step_rad"] = grid_angular_step(xyz, cell, rows)
    if n_nonfinite:
        log.warning("%s: scan %d: dropped %d non-finite points", path, h["scan_index"] + 1,
                    n_nonfinite)
    return ImportedScan(
        xyz=xyz, intensity=_normalise_intensity(inten, h, path),
        time_s=col * line_period_s + row / rows * line_period_s,
        grid=np.stack([row, col], axis=1), header=h, row=cell, n_dropped_nonfinite=n_nonfinite)


def iter_ptx(path, *, chunk_rows: int = 1_000_000, line_period_s: float = LINE_PERIOD_S,
             allow_truncated: bool = False) -> Iterator[ImportedScan]:
    """Stream the scans of a Leica PTX file, one `ImportedScan` at a time.

    Each scan: number of columns, number of rows, scanner position (3 numbers), scanner axes
    (3 lines of 3), a 4x4 transform (4 lines of 4), then ``columns * rows`` lines
    ``x y z intensity [r g b]`` in column-major order, ``0 0 0`` where nothing returned. Scans
    follow each other (blank lines between them are allowed). The grid is read ``chunk_rows``
    lines at a time. `header` holds ``columns, rows, scanner_position, scanner_axes, transform``
    (as written), ``n_cells, n_cells_read, n_missing, n_points, truncated, first_data_line,
    last_data_line, fields, line_period_s, angular_step_rad`` (None if not estimable).
    """
    path = pathlib.Path(path)
    if not path.is_file():
        raise CampaignError(path, "file", "expected an existing PTX file, not found")
    if chunk_rows < 1:
        raise ValueError(f"chunk_rows must be positive, not {chunk_rows!r}")
    with open(path, "rb") as f:
        lines = _Lines(f)
        k, prev = 0, ""
        while True:
            first = lines.next_nonblank()
            if first is None:
                if k == 0:
                    raise CampaignError(path, f"line {lines.n + 1}", "expected the number of "
                                        "columns of scan 1 (a PTX header), found the end of a "
                                        "blank file")
                return
            h = _ptx_header(path, lines, first, k, prev)
            h["first_line"] = lines.n - 9
            if not (np.allclose(h["scanner_position"], 0) and
                    np.allclose(h["scanner_axes"], np.eye(3))):
                log.info("%s: scan %d: header scanner position/axes are not the origin/identity; "
                         "the points are used as written (scanner-local frame)", path, k + 1)
            scan = _ptx_grid(path, lines, h, chunk_rows, line_period_s, allow_truncated)
            yield scan
            if h["truncated"]:
                return
            k += 1
            prev = (f" (scan {k} of {h['columns']} x {h['rows']} grid points ended at line "
                    f"{lines.n})")


def read_ptx(path, *, chunk_rows: int = 1_000_000, line_period_s: float = LINE_PERIOD_S,
             allow_truncated: bool = False) -> list[ImportedScan]:
    """All scans of a PTX file (see `iter_ptx`)."""
    return list(iter_ptx(path, chunk_rows=chunk_rows, line_period_s=line_period_s,
                         allow_truncated=allow_truncated))


# ----------------------------------------------------------------------------- XYZ

_NAMES = {"x": ("x", "xm", "cartesianx", "px"), "y": ("y", "ym", "cartesiany", "py"),
          "z": ("z", "zm", "cartesianz", "pz"),
          "intensity": ("intensity", "i", "int", "reflectance", "amplitude", "scalarintensity")}
_XYZ_WIDTHS = {3: "x y z", 4: "x y z intensity", 7: "x y z intensity r g b"}


def _is_number(tok: str) -> bool:
    try:
        return len(np.fromstring(tok, sep=" ")) == 1
    except ValueError:
        return False


def _xyz_layout(path, no: int, line: bytes, sep: bytes | None, header: bool) -> tuple:
    """(width, column of x, y, z, column of intensity or None) from the first line."""
    text = line.decode("latin-1")
    toks = [t.strip() for t in (text.split(sep.decode()) if sep else text.split())]
    w = len(toks)
    if header:
        norm = [re.sub(r"[^a-z0-9]", "", t.lower()) for t in toks]
        find = {k: next((i for i, t in enumerate(norm) if t in names), None)
                for k, names in _NAMES.items()}
        if all(find[k] is not None for k in "xyz"):
            return w, (find["x"], find["y"], find["z"]), find["intensity"]
    if w not in _XYZ_WIDTHS:
        raise CampaignError(path, f"line {no}", "expected 3 (x y z), 4 (x y z intensity) or 7 "
                            f"(x y z intensity r g b) fields, found {w}: {_show(line)} (a header "
                            "line naming the columns x, y, z, intensity removes the ambiguity)")
    return w, (0, 1, 2), 3 if w >= 4 else None


def read_xyz(path, *, chunk_rows: int = 1_000_000, dt_s: float = XYZ_DT_S) -> ImportedScan:
    """A plain XYZ text export: ``x y z [intensity ...]`` per line, one scan.

    Fields are separated by commas, semicolons or whitespace (decided on the first data line); an
    optional header line (the first non-blank line, if it is not all numbers; lines starting with
    ``#`` before it are skipped) may name the columns (``x, y, z, intensity``). Blank lines are
    skipped. Points at the origin and non-finite points are dropped (counted in `header`).
    ``time_s = data row * dt_s``; `row` is the data row (0-based, header and blank lines not
    counted). `header`: ``format, separator, columns, fields, n_rows, n_points, n_zero_dropped,
    first_data_line, angular_step_rad`` (nearest-neighbour estimate, see `nn_angular_step`).
    """
    path = pathlib.Path(path)
    if not path.is_file():
        raise CampaignError(path, "file", "expected an existing XYZ text file, not found")
    h: dict = {"format": "xyz"}
    with open(path, "rb") as f:
        lines = _Lines(f)
        first = lines.next_nonblank()
        while first is not None and first.lstrip().startswith((b"#", b"//")):
            first = lines.next_nonblank()
        if first is None:
            raise CampaignError(path, f"line {lines.n + 1}", "expected x y z [intensity] "
                                "points, found an empty file")
        sep = b"," if b"," in first else b";" if b";" in first else None
        h["separator"] = sep.decode() if sep else "whitespace"
        text0 = first.decode("latin-1")
        toks = text0.split(sep.decode()) if sep else text0.split()
        is_header = not all(_is_number(t.strip()) for t in toks)
        if is_header:
            h["columns"] = [t.strip() for t in toks]
            h["header_line"] = lines.n
            width, ixyz, iint = _xyz_layout(path, lines.n, first, sep, True)
            pending: list[bytes] = []
        else:
            width, ixyz, iint = _xyz_layout(path, lines.n, first, sep, False)
            pending = [first]
        h["first_data_line"] = lines.n + (1 if is_header else 0)
        h["fields"] = " ".join(h["columns"]) if is_header else _XYZ_WIDTHS[width]
        xyzs, ints, rows_ = [], [], []
        n_rows = n_zero = n_nonfinite = 0
        no0 = h["first_data_line"]
        while True:
            block = pending + lines.block(chunk_rows)
            pending = []
            if not block:
                break
            values, counts = _parse_block(path, block, no0, sep)
            bad = (counts > 0) & (counts != width)
            if bad.any():
                i = int(np.argmax(bad))
                c = int(counts[i])
                src = "the header" if is_header else f"line {h['first_data_line']}"
                raise CampaignError(path, f"line {no0 + i}", f"expected {width} fields as on "
                                    f"{src}, found {c}{' (short row)' if c < width else ''}: "
                                    f"{_show(block[i])}")
            st = _starts(counts)[counts > 0]
            xyz = np.stack([values[st + j] for j in ixyz], axis=1)
            inten = values[st + iint] if iint is not None else np.full(len(st), DEFAULT_INTENSITY)
            data_row = n_rows + np.arange(len(st), dtype=np.int64)
            n_rows += len(st)
            fin = np.isfinite(xyz).all(axis=1) & np.isfinite(inten)
            zero = fin & (xyz == 0).all(axis=1)
            keep = fin & ~zero
            n_nonfinite += int((~fin).sum())
            n_zero += int(zero.sum())
            xyzs.append(xyz[keep])
            ints.append(inten[keep])
            rows_.append(data_row[keep])
            no0 += len(block)
    xyz = np.concatenate(xyzs) if xyzs else np.empty((0, 3))
    row = np.concatenate(rows_) if rows_ else np.empty(0, np.int64)
    inten = np.concatenate(ints) if ints else np.empty(0)
    if not len(xyz):
        raise CampaignError(path, "points", f"expected at least one point, found none "
                            f"({n_rows} rows: {n_zero} at the origin, {n_nonfinite} non-finite)")
    if n_nonfinite:
        log.warning("%s: dropped %d non-finite points", path, n_nonfinite)
    h.update(n_rows=n_rows, n_points=len(xyz), n_zero_dropped=n_zero,
             n_dropped_nonfinite=n_nonfinite, dt_s=dt_s, angular_step_rad=nn_angular_step(xyz))
    return ImportedScan(xyz=xyz, intensity=_normalise_intensity(inten, h, path),
                        time_s=row * dt_s, grid=None, header=h, row=row,
                        n_dropped_nonfinite=n_nonfinite)


# ----------------------------------------------------------------------------- telescopes


def _load_preset(name_or_toml) -> tuple[Site, Telescope, Scanner, set[str]]:
    """Preset or TOML -> (site, telescope, scanner, scanner keys given explicitly)."""
    key = str(name_or_toml).strip().lower()
    if key in _PRESETS:
        site, tel = _PRESETS[key]
        return site, tel, LEICA_EXPORT_SCANNER, set()
    path = pathlib.Path(str(name_or_toml))
    if not path.is_file():
        raise CampaignError(name_or_toml, "telescope", "expected 'gbt', 'hartrao' or a TOML "
                            "file with a [telescope] table, found neither a preset nor a file")

    try:
        doc = tomllib.loads(path.read_bytes().decode("utf-8"))
    except (tomllib.TOMLDecodeError, UnicodeDecodeError) as e:
        raise CampaignError(path, "toml", f"expected valid UTF-8 TOML, {e}") from None
    base = doc.get("preset", "gbt")
    if base not in _PRESETS:
        raise CampaignError(path, "preset", f"expected one of {sorted(_PRESETS)} (fills a missing "
                            f"[site]), found {base!r}")
    if "telescope" not in doc:
        raise CampaignError(path, "telescope", "required table is missing (expected [telescope] "
                            "with mount, diameter_m, focal_length_m, cone_radius_m)")
    tel = _telescope(_Table(path, "telescope", doc["telescope"]))
    site = (_site(_Table(path, "site", doc["site"])) if "site" in doc else _PRESETS[base][0])
    sc = doc.get("scanner", {})
    if not isinstance(sc, dict):
        raise CampaignError(path, "scanner", f"expected a table, found {type(sc).__name__}")
    merged = {"sigma_range_m": LEICA_EXPORT_SCANNER.sigma_range_m,
              "sigma_angle_rad": LEICA_EXPORT_SCANNER.sigma_angle_rad,
              "angular_step_rad": LEICA_EXPORT_SCANNER.angular_step_rad, **sc}
    return site, tel, _scanner(_Table(path, "scanner", merged)), set(sc)


def telescope_preset(name_or_toml) -> tuple[Site, Telescope, Scanner]:
    """Site, telescope and scanner a priori for an import.

    ``"hartrao"``: the spec's defaults (HA-DEC, f = 10.9816 m, D = 25.9 m, panels, quadrupod).
    ``"gbt"``: the 100-m Green Bank Telescope (alt-az, latitude 38.433, longitude -79.84,
    f = 60 m, D = 100 m, ``offset_m = 54``: off-axis section of a 208-m parent paraboloid, aperture
    centre 54 m from its axis; no cone, no panels, no quadrupod). Otherwise a TOML file with a
    ``[telescope]`` table (keys as in campaign.toml), optional ``[site]`` (default: the site of
    ``preset = "gbt"|"hartrao"``, gbt if absent) and optional ``[scanner]`` (keys override
    `LEICA_EXPORT_SCANNER`). The scanner of the named presets is `LEICA_EXPORT_SCANNER`.
    """
    site, tel, scanner, _ = _load_preset(name_or_toml)
    return site, tel, scanner


def _altaz_to_hadec(el_deg: float, az_deg: float, lat_deg: float) -> tuple[float, float]:
    """(HA, DEC) in degrees of a direction at elevation/azimuth (from north towards east)."""
    el, az, lat = np.radians([el_deg, az_deg, lat_deg])
    dec = math.asin(np.clip(math.sin(el) * math.sin(lat) + math.cos(el) * math.cos(lat)
                            * math.cos(az), -1, 1))
    ha = math.atan2(-math.cos(el) * math.sin(az),
                    math.sin(el) * math.cos(lat) - math.cos(el) * math.sin(lat) * math.cos(az))
    return math.degrees(ha), math.degrees(dec)


def _pointing(tel: Telescope, site: Site, elevation_deg, azimuth_deg, ha_deg, dec_deg) -> dict:
    out: dict = {}
    extra: dict = {}
    if tel.mount == "alt-az":
        if elevation_deg is None:
            extra["elevation_assumed"] = True
        if azimuth_deg is None:
            extra["azimuth_assumed"] = True
        out["elevation_deg"] = 90.0 if elevation_deg is None else float(elevation_deg)
        out["azimuth_deg"] = 0.0 if azimuth_deg is None else float(azimuth_deg)
    else:
        if ha_deg is not None and dec_deg is not None:
            out["ha_deg"], out["dec_deg"] = float(ha_deg), float(dec_deg)
        elif elevation_deg is not None:
            if azimuth_deg is None:
                extra["azimuth_assumed"] = True
            out["ha_deg"], out["dec_deg"] = _altaz_to_hadec(
                elevation_deg, azimuth_deg or 0.0, site.latitude_deg)
            extra["elevation_deg_given"] = float(elevation_deg)
            if azimuth_deg is not None:
                extra["azimuth_deg_given"] = float(azimuth_deg)
        else:
            out["ha_deg"], out["dec_deg"] = 0.0, float(site.latitude_deg)
            extra["elevation_assumed"] = True
    return {**out, "extra": extra}


# ----------------------------------------------------------------------------- import


def _infer_format(path: pathlib.Path) -> str:
    s = path.suffix.lower()
    return "ptx" if s == ".ptx" else "e57" if s == ".e57" else "xyz"


def _clean_extra(h: dict, keys) -> dict:
    return {k: h[k] for k in keys if k in h and h[k] is not None}


def _ptx_extra(h: dict) -> dict:
    out = {"ptx_scan_index": h["scan_index"] + 1, "ptx_first_line": h["first_line"],
           "ptx_columns": h["columns"], "ptx_rows": h["rows"],
           "ptx_scanner_position": h["scanner_position"], "ptx_scanner_axes": h["scanner_axes"],
           "ptx_transform": h["transform"], "ptx_fields": h["fields"],
           "n_cells": h["n_cells"], "n_cells_read": h["n_cells_read"],
           "n_missing": h["n_missing"], "truncated": h["truncated"],
           "line_period_s": h["line_period_s"]}
    return out


def _e57_imported(path) -> tuple[ScanData, dict]:
    data = read_scan_e57(path, 0)
    st = np.sin(data.theta_rad)
    xyz = np.stack([data.range_m * st * np.sin(data.phi_rad),
                    data.range_m * st * np.cos(data.phi_rad),
                    data.range_m * np.cos(data.theta_rad)], axis=1)
    return data, {"format": "e57", "n_points": len(data),
                  "angular_step_rad": nn_angular_step(xyz)}


def import_file(path, fmt: str | None = None, out_dir=None, telescope="gbt",
                elevation_deg: float | None = None, azimuth_deg: float | None = None,
                position: str = "p1", *, ha_deg: float | None = None,
                dec_deg: float | None = None, line_period_s: float = LINE_PERIOD_S,
                dt_s: float = XYZ_DT_S, chunk_rows: int = 1_000_000,
                allow_truncated: bool = False, overwrite: bool = False) -> Campaign:
    """Import a PTX / XYZ / E57 export into a one-face campaign (``cycle = 0``) at `out_dir`.

    One ``[[scan]]`` per scan of the file: id ``<position>c0`` (several PTX scans: positions
    ``<position>-1, -2, ...``, each scan is its own scanner setup). Scan extras record the source
    (``source_file, source_format``), ``frame`` (see the module docstring), the PTX header
    (``ptx_transform`` etc.), the counts, ``angular_step_rad_estimate`` and the pointing flags
    (``elevation_assumed`` ...). The campaign's ``angular_step_rad`` is the median of the scans'
    estimates unless a TOML ``[scanner]`` sets it. `fmt` None: from the suffix (.ptx, .e57, else
    xyz). Refuses to write over an existing campaign.toml unless `overwrite`. Returns the
    campaign as loaded back from disk.
    """
    path = pathlib.Path(path)
    fmt = (fmt or _infer_format(path)).lower()
    if fmt not in FORMATS:
        raise ValueError(f"fmt must be one of {', '.join(FORMATS)}, not {fmt!r}")
    if out_dir is None:
        raise ValueError("out_dir is required")
    out_dir = pathlib.Path(out_dir)
    if not path.is_file():
        raise CampaignError(path, "file", f"expected an existing {fmt.upper()} file, not found")
    if not re.fullmatch(r"[A-Za-z0-9_][A-Za-z0-9._-]*", position):
        raise ValueError(f"position {position!r} must use letters, digits, '.', '_' and '-' "
                         "(it names the scan files)")
    if (out_dir / "campaign.toml").exists() and not overwrite:
        raise CampaignError(out_dir / "campaign.toml", "file", "expected a new campaign "
                            "directory, found an existing campaign.toml (overwrite=True replaces "
                            "it)")
    site, tel, scanner, explicit = _load_preset(telescope)
    pointing = _pointing(tel, site, elevation_deg, azimuth_deg, ha_deg, dec_deg)
    point_extra = pointing.pop("extra")

    items: list[tuple[ScanData, dict]] = []
    if fmt == "ptx":
        for s in iter_ptx(path, chunk_rows=chunk_rows, line_period_s=line_period_s,
                          allow_truncated=allow_truncated):
            items.append((to_scan_data(s), {**_ptx_extra(s.header), "n_points": len(s),
                                            "_step": s.header["angular_step_rad"]}))
            del s
    elif fmt == "xyz":
        s = read_xyz(path, chunk_rows=chunk_rows, dt_s=dt_s)
        h = s.header
        items.append((to_scan_data(s), {
            **_clean_extra(h, ("separator", "fields", "n_rows", "n_zero_dropped", "dt_s",
                               "intensity_scaled_from")),
            "n_points": len(s), "_step": h["angular_step_rad"]}))
        del s
    else:
        data, h = _e57_imported(path)
        items.append((data, {"n_points": len(data), "_step": h["angular_step_rad"]}))

    for k, (data, extra) in enumerate(items):
        if not len(data):
            log.warning("%s: scan %d has no points (all cells missing), not imported", path, k + 1)
    numbered = [(k, d, e) for k, (d, e) in enumerate(items) if len(d)]
    if not numbered:
        raise CampaignError(path, "points", f"expected at least one point, found none in "
                            f"{len(items)} scan{'s' if len(items) != 1 else ''}")
    metas, scans, steps = [], {}, []
    for k, data, extra in numbered:
        step = extra.pop("_step")
        if step is not None and step > 0:
            steps.append(step)
            extra["angular_step_rad_estimate"] = step
        if data.n_dropped_nonfinite:
            extra["n_dropped_nonfinite"] = data.n_dropped_nonfinite
        pos = position if len(items) == 1 else f"{position}-{k + 1}"
        sid = f"{pos}c0"
        metas.append(ScanMeta(id=sid, position=pos, cycle=0, file=f"scans/{sid}.parquet",
                              **pointing, extra={"source_file": path.name, "source_format": fmt,
                                                 "frame": FRAME_NOTE, **point_extra, **extra}))
        scans[sid] = data
    if "angular_step_rad" not in explicit:
        step = float(np.median(steps)) if steps else DEFAULT_ANGULAR_STEP_RAD
        if not steps:
            log.warning("%s: angular step not estimable, using %g rad", path, step)
        scanner = dataclasses.replace(scanner, angular_step_rad=step)
    campaign = Campaign(root=out_dir, site=site, telescope=tel, scanner=scanner,
                        scans=tuple(metas),
                        extra={"import": {"source": str(path), "format": fmt,
                                          "frame": FRAME_NOTE, "tool": "hartrao-jax import"}})
    return write_campaign(out_dir, campaign, scans)


# ----------------------------------------------------------------------------- CLI
