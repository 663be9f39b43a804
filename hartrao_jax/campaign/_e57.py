"""ASTM E57 scans through pye57's libe57 layer (float64 fields; pye57's writer cannot do this).

Angle conventions (radians). Raw scanner angles of `campaign-format.md`:
``x = r sin(theta) sin(phi), y = r sin(theta) cos(phi), z = r cos(theta)``; face 1 has theta in
(0, pi), face 2 has theta in (pi, 2 pi) and ``phi + pi``. E57 stores one face:
``x = r cos(el) cos(az), y = r cos(el) sin(az), z = r sin(el)``. With the direction azimuth
``a = atan2(x, y)`` and ``theta0 = acos(z / r)`` this gives ``az = pi/2 - a`` and
``el = pi/2 - theta0``. Going back, ``(a, theta0)`` is face 1 when ``a`` lies in the cycle's phi
range, otherwise face 2 ``((a - pi) mod 2 pi, 2 pi - theta0)``; cycle 0 is always face 1.
"""

from __future__ import annotations

import logging
import math
import os
import pathlib
import uuid
from collections.abc import Iterator

import numpy as np

from ._format import (
    ANGLE_TOL_RAD,
    DEFAULT_INTENSITY,
    PHI_RANGE,
    CampaignError,
    ScanData,
    _check_angles,
    _first_line,
)

log = logging.getLogger(__name__)

TWO_PI = 2 * math.pi
SPHERICAL = ("sphericalRange", "sphericalAzimuth", "sphericalElevation")
CARTESIAN = ("cartesianX", "cartesianY", "cartesianZ")


def _mod2pi(a: np.ndarray) -> np.ndarray:
    """a mod 2 pi in [0, 2 pi) (np.mod can round up to exactly 2 pi)."""
    a = np.mod(a, TWO_PI)
    return np.where(a >= TWO_PI, 0.0, a)


def raw_to_e57(phi: np.ndarray, theta: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    """Raw two-face (phi, theta) -> E57 (azimuth in (-pi, pi], elevation in [-pi/2, pi/2])."""
    face2 = theta > math.pi
    theta0 = np.where(face2, TWO_PI - theta, theta)
    a = np.where(face2, phi + math.pi, phi)
    az = math.pi - _mod2pi(math.pi - (math.pi / 2 - a))
    return az, math.pi / 2 - theta0


def e57_to_raw(az: np.ndarray, el: np.ndarray, cycle: int) -> tuple[np.ndarray, np.ndarray]:
    """E57 face-1 (azimuth, elevation) -> raw (phi, theta) of the given cycle (0, 1 or 2)."""
    a = _mod2pi(math.pi / 2 - np.asarray(az, dtype=np.float64))
    theta0 = math.pi / 2 - np.asarray(el, dtype=np.float64)
    if cycle == 0:
        return a, theta0
    lo, hi = PHI_RANGE[cycle]
    face1 = (a >= lo) & (a < hi)
    return np.where(face1, a, _mod2pi(a - math.pi)), np.where(face1, theta0, TWO_PI - theta0)


def cartesian_to_e57(x, y, z) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    """Cartesian scanner-frame coordinates (m) -> E57 (range m, azimuth rad, elevation rad)."""
    h = np.hypot(x, y)
    return np.hypot(h, z), np.arctan2(y, x), np.arctan2(z, h)


# ----------------------------------------------------------------------------- reading


def _libe57():
    from pye57 import libe57

    return libe57


def _node_value(parent, name: str) -> float | None:
    """Numeric value of a child node (Float, Integer or ScaledInteger), None if absent."""
    from pye57.utils import get_node

    if not parent.isDefined(name):
        return None
    n = get_node(parent, name)
    return float(n.scaledValue() if hasattr(n, "scaledValue") else n.value())


def _fields(struct) -> list[str]:
    return [struct.get(i).elementName() for i in range(struct.childCount())]


def _intensity_scale(scan_node) -> tuple[float, float] | None:
    """(min, max) to normalise intensity to 0..1 when the file's limits lie outside 0..1."""
    lib = _libe57()
    if not scan_node.isDefined("intensityLimits"):
        return None
    lim = lib.StructureNode(scan_node.get("intensityLimits"))
    lo, hi = _node_value(lim, "intensityMinimum"), _node_value(lim, "intensityMaximum")
    if lo is None or hi is None or hi <= lo or (lo >= 0.0 and hi <= 1.0):
        return None
    return lo, hi


def _to_columns(path, buf: dict, m: int, spherical: bool, cycle: int, scale) -> dict:
    """One chunk of E57 buffers -> raw scan columns (invalid points get NaN range)."""
    if spherical:
        r, az, el = (buf[k][:m].copy() for k in SPHERICAL)
    else:
        r, az, el = cartesian_to_e57(*(buf[k][:m] for k in CARTESIAN))
    bad = np.abs(el) > math.pi / 2 + ANGLE_TOL_RAD
    if bad.any():
        i = int(np.argmax(bad))
        raise CampaignError(path, "sphericalElevation", "expected values in [-pi/2, pi/2] rad to "
                            f"convert to raw angles, found {int(bad.sum())} outside, first: "
                            f"{float(el[i])!r}")
    phi, theta = e57_to_raw(az, el, cycle)
    state = buf.get("sphericalInvalidState" if spherical else "cartesianInvalidState")
    if state is not None:
        r[state[:m] != 0] = np.nan
    inten = buf["intensity"][:m].copy() if "intensity" in buf else \
        np.full(m, DEFAULT_INTENSITY, np.float32)
    if scale is not None:
        inten = ((inten - scale[0]) / (scale[1] - scale[0])).astype(np.float32)
    time = buf["timeStamp"][:m].copy() if "timeStamp" in buf else np.zeros(m)
    return {"range_m": r, "phi_rad": phi, "theta_rad": theta, "intensity": inten, "time_s": time}


def iter_e57_columns(path: pathlib.Path, cycle: int, rows_per_chunk: int | None) -> Iterator[dict]:
    """Yield the raw scan columns of a one-scan E57 file (all at once or in chunks of points)."""
    lib = _libe57()
    if not path.is_file():
        raise CampaignError(path, "file", "expected an existing E57 scan file, not found")
    try:
        imf = lib.ImageFile(str(path), "r")
    except lib.E57Exception as e:
        raise CampaignError(path, "file", "expected an E57 file, could not read it (truncated or "
                            f"not E57): {_first_line(e)}") from None
    reader = None
    try:
        root = imf.root()
        n_scans = lib.VectorNode(root.get("data3D")).childCount() if root.isDefined("data3D") else 0
        if n_scans != 1:
            raise CampaignError(path, "data3D", f"expected exactly one scan, found {n_scans}")
        scan_node = lib.StructureNode(lib.VectorNode(root.get("data3D")).get(0))
        points = lib.CompressedVectorNode(scan_node.get("points"))
        names = _fields(lib.StructureNode(points.prototype()))
        spherical = all(k in names for k in SPHERICAL)
        if not spherical and not all(k in names for k in CARTESIAN):
            raise CampaignError(path, "points", "expected spherical (sphericalRange/Azimuth/"
                                "Elevation) or Cartesian (cartesianX/Y/Z) fields to convert to raw"
                                f" angles, found {', '.join(names) or 'none'}")
        if scan_node.isDefined("pose"):
            log.debug("%s: pose ignored, raw angles are in the scanner's own frame", path)
        for k, what in (("intensity", f"intensity set to {DEFAULT_INTENSITY}"),
                        ("timeStamp", "time_s set to 0")):
            if k not in names:
                log.warning("%s: no %s field, %s", path, k, what)
        scale = _intensity_scale(scan_node)
        if scale is not None:
            log.info("%s: intensity normalised from [%g, %g] to [0, 1]", path, *scale)
        n = points.childCount()
        cap = max(1, min(n, rows_per_chunk or n))
        state = "sphericalInvalidState" if spherical else "cartesianInvalidState"
        dtypes = {k: np.float64 for k in (SPHERICAL if spherical else CARTESIAN)}
        dtypes.update({k: t for k, t in (("intensity", np.float32), ("timeStamp", np.float64),
                                         (state, np.longlong)) if k in names})
        buf = {k: np.empty(cap, dtype=t) for k, t in dtypes.items()}
        bufs = lib.VectorSourceDestBuffer()
        for k, a in buf.items():
            bufs.append(lib.SourceDestBuffer(imf, k, a, cap, True, True))
        if n == 0:
            yield _to_columns(path, buf, 0, spherical, cycle, scale)
            return
        reader = points.reader(bufs)
        while (m := reader.read()) > 0:
            yield _to_columns(path, buf, m, spherical, cycle, scale)
    except lib.E57Exception as e:
        raise CampaignError(path, "file", "expected a readable E57 scan, reading failed: "
                            f"{_first_line(e)}") from None
    finally:
        if reader is not None:
            reader.close()
        imf.close()


# ----------------------------------------------------------------------------- writing


def _header(lib, imf) -> None:
    root = imf.root()
    imf.extensionsAdd("", lib.E57_V1_0_URI)
    root.set("formatName", lib.StringNode(imf, "ASTM E57 3D Imaging Data File"))
    root.set("guid", lib.StringNode(imf, f"{{{uuid.uuid4()}}}"))
    root.set("versionMajor", lib.IntegerNode(imf, lib.E57_FORMAT_MAJOR))
    root.set("versionMinor", lib.IntegerNode(imf, lib.E57_FORMAT_MINOR))
    root.set("e57LibraryVersion", lib.StringNode(imf, lib.E57_LIBRARY_ID))
    root.set("coordinateMetadata", lib.StringNode(imf, ""))
    root.set("data3D", lib.VectorNode(imf, True))
    root.set("images2D", lib.VectorNode(imf, True))


def _struct(lib, imf, values: dict) -> object:
    node = lib.StructureNode(imf)
    for k, v in values.items():
        node.set(k, lib.FloatNode(imf, float(v)))
    return node


def _write_points(lib, imf, scan_node, cols: dict, inten_lim: tuple[float, float]) -> None:
    """Prototype (float64 spherical/time, float32 intensity, integer state) and the points."""
    proto = lib.StructureNode(imf)
    for k in (*SPHERICAL, "timeStamp"):
        proto.set(k, lib.FloatNode(imf, 0.0, lib.E57_DOUBLE))
    proto.set("intensity", lib.FloatNode(imf, inten_lim[0], lib.E57_SINGLE, *inten_lim))
    proto.set("sphericalInvalidState", lib.IntegerNode(imf, 0, 0, 2))
    points = lib.CompressedVectorNode(imf, proto, lib.VectorNode(imf, True))
    scan_node.set("points", points)
    n = len(cols["sphericalRange"])
    cap = max(1, min(n, 1_000_000))
    buf = {k: np.empty(cap, dtype=v.dtype) for k, v in cols.items()}
    bufs = lib.VectorSourceDestBuffer()
    for k, a in buf.items():
        bufs.append(lib.SourceDestBuffer(imf, k, a, cap, True, True))
    writer = points.writer(bufs)
    try:
        for i in range(0, n, cap):
            m = min(cap, n - i)
            for k, a in buf.items():
                a[:m] = cols[k][i:i + m]
            writer.write(m)
    finally:
        writer.close()


def write_e57(path: pathlib.Path, scan: ScanData, cycle: int) -> None:
    """Write one scan as a one-scan E57 file, spherical face-1 form, float64 coordinates.

    Rows with non-finite values are written with ``sphericalInvalidState = 2`` (and zeros), so
    reading drops and counts them as for Parquet.
    """
    lib = _libe57()
    if cycle not in (0, 1, 2):
        raise ValueError(f"cycle must be 0, 1 or 2, not {cycle!r}")
    finite = np.ones(len(scan), dtype=bool)
    for c in ("range_m", "phi_rad", "theta_rad", "intensity", "time_s"):
        finite &= np.isfinite(getattr(scan, c))
    _check_angles(path, cycle, scan.phi_rad[finite], scan.theta_rad[finite], scan.row[finite])
    z = lambda v: np.where(finite, v, 0).astype(v.dtype)
    az, el = raw_to_e57(z(scan.phi_rad), z(scan.theta_rad))
    cols = {"sphericalRange": z(scan.range_m), "sphericalAzimuth": z(az),
            "sphericalElevation": z(el), "timeStamp": z(scan.time_s),
            "intensity": z(scan.intensity).astype(np.float32),
            "sphericalInvalidState": np.where(finite, 0, 2).astype(np.longlong)}
    inten = cols["intensity"][finite]
    inten_lim = (min(0.0, float(inten.min(initial=0.0))), max(1.0, float(inten.max(initial=1.0))))
    tmp = path.with_name(path.name + ".tmp")
    tmp.unlink(missing_ok=True)
    imf = lib.ImageFile(str(tmp), "w")
    try:
        _header(lib, imf)
        node = lib.StructureNode(imf)
        node.set("guid", lib.StringNode(imf, f"{{{uuid.uuid4()}}}"))
        node.set("name", lib.StringNode(imf, path.stem))
        node.set("description", lib.StringNode(
            imf, f"hartrao-jax raw scan, cycle {cycle}; spherical coordinates in face-1 form"))
        node.set("intensityLimits", _struct(lib, imf, {"intensityMinimum": inten_lim[0],
                                                       "intensityMaximum": inten_lim[1]}))
        if finite.any():
            node.set("sphericalBounds", _struct(lib, imf, {
                "rangeMinimum": scan.range_m[finite].min(),
                "rangeMaximum": scan.range_m[finite].max(),
                "elevationMinimum": el[finite].min(), "elevationMaximum": el[finite].max(),
                "azimuthStart": -math.pi, "azimuthEnd": math.pi}))
        lib.VectorNode(imf.root().get("data3D")).append(node)
        _write_points(lib, imf, node, cols, inten_lim)
        imf.close()
    except BaseException:
        imf.cancel()
        tmp.unlink(missing_ok=True)
        raise
    os.replace(tmp, path)
