"""Compressed tables (usdfiber.bake.compression): the bound holds after a round trip through a
file, recolouring agrees with the uncompressed table at absorptions between and beyond the
checked ones, the furnace survives, and damaged or mismatched files are refused in one line
naming the file. Deterministic: no statistical assertion here (the tables are fixtures)."""
from __future__ import annotations

import json
from pathlib import Path

import numpy as np
import pytest

from usdfiber import table_format
from usdfiber.bake import compression
from usdfiber.bake import recolour as kernel_mod
from usdfiber.bake.storage import TableLayoutError
from usdfiber.bake.table import BcsdfTable

BOUND = 0.01
# At samples and between them, low and high, at the last level (64) and far beyond it.
SIGMAS = [0.0, 0.01, 0.3, 1.0, 2.7, 5.0, 13.0, 64.0, 100.0, 5000.0]


def rel_l2(t: BcsdfTable, a: np.ndarray, b: np.ndarray) -> np.ndarray:
    """Relative L2 over the sphere of p per incoming direction (b the reference)."""
    dom = t.domega_band()[..., None]
    return np.sqrt(((a - b) ** 2 * dom).sum(axis=(-2, -1)) / (b ** 2 * dom).sum(axis=(-2, -1)))


@pytest.fixture(scope="module")
def compressed(silk_table, tmp_path_factory) -> tuple[BcsdfTable, Path]:
    """The silk fixture compressed to 1 %, written and read back (about 2 s)."""
    path = tmp_path_factory.mktemp("compressed") / "silk.npz"
    silk_table.compress(BOUND).save(path)
    return BcsdfTable.load(path), path


def test_round_trip_within_bound(silk_table, compressed):
    c, path = compressed
    assert c.compressed and not silk_table.compressed
    comp = c.header["compression"]
    assert comp["codec"] == compression.CODEC and comp["bound"] == BOUND
    assert 1 <= comp["rank"] < len(c.arrays["absorptions"])
    assert float(c.arrays["compression_error"].max()) <= BOUND
    assert comp["error_max"] == pytest.approx(float(c.arrays["compression_error"].max()))
    for s in SIGMAS:
        err = rel_l2(c, c.recolour(s).p[..., 0], silk_table.recolour(s).p[..., 0])
        assert err.max() <= BOUND, (s, err.max())
    # Smaller in memory than the levels it replaces, and (recolourable) on disk.
    assert c.arrays["basis"].nbytes < 0.5 * (silk_table.arrays["p"].nbytes + silk_table.arrays["lbar"].nbytes)
    assert np.array_equal(c.arrays["albedo"], silk_table.arrays["albedo"])


def test_rgb_recolour_matches_uncompressed(silk_table, compressed):
    c, _ = compressed
    rgb, scale = [0.4, 2.0, 9.0], 1.5
    a, b = c.recolour(rgb, scale), silk_table.recolour(rgb, scale)
    for ch in range(3):
        assert rel_l2(c, a.p[..., ch], b.p[..., ch]).max() <= BOUND
    np.testing.assert_allclose(a.albedo, b.albedo, rtol=1e-6)
    # The table's evaluation and sampling run on the compressed table unchanged.
    v = c.eval_p(0.3, 1.0, -0.3, 4.0, rgb, diameter_scale=scale)
    w = silk_table.eval_p(0.3, 1.0, -0.3, 4.0, rgb, diameter_scale=scale)
    assert v.shape == w.shape == (3,)


@pytest.mark.skipif(not kernel_mod.available(), reason="Dr.Jit has no LLVM backend here")
def test_kernel_matches_numpy(compressed):
    c, _ = compressed
    for s in ([0.0, 3.0, 300.0], 0.7):
        k = c.recolour(s, kernel=True).p
        n = c.recolour(s, kernel=False).p
        np.testing.assert_allclose(k, n, rtol=2e-5, atol=2e-6 * float(np.abs(n).max()))


def test_furnace_survives(circle_table, tmp_path):
    """Without absorption no light is lost: Lambda is kept exactly and p integrates to 1."""
    path = tmp_path / "circle.npz"
    circle_table.compress(BOUND).save(path)
    c = BcsdfTable.load(path)
    th = np.linspace(-1.4, 1.4, 9)
    np.testing.assert_array_equal(c.albedo(th, 0.2, 0.0), circle_table.albedo(th, 0.2, 0.0))
    assert np.all(circle_table.albedo(th, 0.2, 0.0) > 0.999)
    rec = c.recolour(0.0)
    total = (rec.p[..., 0] * c.domega_band()[..., None]).sum(axis=(-2, -1))
    np.testing.assert_allclose(total, 1.0, rtol=1e-5)
    assert np.all(rec.p >= 0)


def test_level_p_of_compressed(silk_table, compressed):
    c, _ = compressed
    for k in (0, 5, len(c.levels) - 1):
        assert rel_l2(c, c.level_p(k), silk_table.level_p(k)).max() <= BOUND


# ---- refusals ----------------------------------------------------------------------------------

def one_line(exc: BaseException, path: Path) -> str:
    msg = str(exc)
    assert "\n" not in msg and str(path) in msg, msg
    return msg


def test_truncated_file_is_refused(compressed, tmp_path):
    _, path = compressed
    bad = tmp_path / "truncated.npz"
    data = path.read_bytes()
    bad.write_bytes(data[: len(data) // 2])
    with pytest.raises(table_format.TableError) as exc:
        BcsdfTable.load(bad)
    one_line(exc.value, bad)


def test_flipped_byte_is_refused(compressed, tmp_path):
    c, path = compressed
    data = bytearray(path.read_bytes())
    blob = c.arrays["basis_codec"].tobytes()
    at = data.find(blob[len(blob) // 2: len(blob) // 2 + 64])
    assert at > 0   # the codec's bytes are stored as they are (no zip deflate on top)
    data[at + 7] ^= 0x10
    bad = tmp_path / "flipped.npz"
    bad.write_bytes(bytes(data))
    with pytest.raises(table_format.TableError) as exc:
        BcsdfTable.load(bad)
    msg = one_line(exc.value, bad)
    assert "checksum" in msg or "corrupt" in msg


def rewrite(path: Path, out: Path, header_change=None, arrays_change=None) -> Path:
    """A copy of a table file with its header or arrays changed (checksums recomputed, so
    only the layout and codec checks can catch the change)."""
    header, arrays = table_format.read_table(path)
    header = {k: v for k, v in header.items() if k not in ("arrays", "checksums", "format", "version")}
    header = json.loads(json.dumps(header))
    if header_change:
        header_change(header)
    if arrays_change:
        arrays_change(arrays)
    table_format.write_table(out, header, arrays, compress=False)
    return out


def test_header_codec_mismatch_is_refused(compressed, tmp_path):
    _, path = compressed

    def other_codec(h):
        h["compression"]["codec"] = "blosc2-zstd"

    bad = rewrite(path, tmp_path / "codec.npz", other_codec)
    with pytest.raises(TableLayoutError) as exc:
        BcsdfTable.load(bad)
    assert "blosc2-zstd" in one_line(exc.value, bad)

    def other_rank(h):
        h["compression"]["rank"] += 1

    bad = rewrite(path, tmp_path / "rank.npz", other_rank)
    with pytest.raises(TableLayoutError) as exc:
        BcsdfTable.load(bad)
    one_line(exc.value, bad)


def test_bytes_of_another_codec_are_refused(compressed, tmp_path):
    """A basis group written with another blosc2 codec than the header names."""
    import blosc2

    c, path = compressed
    first, count, offset, nbytes = c.arrays["basis_groups"][0].tolist()
    R, B, n_po = c.arrays["basis"].shape[2:]

    def zstd_group(arrays):
        z = blosc2.asarray(np.zeros((count * R, B, n_po), np.float32),
                           cparams={"codec": blosc2.Codec.ZSTD}).to_cframe()
        blob = arrays["basis_codec"].tobytes()
        arrays["basis_codec"] = np.frombuffer(blob[:offset] + bytes(z) + blob[offset + nbytes:], np.uint8)
        groups = arrays["basis_groups"].copy()
        groups[0, 3] = len(z)
        groups[1:, 2] += len(z) - nbytes
        arrays["basis_groups"] = groups

    bad = rewrite(path, tmp_path / "zstd.npz", arrays_change=zstd_group)
    with pytest.raises(TableLayoutError) as exc:
        BcsdfTable.load(bad)
    assert "ZSTD" in one_line(exc.value, bad)


def test_unreachable_bound_is_refused(silk_table):
    with pytest.raises(compression.CompressionError) as exc:
        silk_table.compress(compression.MIN_BOUND, rank=compression.MAX_RANK)
    assert "\n" not in str(exc.value) and "compression error" in str(exc.value)
    with pytest.raises(compression.CompressionError, match=r"bound must be in \[0.0001, 1\), got 1e-07"):
        silk_table.compress(1e-7)   # below float16 rounding (its codec tolerance underflowed)
    with pytest.raises(compression.CompressionError):
        silk_table.compress(0.0)


def test_cache_refuses_a_mismatched_compressed_table(compressed, tmp_path):
    """The cache's one verified loader reports a mismatched compressed table and does not use it."""
    from usdfiber.bake.cache import TableCache, TableCacheWarning

    _, path = compressed

    def other_codec(h):
        h["compression"]["codec"] = "blosc2-zstd"

    bad = rewrite(path, tmp_path / "cached.npz", other_codec)
    with pytest.warns(TableCacheWarning, match="blosc2-zstd"):
        assert TableCache(tmp_path).load_verified(bad, BcsdfTable.load, lambda t: True) is None
    assert not bad.exists()
    good = rewrite(path, tmp_path / "good.npz")
    assert TableCache(tmp_path).load_verified(good, BcsdfTable.load, lambda t: True).compressed


@pytest.mark.skipif(not kernel_mod.available(), reason="Dr.Jit has no LLVM backend here")
def test_kernel_launches_split_by_direction_give_the_same_table(compressed, monkeypatch):
    """Large compressed tables are recoloured in several launches (32-bit indices): the same
    values as one launch."""
    c, path = compressed
    whole = c.recolour([0.3, 5.0, 90.0], kernel=True).p.copy()
    R, B, n_po = c.arrays["basis"].shape[2:]
    monkeypatch.setattr(kernel_mod, "_MAX_ELEMENTS", 3 * max(R, 3) * B * n_po)
    split = BcsdfTable.load(path).recolour([0.3, 5.0, 90.0], kernel=True).p
    np.testing.assert_array_equal(split, whole)
