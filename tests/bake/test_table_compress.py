"""Compressed tables in the workflow: ``usdfiber table compress`` (its report, its atomic
outputs, its one-line errors), ``usdfiber bake --compress`` and compressed entries of the
table cache (served under the same key, found by a render's planned lookup, refused when
truncated or written for another key). Deterministic: the tables are fixtures, no statistical
assertion here (the render's agreement is tests/mitsuba/test_compressed_render.py)."""
from __future__ import annotations

import shutil
from pathlib import Path

import numpy as np
import pytest

import usdfiber  # noqa: F401 - registers the schema
from usdfiber.bake.cache import TableCache, TableCacheWarning
from usdfiber.bake.compression import CompressionError
from usdfiber.bake.requests import params_from_mapping, requests_for_params
from usdfiber.bake.settings import BakeSettings
from usdfiber.bake.table import BcsdfTable
from usdfiber.cli import main

BOUND = 0.01
# A quick silk table of the cache (15 deg grid, few photons: about 5 s).
SMALL = BakeSettings(resolution_deg=15, photons=3000, batches=2)


def _request():
    return requests_for_params(params_from_mapping({"preset": "silk"}))[0]


@pytest.fixture(scope="module")
def baked_cache(tmp_path_factory) -> tuple[Path, str]:
    """A cache holding one uncompressed 15 deg silk table: (root, key)."""
    root = tmp_path_factory.mktemp("baked") / "cache"
    res = TableCache(root).get_or_bake(_request(), SMALL)
    assert not res.table.compressed
    return root, res.key


@pytest.fixture()
def cache(baked_cache, tmp_path) -> tuple[TableCache, str]:
    """A copy of ``baked_cache`` this test may change."""
    root, key = baked_cache
    shutil.copytree(root / "tables", tmp_path / "cache" / "tables")
    return TableCache(tmp_path / "cache"), key


@pytest.fixture()
def table_file(silk_table, tmp_path) -> Path:
    path = tmp_path / "silk.npz"
    silk_table.save(path)
    return path


def run(args: list[str]) -> int:
    """``usdfiber ARGS`` in this process: its exit status (argparse's errors exit)."""
    try:
        return main(args)
    except SystemExit as exc:
        return int(exc.code)


def _one_line_error(capsys, needle: str) -> str:
    err = capsys.readouterr().err
    assert err.count("\n") == 1 and needle in err, err
    return err


# ---------------------------------------------------------------------------------------------
# The command
# ---------------------------------------------------------------------------------------------

def test_compress_writes_the_compressed_table_and_reports_it(table_file, tmp_path, capsys):
    out = tmp_path / "small.npz"
    before = table_file.read_bytes()
    assert run(["table", "compress", str(table_file), "-o", str(out)]) == 0
    line = capsys.readouterr().out.strip()
    c = BcsdfTable.load(out)
    comp = c.header["compression"]
    assert c.compressed and comp["bound"] == BOUND and comp["error_max"] <= BOUND
    size_in, size_out = table_file.stat().st_size, out.stat().st_size
    assert line.startswith(f"{table_file} -> {out}: {size_in / 1e6:.2f} MB -> {size_out / 1e6:.2f} MB on disk"), line
    assert f"rank {comp['rank']}, worst error {comp['error_max']:.2%} (bound 1.00%)" in line, line
    assert table_file.read_bytes() == before                    # the source is left as it was
    assert not list(tmp_path.glob(".*.tmp"))                     # written atomically: no temporary left
    # What the table names (the cache key, the bake) travels with it.
    src = BcsdfTable.load(table_file)
    for k in ("geometry_key", "inputs", "bake", "photons", "error_estimate", "resolution"):
        assert c.header[k] == src.header[k], k
    assert run(["table", "inspect", str(out)]) == 0
    assert f"rank {comp['rank']}, p within 1.00%" in capsys.readouterr().out


def test_compress_in_place_and_into_a_directory(table_file, tmp_path, capsys):
    other = tmp_path / "other.npz"
    shutil.copy(table_file, other)
    outdir = tmp_path / "out"
    outdir.mkdir()
    assert run(["table", "compress", str(table_file), str(other), "-o", str(outdir), "--bound", "0.02"]) == 0
    lines = capsys.readouterr().out.strip().splitlines()
    assert len(lines) == 2
    for name in ("silk.npz", "other.npz"):
        t = BcsdfTable.load(outdir / name)
        assert t.compressed and t.header["compression"]["bound"] == 0.02
    assert run(["table", "compress", str(other), "--in-place"]) == 0
    assert "in place" in capsys.readouterr().out
    assert BcsdfTable.load(other).compressed


@pytest.mark.parametrize("case", ["not a table", "missing", "already compressed", "bound"])
def test_compress_errors_are_one_line_and_leave_the_file(case, table_file, tmp_path, capsys):
    path = table_file
    args = ["--in-place"]
    needle = {"not a table": "not a usdfiber table", "missing": "missing",
              "already compressed": "is already compressed", "bound": "cannot be compressed within 0.001"}[case]
    if case == "not a table":
        path = tmp_path / "junk.npz"
        path.write_text("junk")
    elif case == "missing":
        path = tmp_path / "missing.npz"
    elif case == "already compressed":
        BcsdfTable.load(table_file).compress(BOUND).save(table_file)
    else:
        # The silk fixture needs a rank above the largest at 0.1 % (tests/bake/test_compression.py).
        args += ["--bound", "0.001"]
    before = path.read_bytes() if path.exists() else None
    assert run(["table", "compress", str(path), *args]) == 2
    err = _one_line_error(capsys, needle)
    assert str(path) in err and "Traceback" not in err
    assert (path.read_bytes() if path.exists() else None) == before


def test_compress_continues_past_a_bad_file(table_file, tmp_path, capsys):
    junk = tmp_path / "junk.npz"
    junk.write_text("junk")
    outdir = tmp_path / "out"
    outdir.mkdir()
    assert run(["table", "compress", str(junk), str(table_file), "-o", str(outdir)]) == 2
    _one_line_error(capsys, f"{junk}: not a usdfiber table")
    assert BcsdfTable.load(outdir / "silk.npz").compressed and not (outdir / "junk.npz").exists()


def test_compress_refuses_two_tables_written_to_one_file(table_file, tmp_path, capsys):
    """Tables of one name from different folders into one -o directory (the second overwrote the
    first), or a table given twice: refused in one line before anything is written."""
    (tmp_path / "b").mkdir()
    twin = tmp_path / "b" / "silk.npz"
    shutil.copy(table_file, twin)
    outdir = tmp_path / "out"
    outdir.mkdir()
    assert run(["table", "compress", str(table_file), str(twin), "-o", str(outdir)]) == 2
    _one_line_error(capsys, f"{table_file} and {twin} would both be written to {outdir / 'silk.npz'}")
    assert not list(outdir.iterdir())
    before = table_file.read_bytes()
    assert run(["table", "compress", str(table_file), str(tmp_path / "b" / ".." / "silk.npz"), "--in-place"]) == 2
    _one_line_error(capsys, "given twice")
    assert table_file.read_bytes() == before


@pytest.mark.parametrize("args, needle", [
    ([], "-o OUT or --in-place"),
    (["-o", "nowhere/"], "expected a directory for 2 tables"),
    (["--bound", "0"], "must be in [0.0001, 1)"),
    (["--bound", "1.5"], "must be in [0.0001, 1)"),
    (["--bound", "1e-300"], "must be in [0.0001, 1)"),   # the codec's tolerance underflowed to NaN work
    (["--cache"], "FILE arguments or --cache, not both"),
    (["-o", "x.npz", "--in-place"], "not allowed with"),
])
def test_compress_usage_errors(args, needle, table_file, capsys):
    assert run(["table", "compress", str(table_file), str(table_file), *args]) == 2
    _one_line_error(capsys, needle)


# ---------------------------------------------------------------------------------------------
# The cache
# ---------------------------------------------------------------------------------------------

def test_cache_serves_a_compressed_entry_under_its_key(cache, capsys, monkeypatch):
    """``table compress --cache`` compresses the entry in place; the render's lookups (the
    planned one, the cache's own, a request for fewer photons) find it under the same key."""
    from usdfiber.translators.mitsuba.table_plan import PlannedTableCache

    tc, key = cache
    raw = tc.load(key)
    assert run(["table", "compress", "--cache", "--cache-dir", str(tc.root)]) == 0
    out = capsys.readouterr().out.strip().splitlines()
    assert out[-1] == "1 table compressed, 0 already compressed" and "in place" in out[0]
    req = _request()
    res = tc.get_or_bake(req, SMALL, bake_missing=False)
    assert res is not None and res.key == key and res.table.compressed and not res.baked
    assert res.table.header["cache_key"] == key
    assert PlannedTableCache(tc.root).plan([req], lambda r: SMALL) == []
    fewer = BakeSettings(resolution_deg=15, photons=1000, batches=2)
    assert tc.find_serving(req, fewer) == key
    # What the renderer reads of it: the width and albedo exactly, p within the bound.
    t = res.table
    np.testing.assert_array_equal(t.arrays["width"], raw.arrays["width"])
    np.testing.assert_array_equal(t.band_start, raw.band_start)
    sigma = [0.0, 0.05, 0.4]
    a, b = t.recolour(sigma), raw.recolour(sigma)
    np.testing.assert_allclose(a.albedo, b.albedo, rtol=1e-6)
    ti, pi = np.radians([-40.0, 10.0, 55.0]), np.radians([0.0, 90.0, 200.0])
    np.testing.assert_allclose(a.albedo_at(ti, pi), b.albedo_at(ti, pi), rtol=1e-6)
    dom = t.domega_band()[..., None, None]          # (n_ti, n_pi, B, 1, 1): per channel
    err = np.sqrt(((a.p - b.p) ** 2 * dom).sum(axis=(2, 3)) / (b.p ** 2 * dom).sum(axis=(2, 3)))
    # At absorptions between the checked ones the spline may add a little: 1.5x the bound.
    print(f"\n[compressed cache entry] worst relative L2 of p at {sigma}: {err.max():.4f}")
    assert err.max() <= 1.5 * BOUND, err.max()
    capsys.readouterr()
    assert run(["table", "compress", "--cache", "--cache-dir", str(tc.root)]) == 0
    assert capsys.readouterr().out.strip() == "0 tables compressed, 1 already compressed"


def test_bake_compress_stores_compressed_tables(tmp_path, capsys):
    """``bake --compress`` compresses before storing (no uncompressed table is kept), under the key."""
    root = tmp_path / "cache"
    rc = run(["bake", "--preset", "polyester", "--resolution", "15", "--photons", "2000", "--batches", "2",
               "--no-progress", "--cache-dir", str(root), "--compress", "0.02"])
    assert rc == 0
    out = capsys.readouterr().out.strip().splitlines()
    assert len(out) == 1 and "baked, compressed (rank" in out[0], out
    key = out[0].split()[0]
    t = TableCache(root).load(key)
    assert t.compressed and t.header["compression"]["bound"] == 0.02 and t.header["cache_key"] == key


def test_bake_compress_compresses_cached_tables_in_place(cache, monkeypatch):
    tc, key = cache
    res = tc.get_or_bake(_request(), SMALL, bake_missing=False, compress=BOUND)
    assert res.key == key and res.table.compressed and not res.baked
    assert BcsdfTable.load(tc.table_path(key)).compressed


def test_a_table_the_bound_cannot_hold_is_kept_uncompressed(cache, monkeypatch):
    tc, key = cache

    def refuse(self, bound=BOUND, **kw):
        raise CompressionError(f"{self.path or 'table'}: incoming direction (0, 0) keeps a compression error "
                               f"of 2.000% > {bound:.3%} at rank 12")

    monkeypatch.setattr(BcsdfTable, "compress", refuse)
    with pytest.warns(TableCacheWarning, match="kept uncompressed") as rec:
        res = tc.get_or_bake(_request(), SMALL, bake_missing=False, compress=BOUND)
    assert "\n" not in str(rec[0].message) and str(rec[0].message).count(str(tc.table_path(key))) == 1
    assert res.table is not None and not res.table.compressed
    assert not BcsdfTable.load(tc.table_path(key)).compressed


def test_a_truncated_compressed_entry_is_refused_in_one_line(cache, capsys):
    tc, key = cache
    assert tc.compress_entry(key, BOUND).compressed
    path = tc.table_path(key)
    data = path.read_bytes()
    path.write_bytes(data[: len(data) * 2 // 3])
    assert run(["table", "inspect", str(path)]) == 2
    _one_line_error(capsys, str(path))
    with pytest.warns(TableCacheWarning) as rec:
        assert tc.get_or_bake(_request(), SMALL, bake_missing=False) is None
    msg = str(rec[0].message)
    assert "\n" not in msg and msg.startswith(f"{path}: ") and "baking it again" in msg
    assert not path.exists()          # reported and removed, never used


def test_a_compressed_entry_under_another_key_is_refused(cache):
    tc, key = cache
    tc.compress_entry(key, BOUND)
    other = "0" * 64
    shutil.copy(tc.table_path(key), tc.table_path(other))
    with pytest.warns(TableCacheWarning, match="written for another cache key"):
        assert tc.load(other) is None
    assert tc.load(key).compressed
