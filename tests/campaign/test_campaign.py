"""Campaign I/O: round trips (TOML, Parquet, E57) and one specific error per bad input."""

from __future__ import annotations

import dataclasses
import datetime as dt
import hashlib
import logging
import math
import pathlib
import re

import numpy as np
import pyarrow as pa
import pyarrow.parquet as pq
import pytest

from hartrao_jax.campaign._campaign import (
    FORMAT,
    Campaign,
    CampaignError,
    ScanData,
    ScanMeta,
    default_campaign,
    iter_scan_chunks,
    load_campaign,
    read_scan,
    read_scan_e57,
    write_campaign,
    write_scan_e57,
    write_scan_parquet,
)
from hartrao_jax.campaign._e57 import cartesian_to_e57, e57_to_raw, raw_to_e57

PI = math.pi
COLS = ("range_m", "phi_rad", "theta_rad", "intensity", "time_s", "row")


# ----------------------------------------------------------------------------- helpers


def make_scan(cycle: int, n: int = 300, seed: int = 0, margin: float = 1e-6) -> ScanData:
    """Random raw observations of one cycle, both faces for cycles 1/2 (kept off the edges)."""
    rng = np.random.default_rng(seed + cycle)
    lo, hi = {0: (0.0, 2 * PI), 1: (0.0, PI), 2: (PI, 2 * PI)}[cycle]
    phi = rng.uniform(lo + margin, hi - margin, n)
    theta = rng.uniform(1e-3, PI - 1e-3, n)
    if cycle:
        theta = np.where(rng.random(n) < 0.5, 2 * PI - theta, theta)
    return ScanData(range_m=rng.uniform(1.0, 14.0, n), phi_rad=phi, theta_rad=theta,
                    intensity=rng.random(n).astype(np.float32), time_s=np.arange(n) * 0.013,
                    row=np.arange(n))


def scan_meta(sid: str, cycle: int, position: str = "r23", **kw) -> ScanMeta:
    return ScanMeta(id=sid, position=position, cycle=cycle, file="", ha_deg=-35.0, dec_deg=-64.0,
                    **kw)


def make_campaign(root: pathlib.Path, fmt: str = "parquet", cycles=(1, 2)) -> Campaign:
    metas = [scan_meta(f"r23c{c}", c) for c in cycles]
    return write_campaign(root, default_campaign(metas),
                          {m.id: make_scan(m.cycle) for m in metas}, fmt=fmt)


def edit_toml(root: pathlib.Path, pattern: str, repl: str, count: int = 1) -> pathlib.Path:
    """Regex-edit campaign.toml (multiline); the pattern must match."""
    path = root / "campaign.toml"
    text, n = re.subn(pattern, repl, path.read_text(), count=count, flags=re.M)
    assert n, f"pattern {pattern!r} not found"
    path.write_text(text)
    return path


def error_of(fn, *args) -> str:
    with pytest.raises(CampaignError) as info:
        fn(*args)
    msg = str(info.value)
    assert "\n" not in msg
    return msg


def assert_parts(msg: str, *parts: str):
    for p in parts:
        assert p in msg, f"{p!r} not in {msg!r}"


def same_scan(a: ScanData, b: ScanData):
    for c in COLS:
        x, y = getattr(a, c), getattr(b, c)
        assert x.dtype == y.dtype and np.array_equal(x, y), c


def write_table(path: pathlib.Path, cols: dict):
    pq.write_table(pa.table(cols), path)


def table_of(scan: ScanData) -> dict:
    return {c: getattr(scan, c) for c in COLS[:-1]}


# ----------------------------------------------------------------------------- round trips


def test_campaign_toml_roundtrip_keeps_extra_keys_and_datetimes(tmp_path):
    start = dt.datetime(2024, 4, 8, 18, 42, tzinfo=dt.UTC)
    s1 = scan_meta("r23c1", 1, tour="red", start=start, temperature_c=17.5,
                   extra={"operator": 'A "B"\n\té\\', "weather": {"wind": [1.5, 2]},
                          "log": [{"t": 1}, {"t": 2}]})
    s2 = scan_meta("r23c2", 2, start=dt.datetime(2024, 4, 8, 19, 0, 0, 250000,
                                                 tzinfo=dt.timezone(dt.timedelta(hours=2))))
    s3 = scan_meta("r40c0", 0, position="r40")
    c = default_campaign([s1, s2, s3], note="x", meta={"when": dt.date(2024, 4, 8)})
    c = dataclasses.replace(
        c, site=dataclasses.replace(c.site, extra={"altitude_m": 1415.0}),
        telescope=dataclasses.replace(c.telescope, extra={"feed": "S-band"}),
        scanner=dataclasses.replace(c.scanner, extra={"model": "Leica P20", "n": 3}))
    out = write_campaign(tmp_path / "c", c, {s.id: make_scan(s.cycle) for s in c.scans})
    assert out.root == tmp_path / "c"
    assert [s.file for s in out.scans] == ["scans/r23c1.parquet", "scans/r23c2.parquet",
                                           "scans/r40c0.parquet"]
    back = dataclasses.replace(out, root=c.root, scans=tuple(
        dataclasses.replace(s, file="") for s in out.scans))
    assert back == c
    assert out.scans[1].start.utcoffset() == dt.timedelta(hours=2)
    assert "start = 2024-04-08T18:42:00Z" in (tmp_path / "c" / "campaign.toml").read_text()
    assert load_campaign(tmp_path / "c" / "campaign.toml") == out


def test_positions_and_scan_lookup(tmp_path):
    metas = [scan_meta("a1", 1, "a"), scan_meta("b1", 1, "b"), scan_meta("a2", 2, "a")]
    c = write_campaign(tmp_path, default_campaign(metas), {m.id: make_scan(m.cycle) for m in metas})
    assert {k: [s.id for s in v] for k, v in c.positions().items()} == {"a": ["a1", "a2"],
                                                                        "b": ["b1"]}
    assert c.scan("a2").cycle == 2
    msg = error_of(c.scan, "zz")
    assert_parts(msg, "campaign.toml", "scan.id", "'zz'", "a1, b1, a2")


def test_parquet_roundtrip_bit_exact(tmp_path):
    c = make_campaign(tmp_path, cycles=(0, 1, 2))
    for s in c.scans:
        data = read_scan(c, s.id)
        same_scan(data, make_scan(s.cycle))
        assert data.n_dropped_nonfinite == 0 and len(data) == 300


def test_alt_az_campaign(tmp_path):
    c = default_campaign([ScanMeta("s1", "p1", 0, "", elevation_deg=45.0, azimuth_deg=10.0)])
    c = dataclasses.replace(c, telescope=dataclasses.replace(
        c.telescope, mount="alt-az", offset_m=1.5, ring_edges_m=None, panels_per_ring=None,
        quadrupod_azimuths_deg=None))
    out = write_campaign(tmp_path, c, {"s1": make_scan(0)})
    assert out.telescope.mount == "alt-az" and out.telescope.offset_m == 1.5
    assert out.telescope.panels_per_ring is None and out.scans[0].ha_deg is None


def test_nonfinite_rows_dropped_counted_and_reported(tmp_path, caplog):
    c = make_campaign(tmp_path)
    scan = make_scan(1)
    scan.range_m[[3, 10]] = np.nan
    scan.time_s[20] = np.inf
    scan.intensity[30] = np.nan
    write_scan_parquet(tmp_path / c.scan("r23c1").file, scan)
    with caplog.at_level(logging.WARNING):
        data = read_scan(c, "r23c1")
    assert data.n_dropped_nonfinite == 4 and len(data) == 296
    keep = np.setdiff1d(np.arange(300), [3, 10, 20, 30])
    assert np.array_equal(data.row, keep)
    same_scan(dataclasses.replace(data, n_dropped_nonfinite=0), scan.subset(keep))
    assert "r23c1.parquet: dropped 4 rows with NaN/inf values" in caplog.text


def test_parquet_nulls_count_as_nonfinite(tmp_path):
    c = make_campaign(tmp_path)
    cols = table_of(make_scan(1))
    cols["range_m"] = pa.array([None, *cols["range_m"][1:]], type=pa.float64())
    write_table(tmp_path / c.scan("r23c1").file, cols)
    data = read_scan(c, "r23c1")
    assert data.n_dropped_nonfinite == 1 and data.row[0] == 1


def test_missing_intensity_filled_with_warning(tmp_path, caplog):
    c = make_campaign(tmp_path)
    cols = table_of(make_scan(1))
    del cols["intensity"]
    write_table(tmp_path / c.scan("r23c1").file, cols)
    with caplog.at_level(logging.WARNING):
        data = read_scan(c, "r23c1")
    assert data.intensity.dtype == np.float32 and np.all(data.intensity == 0.5)
    assert "no intensity column" in caplog.text


def test_float64_intensity_accepted(tmp_path):
    c = make_campaign(tmp_path)
    cols = table_of(make_scan(1))
    cols["intensity"] = cols["intensity"].astype(np.float64)
    write_table(tmp_path / c.scan("r23c1").file, cols)
    assert read_scan(c, "r23c1").intensity.dtype == np.float32


def test_angles_within_tolerance_accepted(tmp_path):
    c = make_campaign(tmp_path)
    scan = make_scan(1)
    scan.phi_rad[0], scan.phi_rad[1] = -1e-10, PI + 1e-10
    write_scan_parquet(tmp_path / c.scan("r23c1").file, scan)
    assert len(read_scan(c, "r23c1")) == 300


def test_iter_scan_chunks_matches_read_scan(tmp_path):
    c = make_campaign(tmp_path, cycles=(1,))
    scan = make_scan(1)
    scan.range_m[[5, 150]] = np.nan
    write_scan_parquet(tmp_path / c.scan("r23c1").file, scan)
    chunks = list(iter_scan_chunks(c, "r23c1", rows_per_chunk=64))
    assert [len(ch) + ch.n_dropped_nonfinite for ch in chunks] == [64, 64, 64, 64, 44]
    whole = read_scan(c, "r23c1")
    for col in COLS:
        assert np.array_equal(np.concatenate([getattr(ch, col) for ch in chunks]),
                              getattr(whole, col))
    assert sum(ch.n_dropped_nonfinite for ch in chunks) == whole.n_dropped_nonfinite == 2


def test_input_files_never_modified(tmp_path):
    for fmt in ("parquet", "e57"):
        c = make_campaign(tmp_path / fmt, fmt=fmt)
        files = sorted(p for p in (tmp_path / fmt).rglob("*") if p.is_file())
        before = {p: (hashlib.sha256(p.read_bytes()).hexdigest(), p.stat().st_mtime_ns)
                  for p in files}
        c = load_campaign(tmp_path / fmt)
        for s in c.scans:
            read_scan(c, s)
            list(iter_scan_chunks(c, s, 100))
        after = {p: (hashlib.sha256(p.read_bytes()).hexdigest(), p.stat().st_mtime_ns)
                 for p in files}
        assert before == after
        assert sorted(p for p in (tmp_path / fmt).rglob("*") if p.is_file()) == files


def test_scandata_subset_keeps_row():
    s = make_scan(1, n=10)
    sub = s.subset(np.array([2, 7]))
    assert np.array_equal(sub.row, [2, 7]) and len(sub) == 2
    assert np.array_equal(s.subset(s.range_m > 5).row, np.flatnonzero(s.range_m > 5))


# ----------------------------------------------------------------------------- E57


def test_raw_to_e57_matches_cartesian_definitions():
    for cycle in (0, 1, 2):
        s = make_scan(cycle)
        r, phi, th = s.range_m, s.phi_rad, s.theta_rad
        xyz = np.stack([r * np.sin(th) * np.sin(phi), r * np.sin(th) * np.cos(phi),
                        r * np.cos(th)])
        az, el = raw_to_e57(phi, th)
        assert np.all((az > -PI) & (az <= PI)) and np.all(np.abs(el) <= PI / 2)
        e57_xyz = np.stack([r * np.cos(el) * np.cos(az), r * np.cos(el) * np.sin(az),
                            r * np.sin(el)])
        np.testing.assert_allclose(e57_xyz, xyz, atol=1e-12)
        r2, az2, el2 = cartesian_to_e57(*xyz)
        np.testing.assert_allclose(r2, r, rtol=1e-14)
        phi2, th2 = e57_to_raw(az2, el2, cycle)
        np.testing.assert_allclose(phi2, phi, atol=1e-12)
        np.testing.assert_allclose(th2, th, atol=1e-12)


def test_e57_face_assignment_follows_spec():
    # a direction with azimuth a = atan2(x, y) = 3/2 pi, theta0 = 1: face 2 in cycle 1, face 1
    # in cycle 2 and in cycle 0.
    az, el = raw_to_e57(np.array([1.5 * PI]), np.array([1.0]))
    assert np.allclose(e57_to_raw(az, el, 1), [[0.5 * PI], [2 * PI - 1.0]])
    assert np.allclose(e57_to_raw(az, el, 2), [[1.5 * PI], [1.0]])
    assert np.allclose(e57_to_raw(az, el, 0), [[1.5 * PI], [1.0]])


@pytest.mark.parametrize("cycle", [0, 1, 2])
def test_e57_roundtrip_two_face(tmp_path, cycle):
    c = make_campaign(tmp_path, fmt="e57", cycles=(cycle,))
    meta = c.scans[0]
    assert meta.file == f"scans/r23c{cycle}.e57"
    data, ref = read_scan(c, meta), make_scan(cycle)
    assert len(data) == len(ref) and data.n_dropped_nonfinite == 0
    np.testing.assert_allclose(data.phi_rad, ref.phi_rad, rtol=0, atol=1e-12)
    np.testing.assert_allclose(data.theta_rad, ref.theta_rad, rtol=0, atol=1e-12)
    np.testing.assert_allclose(data.range_m, ref.range_m, rtol=0, atol=1e-9)
    assert np.array_equal(data.theta_rad > PI, ref.theta_rad > PI)  # faces come back
    if cycle:
        assert 0 < np.mean(ref.theta_rad > PI) < 1
    assert np.array_equal(data.intensity, ref.intensity)
    assert np.array_equal(data.time_s, ref.time_s)
    assert np.array_equal(data.row, ref.row)


def test_e57_nonfinite_rows_dropped(tmp_path):
    scan = make_scan(1)
    scan.range_m[[4, 9]] = np.nan
    scan.phi_rad[11] = np.inf
    write_scan_e57(tmp_path / "s.e57", scan, 1)
    data = read_scan_e57(tmp_path / "s.e57", 1)
    assert data.n_dropped_nonfinite == 3
    assert np.array_equal(data.row, np.setdiff1d(np.arange(300), [4, 9, 11]))


def test_e57_cartesian_only_file(tmp_path):
    import pye57

    ref = make_scan(2)
    r, phi, th = ref.range_m, ref.phi_rad, ref.theta_rad
    xyz = {"cartesianX": r * np.sin(th) * np.sin(phi), "cartesianY": r * np.sin(th) * np.cos(phi),
           "cartesianZ": r * np.cos(th), "intensity": ref.intensity}
    with pye57.E57(str(tmp_path / "cart.e57"), mode="w") as f:
        f.write_scan_raw(xyz)  # pye57's own writer: single precision, no time
    data = read_scan_e57(tmp_path / "cart.e57", 2)
    assert len(data) == 300 and np.all(data.time_s == 0)
    np.testing.assert_allclose(data.range_m, r, rtol=1e-6)
    assert np.array_equal(data.theta_rad > PI, th > PI)
    np.testing.assert_allclose(data.phi_rad, phi, atol=1e-5)
    np.testing.assert_allclose(data.theta_rad, th, atol=1e-5)


def test_e57_wrong_scan_count(tmp_path):
    import pye57

    xyz = {k: np.ones(3) for k in ("cartesianX", "cartesianY", "cartesianZ")}
    with pye57.E57(str(tmp_path / "two.e57"), mode="w") as f:
        f.write_scan_raw(xyz)
        f.write_scan_raw(xyz)
    msg = error_of(read_scan_e57, tmp_path / "two.e57", 1)
    assert_parts(msg, "two.e57", "data3D", "expected exactly one scan, found 2")


def test_e57_truncated(tmp_path):
    c = make_campaign(tmp_path, fmt="e57", cycles=(1,))
    path = tmp_path / c.scans[0].file
    path.write_bytes(path.read_bytes()[:700])
    msg = error_of(read_scan, c, "r23c1")
    assert_parts(msg, "r23c1.e57", "file", "expected an E57 file", "truncated")


def test_e57_not_an_e57(tmp_path):
    c = make_campaign(tmp_path, fmt="e57", cycles=(1,))
    (tmp_path / c.scans[0].file).write_text("hello")
    assert_parts(error_of(read_scan, c, "r23c1"), "r23c1.e57", "file", "expected an E57 file")


# ----------------------------------------------------------------------------- bad campaign.toml


def test_missing_campaign_toml(tmp_path):
    assert_parts(error_of(load_campaign, tmp_path), "campaign.toml", "file",
                 "expected a campaign directory or its campaign.toml, not found")


def test_invalid_toml_syntax(tmp_path):
    (tmp_path / "campaign.toml").write_text('format = "hartrao-campaign/1"\n[site\n')
    assert_parts(error_of(load_campaign, tmp_path), "campaign.toml", "toml",
                 "expected valid UTF-8 TOML", "line 2")


def test_unknown_format_version(tmp_path):
    make_campaign(tmp_path)
    edit_toml(tmp_path, r'^format = .*$', 'format = "hartrao-campaign/2"')
    assert_parts(error_of(load_campaign, tmp_path), "campaign.toml", "format",
                 f"expected {FORMAT!r}", "found 'hartrao-campaign/2'")


def test_missing_format(tmp_path):
    make_campaign(tmp_path)
    edit_toml(tmp_path, r'^format = .*\n', '')
    assert_parts(error_of(load_campaign, tmp_path), "campaign.toml", ": format:",
                 "required key is missing")


def test_missing_required_key(tmp_path):
    make_campaign(tmp_path)
    edit_toml(tmp_path, r'^focal_length_m = .*\n', '')
    assert_parts(error_of(load_campaign, tmp_path), "campaign.toml", "telescope.focal_length_m",
                 "required key is missing", "expected a number")


def test_missing_table(tmp_path):
    make_campaign(tmp_path)
    edit_toml(tmp_path, r'^\[scanner\]\n(.*\n)*?\n', '')
    assert_parts(error_of(load_campaign, tmp_path), "campaign.toml", "scanner",
                 "required key is missing (expected a table)")


def test_missing_scan_key(tmp_path):
    make_campaign(tmp_path)
    edit_toml(tmp_path, r'^position = .*\n', '', count=0)
    assert_parts(error_of(load_campaign, tmp_path), "campaign.toml", "scan[0].position",
                 "required key is missing", "(scan 'r23c1')")


def test_no_scans(tmp_path):
    make_campaign(tmp_path)
    text = (tmp_path / "campaign.toml").read_text()
    (tmp_path / "campaign.toml").write_text(text[:text.index("[[scan]]")])
    assert_parts(error_of(load_campaign, tmp_path), "campaign.toml", "scan",
                 "expected at least one [[scan]] table")


def test_wrong_type_number(tmp_path):
    make_campaign(tmp_path)
    edit_toml(tmp_path, r'^latitude_deg = .*$', 'latitude_deg = "south"')
    assert_parts(error_of(load_campaign, tmp_path), "campaign.toml", "site.latitude_deg",
                 "expected a number in degrees", "found string 'south'")


def test_number_out_of_range(tmp_path):
    make_campaign(tmp_path)
    edit_toml(tmp_path, r'^latitude_deg = .*$', 'latitude_deg = -125.9')
    assert_parts(error_of(load_campaign, tmp_path), "campaign.toml", "site.latitude_deg",
                 "expected a finite number in [-90, 90]", "found -125.9")


def test_nonpositive_sigma(tmp_path):
    make_campaign(tmp_path)
    edit_toml(tmp_path, r'^sigma_range_m = .*$', 'sigma_range_m = 0')
    assert_parts(error_of(load_campaign, tmp_path), "campaign.toml", "scanner.sigma_range_m",
                 "expected a positive number in m", "found 0.0")


def test_unknown_mount(tmp_path):
    make_campaign(tmp_path)
    edit_toml(tmp_path, r'^mount = .*$', 'mount = "equatorial"')
    assert_parts(error_of(load_campaign, tmp_path), "campaign.toml", "telescope.mount",
                 'expected "ha-dec" or "alt-az"', "found 'equatorial'")


def test_ha_dec_scan_without_dec(tmp_path):
    make_campaign(tmp_path)
    edit_toml(tmp_path, r'^dec_deg = .*\n', '')
    assert_parts(error_of(load_campaign, tmp_path), "campaign.toml", "scan[0].dec_deg",
                 "required key is missing", "(scan 'r23c1')")


def test_alt_az_scan_without_elevation(tmp_path):
    make_campaign(tmp_path)
    edit_toml(tmp_path, r'^mount = .*$', 'mount = "alt-az"')
    assert_parts(error_of(load_campaign, tmp_path), "campaign.toml", "scan[0].elevation_deg",
                 "required key is missing", "expected a number in degrees")


@pytest.mark.parametrize("value, found", [("3", "found integer 3"), ('"1"', "found string '1'"),
                                          ("1.0", "found float 1.0"), ("-1", "found integer -1")])
def test_bad_cycle(tmp_path, value, found):
    make_campaign(tmp_path)
    edit_toml(tmp_path, r'^cycle = 2$', f"cycle = {value}")
    assert_parts(error_of(load_campaign, tmp_path), "campaign.toml", "scan[1].cycle",
                 "expected 0, 1 or 2", found, "(scan 'r23c2')")


def test_duplicate_scan_ids(tmp_path):
    make_campaign(tmp_path)
    edit_toml(tmp_path, r'^id = "r23c2"$', 'id = "r23c1"')
    assert_parts(error_of(load_campaign, tmp_path), "campaign.toml", "scan[1].id",
                 "expected unique scan ids", "'r23c1' is also the id of scan[0]")


def test_panels_per_ring_length_mismatch(tmp_path):
    make_campaign(tmp_path)
    edit_toml(tmp_path, r'^panels_per_ring = .*$', 'panels_per_ring = [15, 24, 30, 36, 42, 48]')
    assert_parts(error_of(load_campaign, tmp_path), "campaign.toml", "telescope.panels_per_ring",
                 "expected len(ring_edges_m) - 1 = 7 entries", "found 6")


def test_panels_per_ring_not_integers(tmp_path):
    make_campaign(tmp_path)
    edit_toml(tmp_path, r'^panels_per_ring = .*$',
              'panels_per_ring = [15.0, 24, 30, 36, 42, 48, 60]')
    assert_parts(error_of(load_campaign, tmp_path), "campaign.toml", "telescope.panels_per_ring",
                 "expected an array of integers", "found array")


def test_ring_edges_not_increasing(tmp_path):
    make_campaign(tmp_path)
    edit_toml(tmp_path, r'^ring_edges_m = .*$',
              'ring_edges_m = [1.6, 3.2, 3.2, 6.4, 8.0, 9.6, 11.2, 12.95]')
    assert_parts(error_of(load_campaign, tmp_path), "campaign.toml", "telescope.ring_edges_m",
                 "strictly increasing", "found [1.6, 3.2, 3.2")


def test_panels_without_ring_edges(tmp_path):
    make_campaign(tmp_path)
    edit_toml(tmp_path, r'^ring_edges_m = .*\n', '')
    assert_parts(error_of(load_campaign, tmp_path), "campaign.toml", "telescope.ring_edges_m",
                 "required when panels_per_ring is given")


def test_bad_start_datetime(tmp_path):
    make_campaign(tmp_path)
    edit_toml(tmp_path, r'^cycle = 1$', 'cycle = 1\nstart = 2024-04-08')
    assert_parts(error_of(load_campaign, tmp_path), "campaign.toml", "scan[0].start",
                 "expected an offset date-time such as 2024-04-08T18:42:00Z", "found date")


def test_missing_scan_file(tmp_path):
    c = make_campaign(tmp_path)
    (tmp_path / c.scan("r23c2").file).unlink()
    assert_parts(error_of(load_campaign, tmp_path), "campaign.toml", "scan[1].file",
                 "expected an existing scan file", "r23c2.parquet", "not found", "(scan 'r23c2')")


def test_scan_file_wrong_suffix(tmp_path):
    make_campaign(tmp_path)
    edit_toml(tmp_path, r'^file = "scans/r23c1.parquet"$', 'file = "scans/r23c1.ptx"')
    assert_parts(error_of(load_campaign, tmp_path), "campaign.toml", "scan[0].file",
                 "expected a .parquet or .e57 file", "found 'scans/r23c1.ptx'")


def test_scan_file_removed_after_loading(tmp_path):
    c = make_campaign(tmp_path)
    (tmp_path / c.scan("r23c1").file).unlink()
    assert_parts(error_of(read_scan, c, "r23c1"), "r23c1.parquet", "file",
                 "expected an existing Parquet scan file, not found")


# ----------------------------------------------------------------------------- bad scan tables


def test_truncated_parquet(tmp_path):
    c = make_campaign(tmp_path)
    path = tmp_path / c.scan("r23c1").file
    path.write_bytes(path.read_bytes()[:-100])
    assert_parts(error_of(read_scan, c, "r23c1"), "r23c1.parquet", ": file:",
                 "expected a Parquet file", "truncated")


def test_not_a_parquet_file(tmp_path):
    c = make_campaign(tmp_path)
    (tmp_path / c.scan("r23c1").file).write_text("range_m,phi_rad\n1,2\n")
    assert_parts(error_of(read_scan, c, "r23c1"), "r23c1.parquet", ": file:",
                 "expected a Parquet file")


def test_missing_column(tmp_path):
    c = make_campaign(tmp_path)
    cols = table_of(make_scan(1))
    del cols["theta_rad"]
    write_table(tmp_path / c.scan("r23c1").file, cols)
    assert_parts(error_of(read_scan, c, "r23c1"), "r23c1.parquet", "theta_rad",
                 "required column is missing", "found columns: range_m, phi_rad, intensity, time_s")


def test_integer_column_rejected(tmp_path):
    c = make_campaign(tmp_path)
    cols = table_of(make_scan(1))
    cols["time_s"] = np.arange(300, dtype=np.int64)
    write_table(tmp_path / c.scan("r23c1").file, cols)
    assert_parts(error_of(read_scan, c, "r23c1"), "r23c1.parquet", "time_s",
                 "expected column type float64, found int64")


def test_float32_angle_rejected(tmp_path):
    c = make_campaign(tmp_path)
    cols = table_of(make_scan(1))
    cols["phi_rad"] = cols["phi_rad"].astype(np.float32)
    write_table(tmp_path / c.scan("r23c1").file, cols)
    assert_parts(error_of(read_scan, c, "r23c1"), "r23c1.parquet", "phi_rad",
                 "expected column type float64, found float32")


def test_integer_intensity_rejected(tmp_path):
    c = make_campaign(tmp_path)
    cols = table_of(make_scan(1))
    cols["intensity"] = np.zeros(300, dtype=np.int32)
    write_table(tmp_path / c.scan("r23c1").file, cols)
    assert_parts(error_of(read_scan, c, "r23c1"), "r23c1.parquet", "intensity",
                 "expected column type float32 or float64, found int32")


@pytest.mark.parametrize("cycle, col, rows, value, text", [
    (1, "phi_rad", [7, 40], PI + 1e-6, "expected values in [0, pi) rad for cycle 1"),
    (2, "phi_rad", [12], 1.0, "expected values in [pi, 2 pi) rad for cycle 2"),
    (0, "phi_rad", [3], 2 * PI + 1e-6, "expected values in [0, 2 pi) rad for cycle 0"),
    (1, "theta_rad", [9, 10, 11], 2 * PI + 2e-9, "expected values in [0, 2 pi) rad for cycle 1"),
    (1, "theta_rad", [9], -0.5, "expected values in [0, 2 pi) rad for cycle 1"),
    (0, "theta_rad", [250], 4.0, "expected values in (0, pi) rad for cycle 0"),
])
def test_angle_out_of_range(tmp_path, cycle, col, rows, value, text):
    c = make_campaign(tmp_path, cycles=(cycle,))
    scan = make_scan(cycle)
    scan.range_m[2] = np.nan  # a dropped row before: row numbers stay those of the file
    getattr(scan, col)[rows] = value
    write_scan_parquet(tmp_path / c.scans[0].file, scan)
    assert_parts(error_of(read_scan, c, c.scans[0].id), f"r23c{cycle}.parquet", col, text,
                 f"found {len(rows)} rows outside", f"first at row {rows[0]}: {value!r}")


def test_angle_out_of_range_in_e57_write(tmp_path):
    scan = make_scan(1)
    scan.phi_rad[5] = 4.0
    assert_parts(error_of(write_scan_e57, tmp_path / "s.e57", scan, 1), "s.e57", "phi_rad",
                 "expected values in [0, pi) rad for cycle 1", "first at row 5: 4.0")
    assert not (tmp_path / "s.e57").exists()


def test_scan_data_subset_and_padding_keep_every_column():
    """A subset by index array or mask picks the same rows of every column (``row`` too);
    padding appends copies of the first row up to the bucket size and never shortens."""
    rng = np.random.default_rng(3)
    n = 50
    d = ScanData(rng.uniform(5, 15, n), rng.uniform(0, 6, n), rng.uniform(0, 1, n),
                 rng.uniform(0, 1, n).astype(np.float32), np.arange(n, dtype=float),
                 np.arange(n, dtype=np.int64) + 100)
    idx = np.array([4, 0, 49, 4])
    by_index, by_mask = d.subset(idx), d.subset(np.isin(np.arange(n), idx))
    for c in COLS:
        assert np.array_equal(getattr(by_index, c), getattr(d, c)[idx])
        assert np.array_equal(getattr(by_mask, c), getattr(d, c)[[0, 4, 49]])
    p = d.padded(64)
    assert len(p) == 64 and d.padded(50) is d and d.padded(10) is d
    for c in COLS:
        a, b = getattr(p, c), getattr(d, c)
        assert a.dtype == b.dtype
        assert np.array_equal(a[:n], b) and np.all(a[n:] == b[0])
