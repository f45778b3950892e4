"""The baked-table container: round trip, damage detection and atomic writes."""
from __future__ import annotations

import json
import zipfile
import subprocess
import sys
import textwrap
from pathlib import Path

import numpy as np
import pytest

from usdfiber import table_format as T
from usdfiber.table_format import TableError, read_header, read_table, write_table

REPO = Path(__file__).resolve().parents[2]


def header() -> dict:
    return {
        "geometry_key": "ab" * 32,
        "inputs": {"profile_family": "round", "eta": 1.635, "beta": 3.1, "units": {"beta": "deg"}},
        "resolution": {"theta": 45, "phi": 180},
        "photons": 1_000_000,
        "error_estimate": 0.01,
    }


def arrays() -> dict[str, np.ndarray]:
    rng = np.random.default_rng(0)
    return {
        "bcsdf": rng.random((4, 8, 16), dtype=np.float32),
        "albedo": rng.random((4, 8)).astype(np.float64),
        "counts": np.arange(12, dtype=np.int64).reshape(3, 4),
        "fortran": np.asfortranarray(rng.random((5, 3), dtype=np.float32)),
    }


@pytest.mark.parametrize("compress", [True, False, 0, 1, 9])
def test_round_trip(tmp_path, compress):
    path = tmp_path / "t.npz"
    written = write_table(path, header(), arrays(), compress=compress)
    h, a = read_table(path)
    assert h == written
    assert h["format"] == "usdfiber-bcsdf" and h["version"] == 1
    assert h["geometry_key"] == "ab" * 32 and h["inputs"]["eta"] == 1.635
    assert "created" in h and set(h["checksums"]) == set(arrays())
    for name, arr in arrays().items():
        assert a[name].dtype == arr.dtype and np.array_equal(a[name], arr)
    assert read_header(path) == h
    assert read_header(path, verify=True) == h
    # Plain numpy can read it, without pickles.
    with np.load(path, allow_pickle=False) as z:
        raw = json.loads(z["header"].tobytes().decode("utf-8"))
        assert raw == h and np.array_equal(z["counts"], arrays()["counts"])
    assert (path.stat().st_mode & 0o777) == 0o644
    assert [p.name for p in tmp_path.iterdir()] == ["t.npz"]  # no temp file left
    # Stored or deflated, as asked (True: the default level).
    with zipfile.ZipFile(path) as z:
        methods = {i.compress_type for i in z.infolist()}
    assert methods == ({zipfile.ZIP_DEFLATED} if compress else {zipfile.ZIP_STORED})


def test_default_level_is_written_by_isal_and_read_by_zlib(tmp_path, monkeypatch):
    """compress=True deflates with ISA-L: every entry inflates with zlib (the reader's own
    codec) to the bytes zlib's level 1 writes them from, and the file is the size zlib's would
    be within a few percent; without ISA-L, zlib writes the same arrays."""
    import zlib

    assert T.FAST_DEFLATE, "isal is a dependency: the default level must use it"
    rng = np.random.default_rng(1)
    big = {"p": (rng.random((64, 4096)) ** 6).astype(np.float16), "n": np.arange(5000, dtype=np.int64)}
    fast, slow = tmp_path / "fast.npz", tmp_path / "slow.npz"
    write_table(fast, header(), big, compress=True)
    monkeypatch.setattr(T, "FAST_DEFLATE", False)
    write_table(slow, header(), big, compress=True)
    with zipfile.ZipFile(fast) as zf, zipfile.ZipFile(slow) as zs:
        assert zf.testzip() is None and zs.testzip() is None        # CRCs of what zlib inflates
        for name in ("p.npy", "n.npy"):
            raw_f = zlib.decompress(_member_bytes(fast, zf.getinfo(name)), -15)
            assert raw_f == zs.read(name)
        assert _member_bytes(fast, zf.getinfo("p.npy")) != _member_bytes(slow, zs.getinfo("p.npy"))  # two codecs
        fsize = sum(i.compress_size for i in zf.infolist())
        ssize = sum(i.compress_size for i in zs.infolist())
    assert 0.9 < fsize / ssize < 1.1
    for name, a in big.items():
        assert np.array_equal(read_table(fast)[1][name], a)
    # deflate() is the writer's codec: the entry's compressed size, less the .npy header's bytes.
    monkeypatch.setattr(T, "FAST_DEFLATE", True)
    with zipfile.ZipFile(fast) as zf:
        assert abs(len(T.deflate(big["p"])) - zf.getinfo("p.npy").compress_size) < 256


def _member_bytes(path: Path, info: zipfile.ZipInfo) -> bytes:
    """A zip member's compressed bytes as stored (after its local header)."""
    import struct

    with open(path, "rb") as f:
        f.seek(info.header_offset)
        local = f.read(30)
        n, m = struct.unpack("<HH", local[26:30])
        f.seek(info.header_offset + 30 + n + m)
        return f.read(info.compress_size)


@pytest.mark.parametrize("bad", [-1, 10, 2.5])
def test_refuses_unknown_levels(tmp_path, bad):
    with pytest.raises(ValueError, match="zlib level"):
        write_table(tmp_path / "t.npz", header(), arrays(), compress=bad)
    assert list(tmp_path.iterdir()) == []


@pytest.mark.parametrize("a", [
    np.ones((), np.float16), np.zeros(0), np.zeros((0, 3), np.float32), np.arange(20, dtype=np.float16).reshape(4, 5),
    np.arange(20.0).reshape(4, 5)[:, ::2], np.asfortranarray(np.arange(12.0).reshape(3, 4)),
    np.arange(10, dtype=">i4"), np.array([True, False]), np.array(["ab", "c"]), np.zeros(3, dtype="S0"),
    np.arange(24, dtype=np.int16).reshape(2, 3, 4).transpose(2, 0, 1)], ids=lambda a: f"{a.dtype.str}{a.shape}")
def test_checksum_is_sha256_of_c_order_bytes(a):
    # Tables written before the checksum hashed in place must still verify: the digest is
    # the sha256 of the array's bytes in C order, whatever its layout, byte order or size.
    import hashlib
    assert T.array_checksum(a) == hashlib.sha256(np.ascontiguousarray(a).tobytes()).hexdigest()


def test_numpy_scalars_in_header(tmp_path):
    h = header()
    h["photons"] = np.int64(5)
    h["error_estimate"] = np.float32(0.5)
    write_table(tmp_path / "t.npz", h, {"x": np.zeros(3)})
    assert read_header(tmp_path / "t.npz")["photons"] == 5


def test_other_container_names_are_kept_apart(tmp_path):
    """The same container under another format name (the baker's resume chunks): no table
    keys are required, and neither kind of file is read as the other."""
    chunk, table = tmp_path / "chunk.npz", tmp_path / "table.npz"
    write_table(chunk, {"bake_key": "k"}, {"x": np.arange(3.0)}, container="usdfiber-test-chunk")
    write_table(table, header(), arrays())
    h, a = read_table(chunk, container="usdfiber-test-chunk")
    assert h["format"] == "usdfiber-test-chunk" and h["bake_key"] == "k" and np.array_equal(a["x"], np.arange(3.0))
    with pytest.raises(TableError, match="not a usdfiber table .format is not 'usdfiber-bcsdf'"):
        read_table(chunk)
    with pytest.raises(TableError, match="not a usdfiber-test-chunk file .format is not 'usdfiber-test-chunk'"):
        read_header(table, container="usdfiber-test-chunk")
    with pytest.raises(TableError, match="header lacks"):
        write_table(tmp_path / "t.npz", {"bake_key": "k"}, {"x": np.zeros(1)})


def test_missing(tmp_path):
    with pytest.raises(TableError, match="missing"):
        read_table(tmp_path / "nope.npz")
    with pytest.raises(TableError, match="missing"):
        read_header(tmp_path / "nope.npz")


def test_garbage_file(tmp_path):
    path = tmp_path / "g.npz"
    path.write_bytes(b"this is not a table at all\n" * 20)
    with pytest.raises(TableError, match="not a usdfiber table"):
        read_table(path)
    np.save(tmp_path / "plain.npy", np.zeros(3))
    with pytest.raises(TableError, match="not a usdfiber table"):
        read_header(tmp_path / "plain.npy")


def test_npz_that_is_not_a_table(tmp_path):
    path = tmp_path / "other.npz"
    np.savez(path, data=np.zeros(3))
    with pytest.raises(TableError, match=r"not a usdfiber table \(no header"):
        read_header(path)
    bad = json.dumps({"format": "something-else", "version": 1}).encode()
    np.savez(path, header=np.frombuffer(bad, dtype=np.uint8))
    with pytest.raises(TableError, match="not a usdfiber table"):
        read_table(path)


@pytest.mark.parametrize("fraction", [0.0, 0.5, 0.9, 0.999])
def test_truncated(tmp_path, fraction):
    path = tmp_path / "t.npz"
    write_table(path, header(), arrays())
    data = path.read_bytes()
    path.write_bytes(data[: int(len(data) * fraction)])
    with pytest.raises(TableError, match="truncated or corrupt"):
        read_table(path)


def _rewrite(path: Path, head: dict, arrs: dict) -> None:
    payload = np.frombuffer(json.dumps(head).encode("utf-8"), dtype=np.uint8)
    np.savez(path, header=payload, **arrs)


def test_flipped_byte(tmp_path):
    path = tmp_path / "t.npz"
    write_table(path, header(), arrays(), compress=False)
    data = bytearray(path.read_bytes())
    # Flip one bit inside the float data of the first (largest) array entry.
    start = data.index(b"bcsdf.npy")
    data[start + 400] ^= 0x01
    path.write_bytes(bytes(data))
    with pytest.raises(TableError, match="truncated or corrupt|checksum mismatch"):
        read_table(path)
    # The zip CRC is intact here (archive rewritten), so only our checksum can tell.
    h = write_table(path, header(), arrays())
    a = arrays()
    a["bcsdf"] = a["bcsdf"].copy()
    a["bcsdf"].view(np.uint32)[1, 2, 3] ^= 1
    _rewrite(path, h, a)
    with pytest.raises(TableError, match="checksum mismatch for array bcsdf"):
        read_table(path)
    read_header(path)  # header alone is still fine
    with pytest.raises(TableError, match="checksum mismatch for array bcsdf"):
        read_header(path, verify=True)


def test_reading_some_arrays_verifies_those(tmp_path):
    """``read_table(names=...)`` reads and verifies the named arrays only: a damaged array
    left on disk does not stop them, a damaged named one does, and a name the file lacks is
    refused."""
    path = tmp_path / "t.npz"
    h = write_table(path, header(), arrays())
    a = arrays()
    a["bcsdf"] = a["bcsdf"].copy()
    a["bcsdf"].view(np.uint32)[1, 2, 3] ^= 1
    _rewrite(path, h, a)
    head, got = read_table(path, names=("albedo",))
    assert set(got) == {"albedo"} and head["checksums"] == h["checksums"]
    np.testing.assert_array_equal(got["albedo"], arrays()["albedo"])
    with pytest.raises(TableError, match="checksum mismatch for array bcsdf"):
        read_table(path, names=("albedo", "bcsdf"))
    with pytest.raises(TableError, match="truncated or corrupt: no array nothing"):
        read_table(path, names=("nothing",))
    del a["counts"]
    _rewrite(path, h, a)
    with pytest.raises(TableError, match="truncated or corrupt: array counts"):
        read_table(path, names=("albedo",))   # the file still has to hold what its header lists


def test_missing_or_extra_array(tmp_path):
    path = tmp_path / "t.npz"
    h = write_table(path, header(), arrays())
    a = arrays()
    del a["albedo"]
    _rewrite(path, h, a)
    with pytest.raises(TableError, match="truncated or corrupt: array albedo"):
        read_table(path)
    a = arrays()
    a["extra"] = np.zeros(2)
    _rewrite(path, h, a)
    with pytest.raises(TableError, match="truncated or corrupt: array extra"):
        read_table(path)


@pytest.mark.parametrize("version", [2, 0, "1", None])
def test_wrong_version(tmp_path, version):
    path = tmp_path / "t.npz"
    h = write_table(path, header(), arrays())
    h["version"] = version
    _rewrite(path, h, arrays())
    with pytest.raises(TableError, match=f"unsupported version {version}"):
        read_header(path)
    with pytest.raises(TableError, match="unsupported version"):
        read_table(path)


def test_write_refuses_bad_input(tmp_path):
    h = header()
    del h["photons"]
    with pytest.raises(TableError, match="lacks photons"):
        write_table(tmp_path / "t.npz", h, arrays())
    with pytest.raises(TableError, match="invalid array name 'header'"):
        write_table(tmp_path / "t.npz", header(), {"header": np.zeros(1)})
    with pytest.raises(TableError, match="dtype object"):
        write_table(tmp_path / "t.npz", header(), {"x": np.array([object()])})
    h = header()
    h["error_estimate"] = float("nan")
    with pytest.raises(TableError, match="not JSON"):
        write_table(tmp_path / "t.npz", h, arrays())
    assert list(tmp_path.iterdir()) == []


def test_failed_replace_leaves_no_file(tmp_path, monkeypatch):
    path = tmp_path / "t.npz"

    def boom(src, dst):
        raise OSError("simulated crash before rename")

    monkeypatch.setattr(T.os, "replace", boom)
    with pytest.raises(OSError, match="simulated"):
        write_table(path, header(), arrays())
    assert not path.exists()
    assert list(tmp_path.iterdir()) == []  # temp file cleaned up


def test_failed_rewrite_keeps_old_table(tmp_path, monkeypatch):
    path = tmp_path / "t.npz"
    old = write_table(path, header(), arrays())
    monkeypatch.setattr(T.os, "replace", lambda s, d: (_ for _ in ()).throw(OSError("crash")))
    h = header()
    h["photons"] = 2
    with pytest.raises(OSError):
        write_table(path, h, {"x": np.ones(4)})
    assert read_table(path)[0] == old


def test_killed_mid_write_leaves_no_file(tmp_path):
    # A process killed after writing the temp file but before the rename: no table at the
    # target path (the temp file may stay behind; it is never read as a table).
    path = tmp_path / "t.npz"
    script = textwrap.dedent(f"""
        import os, sys
        sys.path.insert(0, {str(REPO)!r})
        import numpy as np
        from usdfiber import table_format as T
        T.os.replace = lambda src, dst: os._exit(9)
        T.write_table({str(path)!r}, {header()!r}, {{"x": np.arange(1000.0)}})
    """)
    proc = subprocess.run([sys.executable, "-c", script], capture_output=True)
    assert proc.returncode == 9, proc.stderr.decode()
    assert not path.exists()
    leftovers = list(tmp_path.iterdir())
    assert len(leftovers) == 1 and leftovers[0].name.startswith(".t.npz.") and leftovers[0].suffix == ".tmp"
    with pytest.raises(TableError, match="missing"):
        read_table(path)


def test_empty_file(tmp_path):
    path = tmp_path / "t.npz"
    path.write_bytes(b"")
    with pytest.raises(TableError, match="truncated or corrupt"):
        read_header(path)


def test_table_error_is_value_error():
    assert issubclass(TableError, ValueError)
    e = TableError("/x.npz", "missing")
    assert e.path == "/x.npz" and e.reason == "missing" and str(e) == "/x.npz: missing"


@pytest.mark.parametrize("field, value", [("resolution", None), ("resolution", "30"), ("baked_diameter_um", "x"),
                                          ("baked_diameter_um", 0), ("eta", "x")])
def test_crafted_header_with_valid_checksums_is_refused_in_one_line(tmp_path, circle_table, field, value):
    """A file whose checksums hold but whose header fields have the wrong type or value (a
    crafted or hand-edited table) is refused on load, in one line: never a traceback, never used."""
    from usdfiber.bake.storage import TableLayoutError, write_table_file
    from usdfiber.bake.table import BcsdfTable

    good = tmp_path / "good.npz"
    circle_table.save(good)
    header, arrays = T.read_table(good)
    header[field] = value
    bad = tmp_path / "bad.npz"
    write_table_file(bad, header, arrays)
    with pytest.raises((TableError, TableLayoutError), match="bad.npz: "):   # load's two refusals
        BcsdfTable.load(bad)
    out = subprocess.run([sys.executable, "-m", "usdfiber", "table", "inspect", str(bad)],
                         capture_output=True, text=True)
    assert out.returncode == 2 and "Traceback" not in out.stderr
    assert len(out.stderr.strip().splitlines()) == 1 and "bad.npz" in out.stderr
