"""The table cache: keys, hits and misses, damaged files, resumed bakes, concurrent bakers."""
from __future__ import annotations

import multiprocessing as mp
import time
from pathlib import Path

import numpy as np
import pytest

import usdfiber  # noqa: F401 - registers the schema
from pxr import Usd

from usdfiber import authoring
from usdfiber.bake.baker import bake_request
from usdfiber.bake.cache import TableCache, TableCacheWarning, cache_key, default_cache_dir, load_or_make
from usdfiber.bake.chunks import chunk_name
from usdfiber.bake.requests import params_from_mapping, requests_for_params, tables_for_stage
from usdfiber.bake.settings import BakeSettings
from usdfiber.bcsdf import MissingTableError, load_table, tables_for_prim
from stage_util import straight_curves

TINY = BakeSettings(resolution_deg=30, photons=2000, batches=2)


def request(**values):
    """The first table request of a fiber given by parameter-file values."""
    return requests_for_params(params_from_mapping(values))[0]


@pytest.fixture()
def cache(tmp_path):
    return TableCache(tmp_path / "cache")


# ---------------------------------------------------------------------------------------------
# Keys
# ---------------------------------------------------------------------------------------------

def test_key_changes_with_inputs_not_with_dye_or_size():
    base = request(preset="silk")
    k0 = cache_key(base.inputs, 0, TINY)
    same = [
        request(preset="silk", dye="reactiveRed"),
        request(preset="silk", dye="disperseBlue", depth_of_shade=3.0),
        request(preset="silk", diameter=6.0),
        request(preset="silk", density=1.2),
    ]
    for r in same:
        assert cache_key(r.inputs, 0, TINY) == k0
    different = [
        cache_key(request(preset="silk", beta=9.0).inputs, 0, TINY),
        cache_key(request(preset="silk", ior=1.6).inputs, 0, TINY),
        cache_key(request(preset="silk", seed=3).inputs, 0, TINY),
        cache_key(request(preset="cotton").inputs, 0, TINY),
        cache_key(base.inputs, 1, TINY),
        cache_key(base.inputs, 0, BakeSettings(resolution_deg=15, photons=2000, batches=2)),
        cache_key(base.inputs, 0, BakeSettings(resolution_deg=30, photons=4000, batches=2)),
        cache_key(base.inputs, 0, BakeSettings(resolution_deg=30, photons=2000, batches=2, seed=1)),
        cache_key(base.inputs, 0, BakeSettings(resolution_deg=30, photons=2000, batches=2, target_error=0.05)),
    ]
    assert k0 not in different and len(set(different)) == len(different)
    # Cuticle sizes are relative to the diameter: a wool fiber scaled as a whole keeps its key.
    w1 = request(preset="wool", diameter=30.0, cuticle_height=0.6, cuticle_spacing=9.0)
    w2 = request(preset="wool", diameter=40.0, cuticle_height=0.8, cuticle_spacing=12.0)
    w3 = request(preset="wool", diameter=40.0, cuticle_height=0.6, cuticle_spacing=9.0)
    assert cache_key(w1.inputs, 0, TINY) == cache_key(w2.inputs, 0, TINY) != cache_key(w3.inputs, 0, TINY)


def test_default_cache_dir(monkeypatch, tmp_path):
    monkeypatch.setenv("USDFIBER_CACHE_DIR", str(tmp_path / "x"))
    assert default_cache_dir() == tmp_path / "x"
    monkeypatch.delenv("USDFIBER_CACHE_DIR")
    monkeypatch.delenv("XDG_CACHE_HOME", raising=False)
    assert default_cache_dir() == Path.home() / ".cache" / "usdfiber"


# ---------------------------------------------------------------------------------------------
# What a stage needs
# ---------------------------------------------------------------------------------------------

def _curves(stage, path):
    return straight_curves(stage, path, width=0.02)


def test_tables_for_stage_exactly_the_distinct_tables():
    stage = Usd.Stage.CreateInMemory()
    authoring.define_fiber_class(stage, "/_classes/Cotton", "cotton", variant_count=2)
    authoring.define_fiber_class(stage, "/_classes/Unused", "silk")       # no user: no table
    for i in range(5):                                                   # five curves, one class
        authoring.inherit(_curves(stage, f"/World/Cotton{i}"), "/_classes/Cotton")
    dyed = _curves(stage, "/World/CottonDyed")                           # dye and size: same tables
    authoring.inherit(dyed, "/_classes/Cotton")
    authoring.apply_fiber(dyed, None, dye="reactiveBlue", depth_of_shade=4.0, diameter=20.0)
    rough = _curves(stage, "/World/CottonRough")                         # other roughness: new tables
    authoring.inherit(rough, "/_classes/Cotton")
    authoring.apply_fiber(rough, None, beta=20.0)
    yarn = _curves(stage, "/World/Yarn")                                 # a yarn of the class's fiber
    authoring.apply_fiber(yarn, "cotton", variant_count=2)
    authoring.apply_yarn(yarn, "CNe 50")
    authoring.apply_fiber(_curves(stage, "/World/Poly"), "polyester")    # round: one variant
    reqs = tables_for_stage(stage)
    keys = {(r.geometry_key, r.variant) for r in reqs}
    assert len(reqs) == len(keys) == 5
    by_prims = {tuple(sorted(r.prims)): r for r in reqs}
    cotton = sorted([f"/World/Cotton{i}" for i in range(5)] + ["/World/CottonDyed", "/World/Yarn"])
    assert sorted(r.variant for r in reqs if sorted(r.prims) == cotton) == [0, 1]
    assert sorted(r.variant for r in reqs if r.prims == ["/World/CottonRough"]) == [0, 1]
    assert [r.variant for r in reqs if r.prims == ["/World/Poly"]] == [0]
    assert not any("/_classes" in p for r in reqs for p in r.prims)
    assert len(by_prims) == 3


# ---------------------------------------------------------------------------------------------
# Hits, misses, damaged files
# ---------------------------------------------------------------------------------------------

def test_hit_and_miss(cache):
    req = request(preset="polyester")
    first = cache.get_or_bake(req, TINY)
    assert first.baked and first.path.exists() and first.path.parent == cache.root / "tables"
    assert first.key == cache.key(req, TINY) and first.path.name == f"{first.key}.npz"
    again = cache.get_or_bake(request(preset="polyester", dye="disperseRed"), TINY)
    assert not again.baked and again.path == first.path
    for k, v in first.table.arrays.items():
        assert np.array_equal(again.table.arrays[k], v)
    assert again.table.header["cache_key"] == first.key
    assert cache.get_or_bake(request(preset="polyester", beta=5.0), TINY, bake_missing=False) is None
    assert not (cache.root / "partial" / first.key).exists()


@pytest.mark.parametrize("damage", ["truncated", "corrupt", "empty"])
def test_damaged_file_is_reported_and_rebaked(cache, damage):
    req = request(preset="polyester")
    path = cache.get_or_bake(req, TINY).path
    good = path.read_bytes()
    if damage == "truncated":
        path.write_bytes(good[: len(good) // 2])
    elif damage == "corrupt":
        bad = bytearray(good)
        for i in range(len(bad) // 3, len(bad) // 3 + 64):
            bad[i] ^= 0x5A
        path.write_bytes(bytes(bad))
    else:
        path.write_bytes(b"")
    with pytest.warns(TableCacheWarning, match=r"truncated or corrupt|checksum mismatch") as rec:
        res = cache.get_or_bake(req, TINY)
    assert any(str(path) in str(w.message) for w in rec)
    assert res.baked
    back = load_table(path)                       # a valid file again
    assert np.array_equal(back.arrays["p"], res.table.arrays["p"])


# ---------------------------------------------------------------------------------------------
# Interrupted bakes
# ---------------------------------------------------------------------------------------------

def test_resume_after_interrupted_bake(tmp_path, monkeypatch):
    # Groups of 4 directions: the interruption at the 5th falls in the second group.
    monkeypatch.setattr("usdfiber.bake.settings.GROUP_DIRECTIONS", 4)
    req = request(preset="silk", variant_count=1)
    cache = TableCache(tmp_path / "c1")
    key = cache.key(req, TINY)
    k = 5

    reported = []

    def interrupt(done, total, info):
        if info["event"] == "direction":
            # the 30 deg grid's nodes are at 15 + 30 j degrees
            reported.append(chunk_name(round((info["theta_i_deg"] - 15) / 30), round((info["phi_i_deg"] - 15) / 30)))
            if done >= k:
                raise KeyboardInterrupt

    with pytest.raises(KeyboardInterrupt):
        cache.get_or_bake(req, TINY, interrupt)
    # Every direction reported done has its chunk (its group's chunks are written while the
    # next group traces; the interruption waits for them); nothing past its group.
    chunks = sorted(p.name for p in cache.partial_dir(key).glob("d*_*.npz"))
    assert len(reported) == k and set(reported) <= set(chunks) and not cache.table_path(key).exists()
    assert len(chunks) == 8
    k = len(chunks)

    traced, starts = [], []

    def count(done, total, info):
        if info["event"] == "start":
            starts.append((done, total))
        else:
            traced.append(done)

    res = cache.get_or_bake(req, TINY, count)
    total = starts[0][1]
    assert total == 36 and starts == [(k, total)]          # 3 theta_i x 12 phi_i at 30 degrees
    assert len(traced) == total - k and res.resumed == k
    assert not cache.partial_dir(key).exists()
    # Nothing was lost or changed: the same table as an uninterrupted bake.
    fresh = TableCache(tmp_path / "c2").get_or_bake(req, TINY).table
    for name, arr in fresh.arrays.items():
        assert np.array_equal(res.table.arrays[name], arr), name


def test_unusable_resume_chunks_are_reported_and_traced_again(tmp_path):
    """Every chunk names its bake and direction and carries checksums: a truncated chunk, a
    chunk with a changed array, a chunk of another direction and a chunk of another bake are
    each reported and traced again, and the table equals an uninterrupted bake."""
    import zipfile

    req = request(preset="silk", variant_count=1)
    fresh = bake_request(req, TINY)
    d, other = tmp_path / "resume", tmp_path / "other"
    bake_request(req, TINY, resume_dir=d)                                     # keeps its chunks
    bake_request(req, BakeSettings(resolution_deg=30, photons=2000, batches=2, seed=1), resume_dir=other)
    data = (d / "d0000_0000.npz").read_bytes()
    (d / "d0000_0000.npz").write_bytes(data[: len(data) // 2])              # truncated
    with zipfile.ZipFile(d / "d0000_0001.npz") as z:                         # H changed, header kept
        entries = {n: z.read(n) for n in z.namelist()}
    with np.load(d / "d0000_0001.npz") as z:
        H = z["H"].copy()
    H.flat[0] += 1.0
    buf = tmp_path / "H.npy"
    np.save(buf, H)
    entries["H.npy"] = buf.read_bytes()
    with zipfile.ZipFile(d / "d0000_0001.npz", "w") as z:
        for n, b in entries.items():
            z.writestr(n, b)
    (d / "d0001_0000.npz").write_bytes((d / "d0002_0000.npz").read_bytes())  # another direction
    (d / "d0002_0003.npz").write_bytes((other / "d0002_0003.npz").read_bytes())  # another bake
    with pytest.warns(RuntimeWarning) as caught:
        again = bake_request(req, TINY, resume_dir=d)
    msgs = sorted(str(w.message) for w in caught if "partial bake chunk" in str(w.message))
    assert len(msgs) == 4, msgs
    assert "d0000_0000.npz" in msgs[0] and "truncated or corrupt" in msgs[0]
    assert "d0000_0001.npz" in msgs[1] and "checksum mismatch for array H" in msgs[1]
    assert "d0001_0000.npz" in msgs[2] and "holds direction [2, 0]" in msgs[2]
    assert "d0002_0003.npz" in msgs[3] and "another bake" in msgs[3]
    for name, arr in fresh.arrays.items():
        assert np.array_equal(again.arrays[name], arr), name


def test_load_or_make_looks_again_under_the_lock():
    """Double-checked locking: a value another process finished while this one waited for the
    lock is loaded, not made again; without make_missing nothing is locked or made."""
    events, store = [], {}

    class Lock:
        def __enter__(self):
            events.append("lock")
            store["v"] = "theirs"                 # finished by another process meanwhile

        def __exit__(self, *exc):
            events.append("unlock")

    def make():
        events.append("make")
        return "mine"

    assert load_or_make(lambda: store.get("v"), Lock, make) == ("theirs", False)
    assert events == ["lock", "unlock"]
    events.clear()
    store.clear()
    assert load_or_make(lambda: store.get("w"), Lock, make, make_missing=False) == (None, False)
    assert events == []
    assert load_or_make(lambda: store.get("w"), Lock, make) == ("mine", True)
    assert events == ["lock", "make", "unlock"]


def test_tables_for_prim_bakes_then_finds(tmp_path):
    stage = Usd.Stage.CreateInMemory()
    prim = _curves(stage, "/Fiber")
    authoring.apply_fiber(prim, "polyester", dye="disperseBlue")
    cache = TableCache(tmp_path / "c")
    with pytest.raises(MissingTableError, match="/Fiber"):
        tables_for_prim(prim, TINY, bake_missing=False, cache=cache)
    tabs = tables_for_prim(prim, TINY, cache=cache)
    assert len(tabs) == 1 and tabs[0].grid.n_phi_i == 1
    again = tables_for_prim(prim, TINY, bake_missing=False, cache=cache)
    assert np.array_equal(again[0].arrays["p"], tabs[0].arrays["p"])
    # An explicit fiber:table baked for these parameters is used as it is.
    explicit = tmp_path / "explicit.npz"
    tabs[0].save(explicit)
    authoring.apply_fiber(prim, None, table=str(explicit))
    got = tables_for_prim(prim, TINY, bake_missing=False, cache=TableCache(tmp_path / "empty"))
    assert got[0].path == str(explicit)
    # A stale one (other roughness) is reported and replaced by the cache's tables.
    authoring.apply_fiber(prim, None, beta=9.0)
    with pytest.warns(RuntimeWarning, match="other parameters"):
        with pytest.raises(MissingTableError):
            tables_for_prim(prim, TINY, bake_missing=False, cache=TableCache(tmp_path / "empty"))


# ---------------------------------------------------------------------------------------------
# Concurrent bakers
# ---------------------------------------------------------------------------------------------

def _bake_in_child(root, req, settings, barrier, out):
    import usdfiber  # noqa: F401
    from usdfiber.bake.cache import TableCache

    cache = TableCache(root)
    from usdfiber.backend import mitsuba

    mitsuba()  # import and JIT set-up before the race
    barrier.wait()
    t0 = time.perf_counter()
    res = cache.get_or_bake(req, settings)
    out.put((res.baked, time.perf_counter() - t0, str(res.path)))


def test_two_concurrent_bakers_bake_once(tmp_path):
    req = request(preset="silk", variant_count=1)
    settings = BakeSettings(resolution_deg=30, photons=6000, batches=2)
    ctx = mp.get_context("spawn")
    barrier, out = ctx.Barrier(2), ctx.Queue()
    procs = [ctx.Process(target=_bake_in_child, args=(tmp_path / "c", req, settings, barrier, out))
             for _ in range(2)]
    for p in procs:
        p.start()
    results = [out.get(timeout=300) for _ in procs]
    for p in procs:
        p.join(timeout=60)
        assert p.exitcode == 0
    baked = sorted(r[0] for r in results)
    assert baked == [False, True]
    assert results[0][2] == results[1][2]
    waiter = next(r for r in results if not r[0])
    assert waiter[1] > 0.2                     # it waited for the other's bake, then read it
    assert len(list((tmp_path / "c" / "tables").glob("*.npz"))) == 1
