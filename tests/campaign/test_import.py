"""Import of real recordings: PTX, XYZ, E57 -> one-face campaign (cycle 0)."""

from __future__ import annotations

import math

import numpy as np
import pytest
from helpers import real_gbt_file

from hartrao_jax.campaign._campaign import CampaignError, load_campaign, read_scan
from hartrao_jax.campaign._import import (
    DEFAULT_INTENSITY,
    LEICA_EXPORT_SCANNER,
    ImportedScan,
    _altaz_to_hadec,
    grid_angular_step,
    import_file,
    iter_ptx,
    nn_angular_step,
    read_ptx,
    read_xyz,
    telescope_preset,
    to_scan_data,
)
from hartrao_jax.cli._import import import_command

HEADER = """{cols}
{rows}
1.5 2.5 3.5
1 0 0
0 1 0
0 0 1
0.5 0.8 0 0
-0.8 0.5 0 0
0 0 1 0
10 20 30 1
"""


def ptx_text(cols, rows, cells):
    """One PTX scan: header then one line per cell (column-major)."""
    assert len(cells) == cols * rows
    return HEADER.format(cols=cols, rows=rows) + "".join(c + "\n" for c in cells)


def write(tmp_path, name, text):
    p = tmp_path / name
    p.write_text(text)
    return p


# 2 columns x 3 rows; cells 1 and 4 are missing ("0 0 0" with and without intensity)
CELLS = ["1 2 -3 0.1", "0 0 0 0.5", "2 1 -3 0.3", "-1 2 -3 0.4", "0 0 0", "1 -2 -3 0.6"]


def eq2(r, phi, theta):
    """Seed eq. (2), written out in NumPy."""
    st = np.sin(theta)
    return np.stack([r * st * np.sin(phi), r * st * np.cos(phi), r * np.cos(theta)], axis=-1)


# ----------------------------------------------------------------------------- PTX


def test_ptx_header_and_missing_returns(tmp_path):
    p = write(tmp_path, "a.ptx", ptx_text(2, 3, CELLS))
    (s,) = read_ptx(p)
    h = s.header
    assert (h["columns"], h["rows"]) == (2, 3)
    assert h["scanner_position"] == [1.5, 2.5, 3.5]
    assert h["scanner_axes"] == [[1, 0, 0], [0, 1, 0], [0, 0, 1]]
    assert h["transform"][3] == [10, 20, 30, 1]  # as written: Leica puts the translation last
    assert h["transform"][0] == [0.5, 0.8, 0, 0]
    assert (h["n_cells"], h["n_missing"], h["n_points"], h["truncated"]) == (6, 2, 4, False)
    assert (h["first_line"], h["first_data_line"], h["last_data_line"]) == (1, 11, 16)
    # missing cells dropped, the others keep their cell index and (row, col)
    np.testing.assert_array_equal(s.row, [0, 2, 3, 5])
    np.testing.assert_array_equal(s.grid, [[0, 0], [2, 0], [0, 1], [2, 1]])
    np.testing.assert_array_equal(s.xyz, [[1, 2, -3], [2, 1, -3], [-1, 2, -3], [1, -2, -3]])
    np.testing.assert_allclose(s.intensity, [0.1, 0.3, 0.4, 0.6], rtol=1e-6)
    assert s.intensity.dtype == np.float32 and s.xyz.dtype == np.float64
    # column-major time: col * period + row / rows * period
    np.testing.assert_allclose(s.time_s, [0.0, 2 / 3 * 0.1, 0.1, 0.1 + 2 / 3 * 0.1])
    assert h["angular_step_rad"] > 0


def test_ptx_points_used_as_written_not_transformed(tmp_path):
    p = write(tmp_path, "a.ptx", ptx_text(2, 3, CELLS))
    d = to_scan_data(read_ptx(p)[0])
    # the first point (1, 2, -3): phi = atan2(x, y), theta from the file's own +z axis
    assert d.range_m[0] == pytest.approx(math.sqrt(14))
    assert d.phi_rad[0] == pytest.approx(math.atan2(1, 2))
    assert d.theta_rad[0] == pytest.approx(math.acos(-3 / math.sqrt(14)))


def test_ptx_line_period_and_chunking(tmp_path):
    rng = np.random.default_rng(3)
    cols, rows = 7, 5
    pts = rng.normal(size=(cols * rows, 3))
    cells = [f"{x:.6f} {y:.6f} {z:.6f} 0.25" for x, y, z in pts]
    for i in (0, 4, 5, 17, 34):
        cells[i] = "0 0 0"
    p = write(tmp_path, "c.ptx", ptx_text(cols, rows, cells))
    ref = read_ptx(p, line_period_s=0.2)[0]
    for chunk in (1, 2, 3, 10):
        s = read_ptx(p, chunk_rows=chunk, line_period_s=0.2)[0]
        np.testing.assert_array_equal(s.xyz, ref.xyz)
        np.testing.assert_array_equal(s.row, ref.row)
        np.testing.assert_array_equal(s.time_s, ref.time_s)
    col, row = np.divmod(ref.row, rows)
    np.testing.assert_allclose(ref.time_s, 0.2 * col + 0.2 * row / rows)
    assert len(ref) == cols * rows - 5


def test_ptx_rgb_and_three_field_points(tmp_path):
    rgb = ["1 2 -3 0.1 10 20 30", "0 0 0", "2 1 -3 0.3 1 2 3", "0 0 0 0.5 0 0 0"]
    (s,) = read_ptx(write(tmp_path, "rgb.ptx", ptx_text(2, 2, rgb)))
    assert s.header["fields"] == "x y z intensity r g b"
    np.testing.assert_allclose(s.intensity, [0.1, 0.3], rtol=1e-6)
    (s,) = read_ptx(write(tmp_path, "xyz.ptx", ptx_text(1, 3, ["1 2 3", "0 0 0", "3 2 1"])))
    assert s.header["fields"] == "x y z"
    np.testing.assert_array_equal(s.intensity, [DEFAULT_INTENSITY] * 2)


def test_ptx_multi_scan(tmp_path):
    text = ptx_text(2, 3, CELLS) + "\n" + ptx_text(1, 2, ["4 5 -6 0.9", "0 0 0 0.5"])
    scans = read_ptx(write(tmp_path, "m.ptx", text))
    assert [len(s) for s in scans] == [4, 1]
    assert [s.header["scan_index"] for s in scans] == [0, 1]
    assert scans[1].header["first_line"] == 18  # after 16 lines of scan 1 and a blank line
    np.testing.assert_array_equal(scans[1].xyz, [[4, 5, -6]])
    np.testing.assert_array_equal(scans[1].grid, [[0, 0]])
    # streaming gives the same scans one at a time
    assert [len(s) for s in iter_ptx(tmp_path / "m.ptx", chunk_rows=1)] == [4, 1]


@pytest.mark.parametrize("lines, line_no, expected", [
    # wrong header counts
    ({0: "3722 2412"}, 1, "expected the number of columns of scan 1 (one positive integer), "
                          "found 2 fields"),
    ({1: "3.5"}, 2, "expected the number of rows of scan 1 (one positive integer), found '3.5'"),
    ({2: "0 0"}, 3, "expected the scanner position (3 numbers), found 2 fields: '0 0'"),
    ({4: "0 1 0 0"}, 5, "expected scanner axis 2 (3 numbers), found 4 fields"),
    ({8: "0 0 1"}, 9, "expected row 3 of the 4x4 transform (4 numbers), found 3 fields"),
    ({3: "1 zero 0"}, 4, "expected scanner axis 1 (3 numbers), found 'zero' in field 2"),
    # bad grid lines (data lines start at line 11)
    ({12: "2 1 -3"}, 13, "expected 4 numbers per grid point (x y z intensity) or '0 0 0' for a "
                         "missing return, found 3 (short row): '2 1 -3'"),
    ({13: "-1 2"}, 14, "found 2 (short row)"),
    ({13: "-1 2 -3 0.4 7"}, 14, "found 5: '-1 2 -3 0.4 7'"),
    ({12: ""}, 13, "found an empty line"),
    ({12: "2 1 abc 0.3"}, 13, "expected a number in field 3, found 'abc'"),
    ({15: "1 -2 -3 0,6"}, 16, "expected a number in field 4, found '0,6'"),
    ({10: "1 2 -3 0.1 5 6"}, 11, "expected 3 (x y z), 4 (x y z intensity) or 7"),
    ({10: "1 2"}, 11, "found 2 (short row): '1 2'"),
    ({10: ""}, 11, "found an empty line"),
])
def test_ptx_bad_lines_name_the_line(tmp_path, lines, line_no, expected):
    text = ptx_text(2, 3, CELLS).splitlines()
    for i, v in lines.items():
        text[i] = v
    p = write(tmp_path, "bad.ptx", "\n".join(text) + "\n")
    for chunk in (1, 4, 1000):
        with pytest.raises(CampaignError) as e:
            read_ptx(p, chunk_rows=chunk)
        assert e.value.file == str(p)
        assert e.value.field == f"line {line_no}"
        assert expected in e.value.message
        assert str(e.value).startswith(f"{p}: line {line_no}: expected")


def test_ptx_extra_lines_after_grid(tmp_path):
    p = write(tmp_path, "x.ptx", ptx_text(2, 3, CELLS) + "1 2 3 0.5\n")
    with pytest.raises(CampaignError, match=r"line 17: expected the number of columns of scan 2 "
                       r"\(scan 1 of 2 x 3 grid points ended at line 16\)"):
        read_ptx(p)


def test_ptx_truncated_synthetic(tmp_path):
    p = write(tmp_path, "t.ptx", ptx_text(2, 3, CELLS)[:-len(CELLS[-1]) - 1])  # last cell cut
    with pytest.raises(CampaignError, match=r"line 16: expected grid point 6 of 6 \(2 columns x "
                       r"3 rows\) of scan 1, found the end of the file \(truncated\)"):
        read_ptx(p)
    (s,) = read_ptx(p, allow_truncated=True)
    assert s.header["truncated"] and s.header["n_cells_read"] == 5 and len(s) == 3
    p = write(tmp_path, "h.ptx", "".join(HEADER.format(cols=2, rows=3).splitlines(True)[:6]))
    with pytest.raises(CampaignError, match=r"line 7: expected row 1 of the 4x4 transform, "
                       r"found the end of the file"):
        read_ptx(p)
    with pytest.raises(CampaignError, match="line 3: expected the number of columns of scan 1 "
                       r"\(a PTX header\), found the end of a blank file"):
        read_ptx(write(tmp_path, "blank.ptx", "\n\n"))
    with pytest.raises(CampaignError, match="line 1: expected the number of columns"):
        read_ptx(write(tmp_path, "empty.ptx", ""))


def test_ptx_crlf(tmp_path):
    p = tmp_path / "w.ptx"
    p.write_bytes(ptx_text(2, 3, CELLS).replace("\n", "\r\n").encode())
    (s,) = read_ptx(p)
    assert len(s) == 4 and s.header["scanner_position"] == [1.5, 2.5, 3.5]


def test_grid_angular_step():
    cols, rows, step = 4, 6, 1e-3
    c, r = np.meshgrid(np.arange(cols), np.arange(rows), indexing="ij")
    phi, theta = 0.3 + c.ravel() * step, 2.0 + r.ravel() * step
    xyz = eq2(30.0, phi, theta)
    cell = np.arange(cols * rows)
    keep = cell % 5 != 2
    assert grid_angular_step(xyz[keep], cell[keep], rows) == pytest.approx(step, rel=0.2)


# ----------------------------------------------------------------------------- XYZ


@pytest.mark.parametrize("text, intensity", [
    ("1,2,-3\n2,1,-3\n-1,2,-3\n", None),
    ("1, 2, -3\n2, 1, -3\n\n-1, 2, -3\n", None),
    ("1 2 -3\n2\t1  -3\n  -1 2 -3  \n", None),
    ("1;2;-3;0.1\n2;1;-3;0.2\n-1;2;-3;0.3\n", [0.1, 0.2, 0.3]),
    ("1 2 -3 0.1\n2 1 -3 0.2\n-1 2 -3 0.3\n", [0.1, 0.2, 0.3]),
    ("x,y,z\n1,2,-3\n2,1,-3\n-1,2,-3\n", None),
    ("# exported\nX Y Z Intensity\n1 2 -3 0.1\n2 1 -3 0.2\n-1 2 -3 0.3\n", [0.1, 0.2, 0.3]),
    ("intensity,z,x,y\n0.1,-3,1,2\n0.2,-3,2,1\n0.3,-3,-1,2\n", [0.1, 0.2, 0.3]),
    ("1 2 -3 0.1 9 9 9\n2 1 -3 0.2 9 9 9\n-1 2 -3 0.3 9 9 9\n", [0.1, 0.2, 0.3]),
])
def test_xyz_variants(tmp_path, text, intensity):
    p = write(tmp_path, "a.xyz", text)
    for chunk in (1, 2, 1000):
        s = read_xyz(p, chunk_rows=chunk, dt_s=0.5)
        np.testing.assert_array_equal(s.xyz, [[1, 2, -3], [2, 1, -3], [-1, 2, -3]])
        want = [DEFAULT_INTENSITY] * 3 if intensity is None else intensity
        np.testing.assert_allclose(s.intensity, want, rtol=1e-6)
        np.testing.assert_array_equal(s.time_s, [0.0, 0.5, 1.0])
        np.testing.assert_array_equal(s.row, [0, 1, 2])
        assert s.grid is None


def test_xyz_zero_points_and_intensity_scale(tmp_path):
    s = read_xyz(write(tmp_path, "z.txt", "1 2 3 0\n0 0 0 10\n4 5 6 255\n"))
    assert s.header["n_zero_dropped"] == 1 and len(s) == 2
    np.testing.assert_array_equal(s.row, [0, 2])
    np.testing.assert_allclose(s.intensity, [0.0, 1.0])
    assert s.header["intensity_scaled_from"] == [0.0, 255.0]


@pytest.mark.parametrize("text, line_no, expected", [
    ("1,2,3\n4,5\n", 2, "expected 3 fields as on line 1, found 2 (short row): '4,5'"),
    ("x y z\n1 2 3\n4 5 6\n7 8\n", 4, "expected 3 fields as on the header, found 2 (short row)"),
    ("1 2 3\n4 5 six\n", 2, "expected a number in field 3, found 'six'"),
    ("1,2,3\n4,,6\n", 2, "expected a number in field 2, found an empty field"),
    ("1,2,3\n4,5,6,\n", 2, "expected a number in field 4, found an empty field"),
    ("\n\n1 2 3 4 5\n", 3, "expected 3 (x y z), 4 (x y z intensity) or 7 (x y z intensity r g b) "
                           "fields, found 5"),
    ("", 1, "expected x y z [intensity] points, found an empty file"),
])
def test_xyz_bad_lines(tmp_path, text, line_no, expected):
    p = write(tmp_path, "bad.csv", text)
    with pytest.raises(CampaignError) as e:
        read_xyz(p, chunk_rows=1)
    assert (e.value.file, e.value.field) == (str(p), f"line {line_no}")
    assert expected in e.value.message


def test_nn_angular_step():
    rng = np.random.default_rng(0)
    step = 2e-3
    c, r = np.meshgrid(np.arange(60), np.arange(50), indexing="ij")
    xyz = eq2(40.0, 1.0 + c.ravel() * step, 2.2 + r.ravel() * step)
    assert nn_angular_step(rng.permutation(xyz)) == pytest.approx(step, rel=0.2)
    assert nn_angular_step(xyz, max_points=500) == pytest.approx(step, rel=0.2)
    assert nn_angular_step(xyz[:1]) is None


# ----------------------------------------------------------------------------- conversion


def test_conversion_round_trip():
    rng = np.random.default_rng(7)
    xyz = rng.normal(size=(5000, 3)) * rng.uniform(0.5, 80, size=(5000, 1))
    xyz[:4] = [[0, 1, 0], [0, -1, 0], [1e-12, 5, -1], [0, 0, -3]]  # axes, phi near 0 and 2 pi
    s = to_scan_data(ImportedScan(xyz, np.full(len(xyz), 0.5), np.zeros(len(xyz)), None))
    assert s.range_m.dtype == np.float64 and s.intensity.dtype == np.float32
    assert ((s.phi_rad >= 0) & (s.phi_rad < 2 * np.pi)).all()
    assert ((s.theta_rad >= 0) & (s.theta_rad <= np.pi)).all()
    np.testing.assert_allclose(eq2(s.range_m, s.phi_rad, s.theta_rad), xyz, rtol=0, atol=1e-9)


# ----------------------------------------------------------------------------- presets, pointing


def test_presets(tmp_path):
    site, tel, sc = telescope_preset("gbt")
    assert (tel.mount, tel.focal_length_m, tel.diameter_m, tel.offset_m) == ("alt-az", 60, 100, 54)
    assert tel.panels_per_ring is None and tel.quadrupod_azimuths_deg is None
    assert tel.cone_radius_m == 0.0
    assert (site.latitude_deg, site.longitude_deg) == (38.433, -79.84)
    assert sc == LEICA_EXPORT_SCANNER
    assert sc.sigma_range_m == 0.0008 and sc.sigma_angle_rad == 1.5e-5
    site, tel, _ = telescope_preset("HartRAO")
    assert (tel.mount, tel.focal_length_m, tel.diameter_m) == ("ha-dec", 10.9816, 25.9)
    assert sum(tel.panels_per_ring) == 255 and site.latitude_deg == -25.8897
    toml = write(tmp_path, "t.toml", 'preset = "hartrao"\n[telescope]\nmount = "alt-az"\n'
                 'diameter_m = 12.0\nfocal_length_m = 4.8\ncone_radius_m = 0.5\n'
                 '[scanner]\nsigma_range_m = 0.001\n')
    site, tel, sc = telescope_preset(toml)
    assert (tel.diameter_m, tel.focal_length_m, tel.offset_m) == (12.0, 4.8, 0.0)
    assert site.name == "Hartebeesthoek"
    assert (sc.sigma_range_m, sc.sigma_angle_rad) == (0.001, 1.5e-5)
    bad = write(tmp_path, "b.toml", "[site]\nlatitude_deg = 10.0\n")
    with pytest.raises(CampaignError, match=r"b.toml: telescope: required table is missing"):
        telescope_preset(bad)
    bad = write(tmp_path, "c.toml", '[telescope]\nmount = "azimuthal"\ndiameter_m = 1\n')
    with pytest.raises(CampaignError, match=r"c.toml: telescope.mount: expected"):
        telescope_preset(bad)
    with pytest.raises(CampaignError, match="expected 'gbt', 'hartrao' or a TOML file"):
        telescope_preset("arecibo")


@pytest.mark.parametrize("el, az", [(90.0, 0.0), (40.0, 100.0), (15.0, 200.0), (70.0, 330.0)])
def test_altaz_to_hadec_same_boresight(el, az):
    from hartrao_jax.geometry._geometry import telescope_axes_altaz, telescope_axes_hadec

    lat = -25.8897
    ha, dec = _altaz_to_hadec(el, az, lat)
    b1 = np.asarray(telescope_axes_altaz(np.radians(el), np.radians(az)))[:, 2]
    b2 = np.asarray(telescope_axes_hadec(np.radians(ha), np.radians(dec), np.radians(lat)))[:, 2]
    np.testing.assert_allclose(b1, b2, atol=1e-5)


# ----------------------------------------------------------------------------- import_file


def test_import_ptx_campaign(tmp_path):
    text = ptx_text(2, 3, CELLS) + ptx_text(1, 2, ["4 5 -6 0.9", "0 0 0 0.5"])
    p = write(tmp_path, "m.ptx", text)
    import_file(p, "ptx", tmp_path / "camp", elevation_deg=45.0, azimuth_deg=10.0)
    c2 = load_campaign(tmp_path / "camp")
    assert [s.id for s in c2.scans] == ["p1-1c0", "p1-2c0"]
    assert [s.position for s in c2.scans] == ["p1-1", "p1-2"]
    s0 = c2.scans[0]
    assert s0.cycle == 0 and s0.elevation_deg == 45.0 and s0.azimuth_deg == 10.0
    assert "elevation_assumed" not in s0.extra
    assert s0.extra["ptx_transform"][3] == [10.0, 20.0, 30.0, 1.0]
    assert s0.extra["ptx_scanner_position"] == [1.5, 2.5, 3.5]
    assert s0.extra["source_format"] == "ptx" and "z up" in s0.extra["frame"]
    assert c2.telescope.name == "GBT 100-m" and c2.extra["import"]["format"] == "ptx"
    ref = to_scan_data(read_ptx(p)[0])
    d = read_scan(c2, s0)
    for k in ("range_m", "phi_rad", "theta_rad", "intensity", "time_s"):
        np.testing.assert_array_equal(getattr(d, k), getattr(ref, k))
    with pytest.raises(CampaignError, match="campaign.toml: file: expected a new campaign"):
        import_file(p, "ptx", tmp_path / "camp")
    import_file(p, "ptx", tmp_path / "camp", overwrite=True)


def test_import_skips_scans_without_points(tmp_path):
    text = ptx_text(1, 2, ["0 0 0", "0 0 0"]) + ptx_text(2, 3, CELLS)
    c = import_file(write(tmp_path, "m.ptx", text), "ptx", tmp_path / "camp")
    assert [s.id for s in c.scans] == ["p1-2c0"] and c.scans[0].extra["ptx_scan_index"] == 2
    with pytest.raises(CampaignError, match="points: expected at least one point, found none"):
        import_file(write(tmp_path, "e.ptx", ptx_text(1, 2, ["0 0 0", "0 0 0 0.5"])), "ptx",
                    tmp_path / "camp2")


def test_import_pointing_defaults(tmp_path):
    p = write(tmp_path, "a.xyz", "1 2 -3\n2 1 -3\n-1 2 -3\n")
    c = import_file(p, None, tmp_path / "a", position="r1")
    s = c.scans[0]
    assert (s.id, s.elevation_deg, s.azimuth_deg) == ("r1c0", 90.0, 0.0)
    assert s.extra["elevation_assumed"] is True and s.extra["azimuth_assumed"] is True
    c = import_file(p, "xyz", tmp_path / "b", telescope="hartrao")
    s = c.scans[0]
    assert (s.ha_deg, s.dec_deg) == (0.0, -25.8897) and s.extra["elevation_assumed"] is True
    with pytest.raises(ValueError, match="position"):
        import_file(p, "xyz", tmp_path / "c", position="a b")


def test_import_e57(tmp_path):
    pytest.importorskip("pye57")
    from hartrao_jax.campaign._campaign import write_scan_e57

    rng = np.random.default_rng(1)
    xyz = rng.normal(size=(200, 3)) * 5
    s = to_scan_data(ImportedScan(xyz, np.full(200, 0.3), np.arange(200) * 1e-3, None))
    write_scan_e57(tmp_path / "t.e57", s, 0)
    c = import_file(tmp_path / "t.e57", None, tmp_path / "camp")
    d = read_scan(c, c.scans[0])
    np.testing.assert_allclose(eq2(d.range_m, d.phi_rad, d.theta_rad), xyz, atol=1e-9)


def test_cli(tmp_path):
    from click.testing import CliRunner

    p = write(tmp_path, "a.ptx", ptx_text(2, 3, CELLS))
    r = CliRunner().invoke(import_command, [str(p), "--format", "ptx", "--out",
                                            str(tmp_path / "c"), "--elevation-deg", "30"])
    assert r.exit_code == 0, r.output
    assert "p1c0: 4 points" in r.output
    assert load_campaign(tmp_path / "c").scans[0].elevation_deg == 30.0
    bad = write(tmp_path, "b.ptx", ptx_text(2, 3, CELLS).replace("2 1 -3 0.3", "2 1"))
    r = CliRunner().invoke(import_command, [str(bad), "--out", str(tmp_path / "d")])
    assert r.exit_code == 2 and "b.ptx: line 13: expected 4 numbers" in r.output


# ----------------------------------------------------------------------------- real files


def real(name):
    """$HARTRAO_REAL_DATA/gbt-lassi/<name>: skipped (saying where to get it) when absent."""
    return real_gbt_file(name)


def test_real_scan10_import(tmp_path):
    p = real("scan10_random_sample.csv")
    c = import_file(p, "xyz", tmp_path / "gbt", telescope="gbt")
    c = load_campaign(tmp_path / "gbt")
    (meta,) = c.scans
    assert meta.cycle == 0 and meta.extra["elevation_assumed"] is True
    assert c.telescope.offset_m == 54.0 and c.site.latitude_deg == 38.433
    d = read_scan(c, meta)
    assert len(d) == 56050 and d.n_dropped_nonfinite == 0
    np.testing.assert_allclose(d.intensity, DEFAULT_INTENSITY)
    xyz = np.loadtxt(p, delimiter=",")
    np.testing.assert_allclose(eq2(d.range_m, d.phi_rad, d.theta_rad), xyz, atol=1e-9)
    # the scanner (z up) looks down on the dish: most points lie below its horizon
    assert np.median(d.theta_rad) > np.pi / 2
    assert 1e-5 < c.scanner.angular_step_rad < 0.05


def test_real_bump1_reads():
    s = read_xyz(real("bump1_high_sample.csv"))
    assert len(s) == 32974 and s.header["fields"] == "x y z"


def test_real_ptx_header_example_is_truncated():
    p = real("ptx_header_example.ptx")
    # 3722 x 2412 cells announced, 13 present: an error by default, naming the missing line
    with pytest.raises(CampaignError) as e:
        read_ptx(p)
    assert e.value.field == "line 24"
    assert "expected grid point 14 of 8977464 (3722 columns x 2412 rows)" in e.value.message
    assert "truncated" in e.value.message
    # or read what is there
    (s,) = read_ptx(p, allow_truncated=True)
    h = s.header
    assert (h["columns"], h["rows"], h["n_cells_read"], h["n_missing"]) == (3722, 2412, 13, 5)
    assert h["truncated"] and h["transform"][3] == [1002.60065, 1994.265734, 148.994888, 1.0]
    np.testing.assert_array_equal(s.grid[:, 0], [3, 4, 5, 6, 7, 10, 11, 12])
    np.testing.assert_array_equal(s.grid[:, 1], 0)
    np.testing.assert_allclose(s.xyz[0], [26.456772, -18.582199, -44.610275])
    assert s.intensity[0] == pytest.approx(0.024292)
