"""Crash-safe, strict outputs (``campaign._safeio``): strict JSON, atomic files, result
directories committed by their main JSON with a manifest, output paths checked before work.
The kill test of a whole ``fit`` is in ``tests/cli/test_reliability.py``."""

from __future__ import annotations

import hashlib
import pathlib

import numpy as np
import pytest
from helpers import temporaries

from hartrao_jax.campaign._campaign import CampaignError
from hartrao_jax.campaign._safeio import (
    OutputDir,
    check_output_path,
    dumps_strict,
    file_digest,
    loads_strict,
    strict_json,
    verify_result_dir,
    write_columns,
    write_json_atomic,
    write_table,
)


def test_strict_json_replaces_nonfinite_and_converts_numpy():
    replaced: list[str] = []
    obj = {"a": float("nan"), "b": [1.0, np.inf, np.float32(2.5)], "c": np.array([[1, 2]]),
           "d": {"e": -np.inf, 3: np.int64(4)}, "f": (np.bool_(True), None),
           "g": pathlib.Path("x/y")}
    out = strict_json(obj, replaced)
    assert out == {"a": None, "b": [1.0, None, 2.5], "c": [[1, 2]], "d": {"e": None, "3": 4},
                   "f": [True, None], "g": "x/y"}
    assert replaced == ["a", "b[1]", "d.e"]
    text = dumps_strict({"x": float("nan")})
    doc = loads_strict(text)
    assert doc["x"] is None and doc["nonfinite"]["paths"] == ["x"]
    with pytest.raises(ValueError):
        loads_strict('{"x": NaN}')
    with pytest.raises(TypeError):
        strict_json({"x": object()})


def test_write_json_atomic_leaves_no_temporaries(tmp_path):
    p = write_json_atomic(tmp_path / "sub" / "a.json", {"v": np.float64("inf")})
    assert loads_strict(p.read_text())["v"] is None
    assert [q.name for q in p.parent.iterdir()] == ["a.json"]


def test_output_dir_commit_manifest_and_verify(tmp_path):
    root = tmp_path / "r"
    with OutputDir(root, "main.json") as od:
        od.write_text("a/x.txt", "hello")
        od.write_bytes("y.bin", b"\0" * 10)
        assert not (root / "a" / "x.txt").exists()  # nothing visible before the commit
        od.commit({"schema": "t/1", "v": float("nan")})
    doc = verify_result_dir(root, "main.json")
    assert doc["files"]["a/x.txt"]["bytes"] == 5
    assert doc["files"]["y.bin"]["sha256"] == hashlib.sha256(b"\0" * 10).hexdigest()
    assert doc["v"] is None and doc["nonfinite"]["paths"] == ["v"]
    assert (root / "a" / "x.txt").read_text() == "hello"
    # a second result without y.bin: the old file listed by the old manifest goes
    with OutputDir(root, "main.json") as od:
        od.write_text("a/x.txt", "bye")
        od.commit({"schema": "t/1"})
    assert not (root / "y.bin").exists()
    assert verify_result_dir(root, "main.json")["files"].keys() == {"a/x.txt"}
    (root / "a" / "x.txt").write_text("BYE")
    with pytest.raises(CampaignError, match="sha256: content differs"):
        verify_result_dir(root, "main.json")
    (root / "a" / "x.txt").unlink()
    with pytest.raises(CampaignError, match="missing"):
        verify_result_dir(root, "main.json")


def test_output_dir_write_each_in_threads(tmp_path):
    """Files written and hashed by several threads: the same manifest as one at a time; a
    failing writer takes every file of its call with it, and the error is the writer's."""
    blobs = {f"t/{k}.bin": bytes([k]) * (1000 + k) for k in range(5)}
    docs = []
    for threads, root in ((1, tmp_path / "one"), (3, tmp_path / "three")):
        with OutputDir(root, "main.json") as od:
            paths = od.write_each([(rel, lambda t, b=b: t.write_bytes(b))
                                   for rel, b in blobs.items()], threads=threads)
            assert paths == [root / rel for rel in blobs]
            assert not any(p.exists() for p in paths)  # nothing visible before the commit
            od.commit({"schema": "t/1"})
        docs.append(verify_result_dir(root, "main.json")["files"])
    assert docs[0] == docs[1]
    assert docs[0]["t/3.bin"] == {"bytes": 1003,
                                  "sha256": hashlib.sha256(b"\3" * 1003).hexdigest()}

    def bad(t):
        t.write_bytes(b"half")
        raise OSError("disk full")

    root = tmp_path / "three"
    with pytest.raises(OSError, match="disk full"):
        with OutputDir(root, "main.json") as od:
            od.write_each([("t/0.bin", lambda t: t.write_bytes(b"new")), ("t/9.bin", bad)],
                          threads=2)
    assert verify_result_dir(root, "main.json")["files"] == docs[1]  # the old result stands
    assert not temporaries(root)


@pytest.mark.parametrize("direct", ["1", "0"])
def test_digest_taken_while_writing(tmp_path, monkeypatch, direct):
    """A Parquet table hashed as it is written (``_files.HashingFile``: around the page cache
    through a small aligned buffer here, or through the page cache, its pages handed to the
    writeback every few bytes) has the manifest entry of the file read back, reads back
    whole, and an :class:`OutputDir` lists it; a writer's digest that does not match the
    file's size is not trusted (the file is read)."""
    import pyarrow.parquet as pq

    from hartrao_jax import _files

    monkeypatch.setenv(_files.DIRECT_WRITES_ENV, direct)
    monkeypatch.setattr(_files, "WRITEBACK_BYTES", 4096)
    monkeypatch.setattr(_files, "DIRECT_BYTES", 1 << 16)
    rng = np.random.default_rng(0)
    cols = {"a": rng.normal(size=(50_000, 3))[:, 1], "b": np.arange(50_000)}
    got = write_columns(cols, tmp_path / "t.parquet", row_group_rows=8192)
    assert got.entry() == file_digest(tmp_path / "t.parquet")
    back = pq.read_table(tmp_path / "t.parquet")
    assert np.array_equal(back.column("a").to_numpy(), cols["a"])
    assert np.array_equal(back.column("b").to_numpy(), cols["b"])

    def lying(t):
        t.write_bytes(b"abc")
        return _files.FileDigest(4, "0" * 64)

    with OutputDir(tmp_path / "r", "main.json") as od:
        od.write_each([("t.parquet", lambda t: write_columns(cols, t, row_group_rows=8192)),
                       ("x.bin", lying)])
        od.commit({"schema": "t/1"})
    files = verify_result_dir(tmp_path / "r", "main.json")["files"]
    assert files["t.parquet"] == got.entry()
    assert files["x.bin"] == {"bytes": 3, "sha256": hashlib.sha256(b"abc").hexdigest()}



def test_hashing_file_of_any_length_reads_back_the_same(tmp_path, monkeypatch):
    """Every length, writes of any size: the file holds the bytes written and its digest,
    whether written around the page cache (whole buffers, whole blocks of the rest, then its
    last bytes) or through it; a file system that opens ``O_DIRECT`` but refuses the write
    gets the same file through the page cache."""
    import errno
    import os

    from hartrao_jax import _files

    monkeypatch.setattr(_files, "DIRECT_BYTES", 1 << 14)
    data = np.random.default_rng(1).bytes(3 * (1 << 14) + 4096 + 77)
    for direct in ("1", "0"):
        monkeypatch.setenv(_files.DIRECT_WRITES_ENV, direct)
        for n in (0, 1, 4095, 4096, 1 << 14, (1 << 14) + 1, len(data)):
            path = tmp_path / f"f{direct}-{n}.bin"
            with _files.HashingFile(path) as f:
                for a in range(0, n, 5000):
                    f.write(data[a:min(n, a + 5000)])
            assert path.read_bytes() == data[:n]
            assert f.digest == _files.FileDigest(n, hashlib.sha256(data[:n]).hexdigest())

    monkeypatch.setenv(_files.DIRECT_WRITES_ENV, "1")
    real_write, refused = os.write, []

    def refuse_direct(fd, b):
        fcntl = _files.fcntl
        if fcntl is not None and hasattr(os, "O_DIRECT") and (
                fcntl.fcntl(fd, fcntl.F_GETFL) & os.O_DIRECT):
            refused.append(fd)
            raise OSError(errno.EINVAL, "Invalid argument")
        return real_write(fd, b)

    monkeypatch.setattr(_files.os, "write", refuse_direct)
    with _files.HashingFile(tmp_path / "refused.bin") as f:
        f.write(data)
    assert (tmp_path / "refused.bin").read_bytes() == data
    assert f.digest.sha256 == hashlib.sha256(data).hexdigest()
    assert len(refused) <= 1  # refused once (where opened so), then the page cache

def test_parquet_codec_per_column(tmp_path):
    """Both writers store floating-point columns without a codec and integer and boolean ones
    with Snappy (``parquet_codecs``), an explicit ``compression`` wins, and every value
    reads back as written."""
    import pyarrow as pa
    import pyarrow.parquet as pq

    rng = np.random.default_rng(1)
    cols = {"x_m": rng.normal(size=20_000), "i": np.float32(rng.normal(size=20_000)),
            "row": np.arange(20_000), "used": rng.random(20_000) > 0.1,
            "face": np.int8(rng.integers(1, 3, 20_000))}
    want = {"x_m": "UNCOMPRESSED", "i": "UNCOMPRESSED", "row": "SNAPPY", "used": "SNAPPY",
            "face": "SNAPPY"}

    def codecs(path):
        rg = pq.ParquetFile(path).metadata.row_group(0)
        return {rg.column(k).path_in_schema: rg.column(k).compression
                for k in range(rg.num_columns)}

    write_columns(cols, tmp_path / "a.parquet", row_group_rows=4096)
    write_table(pa.table(cols), tmp_path / "b.parquet")
    write_table(pa.table(cols), tmp_path / "c.parquet", compression="zstd")
    assert codecs(tmp_path / "a.parquet") == want == codecs(tmp_path / "b.parquet")
    assert set(codecs(tmp_path / "c.parquet").values()) == {"ZSTD"}
    for name in ("a", "b", "c"):
        back = pq.read_table(tmp_path / f"{name}.parquet")
        for k, v in cols.items():
            got = back.column(k).to_numpy()
            assert got.dtype == v.dtype and np.array_equal(got, v)


def test_columns_without_nulls_are_written_required(tmp_path):
    """Both writers declare every column without a null required (no definition levels in
    the file), keep a column with nulls optional with its nulls, and read back every value
    (NaN included) as written."""
    import pyarrow as pa
    import pyarrow.parquet as pq

    rng = np.random.default_rng(2)
    x = rng.normal(size=5000)
    x[7] = np.nan  # a value, not a null
    cols = {"x_m": x, "row": np.arange(5000), "used": rng.random(5000) > 0.5}
    holes = pa.array([1.0, None, 3.0] * 1000)

    write_columns(cols, tmp_path / "a.parquet", row_group_rows=1024)
    write_table(pa.table(cols), tmp_path / "b.parquet")
    write_table(pa.table({"x_m": x[:3000], "holes": holes}), tmp_path / "c.parquet")
    for name in ("a", "b"):
        back = pq.read_table(tmp_path / f"{name}.parquet")
        assert [f.nullable for f in back.schema] == [False] * 3
        for k, v in cols.items():
            assert np.array_equal(back.column(k).to_numpy(), v, equal_nan=v.dtype.kind == "f")
    back = pq.read_table(tmp_path / "c.parquet")
    assert [f.nullable for f in back.schema] == [False, True]
    assert back.column("holes").null_count == 1000
    assert back.column("holes").to_pylist() == holes.to_pylist()


def test_output_dir_abort_keeps_the_previous_result(tmp_path):
    root = tmp_path / "r"
    with OutputDir(root, "main.json") as od:
        od.write_text("x.txt", "old")
        od.commit({"schema": "t/1"})
    with pytest.raises(RuntimeError, match="boom"):
        with OutputDir(root, "main.json") as od:
            od.write_text("x.txt", "new")
            raise RuntimeError("boom")
    assert verify_result_dir(root, "main.json")
    assert (root / "x.txt").read_text() == "old"
    assert sorted(p.name for p in root.rglob("*")) == ["main.json", "x.txt"]


def test_stale_temporaries_of_dead_writers_are_removed(tmp_path):
    root = tmp_path / "r"
    root.mkdir()
    stale = root / ".x.txt.tmp-999999999-0123abcd"
    stale.write_text("left by a killed writer")
    with OutputDir(root, "main.json") as od:
        od.write_text("x.txt", "new")
        od.commit({})
    assert not stale.exists()


def test_check_output_path(tmp_path):
    (tmp_path / "f").write_text("x")
    check_output_path(tmp_path / "new" / "deeper", "--out")
    check_output_path(tmp_path / "new.json", "--json", kind="file")
    with pytest.raises(CampaignError, match="--out: .*regular file"):
        check_output_path(tmp_path / "f" / "sub", "--out")
    with pytest.raises(CampaignError, match="--out: .*is a regular file, expected a directory"):
        check_output_path(tmp_path / "f", "--out")
    with pytest.raises(CampaignError, match="--json: .*is a directory"):
        check_output_path(tmp_path, "--json", kind="file")
