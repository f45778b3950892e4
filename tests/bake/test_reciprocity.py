"""Reciprocity averaging streamed through scratch files (:class:`ReciprocalAverage`): the same
result as averaging the whole table in memory, in the memory of one absorption level, with
its scratch files removed however it ends."""
from __future__ import annotations

import math
import os
import re
import tempfile
import tracemalloc
from typing import Any, Mapping

import numpy as np
import pytest

from usdfiber.bake import profiles
from usdfiber.bake import reciprocity
from usdfiber.bake.assembly import assemble
from usdfiber.bake.baker import bake_context, bake_table, resume_fingerprint
from usdfiber.bake.chunks import ResumeDirectory, chunk_name
from usdfiber.bake.grid import Grid
from usdfiber.bake.reciprocity import ReciprocalAverage, partner_bins, reciprocal_average
from usdfiber.bake.settings import RECIPROCITY_NODE_BYTES, RECIPROCITY_THREADS, BakeError, BakeSettings, reciprocity_bytes
from usdfiber.memory_budget import MemoryBudget

ETA = 1.55
PPB = 1000


def _incoming_measure(grid: Grid) -> np.ndarray:
    th = grid.theta_i_nodes()
    h = 0.5 * grid.step
    return grid.step * (np.sin(np.minimum(th + h, 0.5 * math.pi)) - np.sin(np.maximum(th - h, -0.5 * math.pi)))


def _dense_reference(grid: Grid, slices: Mapping[tuple[int, int], Mapping[str, Any]],
                     photons_per_batch: int) -> dict[tuple[int, int], dict[str, Any]]:
    """The averaging with the whole table in memory (what the streamed one must reproduce)."""
    n_ti, n_pi, n_r, n_c = grid.n_theta_i, grid.n_phi_i, grid.n_theta_o, grid.n_phi_o
    first = next(iter(slices.values()))
    K = int(np.asarray(first["H"]).shape[0])
    H = np.zeros((n_ti, n_pi, n_r, n_c, K), dtype=np.float32)
    G = np.zeros_like(H)
    B = np.zeros((n_ti, n_pi))
    N = np.zeros((n_ti, n_pi))
    wbar = np.zeros((n_ti, n_pi))
    for (ti, pi), d in slices.items():
        r0, r1 = d["rows"]
        H[ti, pi, r0:r1] = np.moveaxis(np.asarray(d["H"], dtype=np.float32), 0, -1)
        G[ti, pi, r0:r1] = np.moveaxis(np.asarray(d["G"], dtype=np.float32), 0, -1)
        B[ti, pi] = float(d["photons"]) / float(photons_per_batch)
        N[ti, pi] = float(d["n_hit"]) + float(d.get("misses", 0.0))
        wbar[ti, pi] = float(d["norm"]) / B[ti, pi]
    meas = np.broadcast_to(_incoming_measure(grid)[:, None], (n_ti, n_pi))
    with np.errstate(divide="ignore", invalid="ignore"):
        c = np.where(N > 0, meas * wbar / N, np.inf)
    pt, pp, pr, pc = partner_bins(grid)
    self_pair = (pt == np.arange(n_ti)[:, None, None, None]) & (pp == np.arange(n_pi)[None, :, None, None]) & (
        pr == np.arange(n_r)[None, None, :, None]) & (pc == np.arange(n_c)[None, None, None, :])
    out: dict[tuple[int, int], dict[str, Any]] = {}
    for ti in range(n_ti):
        tP, pP, rP, cP = pt[ti], pp[ti], pr[ti], pc[ti]
        cI = c[ti][:, None, None]
        cQ = c[tP, pP]
        with np.errstate(divide="ignore", invalid="ignore"):
            lam = np.where(np.isfinite(cQ), cQ / (cI + cQ), 1.0)
        lam = np.where(self_pair[ti], 1.0, lam)
        scale = (meas[tP, pP] * B[ti][:, None, None]) / (meas[ti][:, None, None] * B[tP, pP])
        a = lam[..., None].astype(np.float32)
        b = ((1.0 - lam) * scale)[..., None].astype(np.float32)
        Hn = a * H[ti] + b * H[tP, pP, rP, cP]
        Gn = a * G[ti] + b * G[tP, pP, rP, cP]
        tot, tot_n = H[ti].sum(axis=(1, 2), dtype=np.float64), Hn.sum(axis=(1, 2), dtype=np.float64)
        with np.errstate(divide="ignore", invalid="ignore"):
            keep = np.where(tot_n > 0, tot / tot_n, 0.0).astype(np.float32)[:, None, None, :]
        Hn *= keep
        Gn *= keep
        for pi in range(n_pi):
            d = slices[(ti, pi)]
            h0 = H[ti, pi, ..., 0].astype(np.float64)
            mass = h0.sum()
            ratio = float((lam[pi] * h0).sum() / mass) if mass > 0 else 1.0
            nz = np.flatnonzero(Hn[pi, ..., 0].sum(axis=-1) > 0)
            r0, r1 = (int(nz[0]), int(nz[-1]) + 1) if nz.size else (0, 1)
            new = dict(d)
            new["rows"] = (r0, r1)
            new["H"] = np.ascontiguousarray(np.moveaxis(Hn[pi, r0:r1], -1, 0))
            new["G"] = np.ascontiguousarray(np.moveaxis(Gn[pi, r0:r1], -1, 0))
            new["rel_error"] = float(d["rel_error"]) * math.sqrt(ratio)
            out[(ti, pi)] = new
    return out


def _random_slice(grid: Grid, K: int, rng: np.random.Generator, ti: int, pi: int,
                  kind: str = "random") -> dict[str, Any]:
    """A direction's result as the statistics give it: rows with light, H >= 0 falling with
    the level, G, counts. ``kind``: "random"; "dark" (no photon met the fiber: c infinite, no
    light); "unweighed" (no photon counted but light: c infinite, the partner's side is kept
    whole); "full" (light in every row)."""
    n_r, n_c = grid.n_theta_o, grid.n_phi_o
    if kind == "full":
        r0, r1 = 0, n_r
    elif kind == "dark":
        r0, r1 = 0, 1
    else:
        r0 = int(rng.integers(0, n_r - 1))
        r1 = int(rng.integers(r0 + 1, n_r + 1))
    base = rng.exponential(1.0, (r1 - r0, n_c)) * (rng.random((r1 - r0, n_c)) < 0.7)
    if kind != "full":
        base[0, 0] = base[-1, -1] = 1.0     # the rows given are those with light
    if kind == "dark":
        base[:] = 0.0
    atten = np.exp(-np.arange(K)[:, None, None] * rng.uniform(0.05, 0.5, (1, r1 - r0, n_c)))
    H = (base[None] * atten).astype(np.float32)
    G = (H * rng.uniform(0.5, 3.0, H.shape)).astype(np.float32)
    batches = int(rng.integers(1, 9))
    hit = 0 if kind in ("dark", "unweighed") else int(rng.integers(100, 5000))
    return {"rows": (r0, r1), "H": H, "G": G, "norm": float(rng.uniform(0.5, 2.0)) * batches,
            "photons": batches * PPB, "n_hit": hit, "n_cut": 0, "leaks": 0,
            "misses": 0.0 if hit == 0 else float(rng.integers(0, 50)), "rel_error": float(rng.uniform(0.01, 0.2)),
            "seconds": 0.5, "theta_i": 0.1 * ti, "phi_i": 0.2 * pi}


def _random_table(grid: Grid, K: int, seed: int) -> dict[tuple[int, int], dict[str, Any]]:
    rng = np.random.default_rng(seed)
    dirs = [(ti, pi) for ti in range(grid.n_theta_i) for pi in range(grid.n_phi_i)]
    kinds = {dirs[0]: "dark", dirs[len(dirs) // 2]: "unweighed", dirs[-1]: "full"}
    return {d: _random_slice(grid, K, rng, *d, kinds.get(d, "random")) for d in dirs}


GRIDS = [Grid(30.0), Grid(30.0, theta_symmetric=False), Grid(30.0, phi_invariant=True),
         Grid(30.0, theta_symmetric=False, phi_invariant=True), Grid(15.0)]


@pytest.mark.parametrize("grid", GRIDS, ids=lambda g: f"{g.resolution_deg:g}deg-sym{int(g.theta_symmetric)}"
                                                      f"-inv{int(g.phi_invariant)}")
def test_streamed_average_equals_the_dense_one(grid, tmp_path):
    K = 4
    slices = _random_table(grid, K, seed=int(grid.resolution_deg) + 2 * grid.theta_symmetric + grid.phi_invariant)
    ref = _dense_reference(grid, slices, PPB)
    with ReciprocalAverage(grid, K, PPB, tmp_path) as avg:
        for (ti, pi), d in reversed(list(slices.items())):      # any order
            avg.add(ti, pi, d)
        avg.finish()
        got = {key: avg.source(*key) for key in slices}
    widened = 0
    for key, want in ref.items():
        out = got[key]
        assert out.keys() == want.keys()
        assert out["rows"] == want["rows"], key
        for name in ("H", "G"):
            assert out[name].dtype == np.float32 and out[name].flags.c_contiguous
            assert out[name].shape == (K, want["rows"][1] - want["rows"][0], grid.n_phi_o)
            np.testing.assert_allclose(out[name], want[name], rtol=1e-6, atol=0, err_msg=str(key))
        assert out["rel_error"] == pytest.approx(want["rel_error"], rel=1e-12)
        for name in set(want) - {"rows", "H", "G", "rel_error"}:
            assert out[name] == want[name]
        widened += want["rows"] != tuple(slices[key]["rows"])
    # The cases the slices were built for happen: partners' light outside a direction's own
    # rows, and a direction without light that gets none (its total is its own: zero).
    assert widened > 0
    dark = next(iter(slices))
    assert got[dark]["rows"] == (0, 1) and not got[dark]["H"].any()
    # The compatibility function gives the same.
    again = reciprocal_average(grid, slices, PPB)
    for key in slices:
        np.testing.assert_array_equal(again[key]["H"], got[key]["H"])


def test_partner_bins_are_the_nodes_partners():
    for g in GRIDS:
        full = partner_bins(g)
        for ti in range(g.n_theta_i):
            for a, b in zip(full, reciprocity.node_partners(g, ti)):
                np.testing.assert_array_equal(a[ti], np.broadcast_to(b, a.shape[1:]))


def test_averaging_holds_one_level_not_the_table(tmp_path):
    """Peak of the Python-side memory while a table streams through: below one level's
    working set (:func:`reciprocity_bytes`) plus slack, while the table's H and G alone are
    K = 11 times two levels."""
    g, K = Grid(6.0), 11
    level = 4 * g.n_theta_i * g.n_phi_i * g.n_theta_o * g.n_phi_o
    rng = np.random.default_rng(5)
    tracemalloc.start()
    try:
        with ReciprocalAverage(g, K, PPB, tmp_path) as avg:
            threads = avg.threads
            for ti in range(g.n_theta_i):
                for pi in range(g.n_phi_i):
                    avg.add(ti, pi, _random_slice(g, K, rng, ti, pi))
            avg.finish()
            rows = 0
            for ti in range(g.n_theta_i):
                for pi in range(g.n_phi_i):
                    rows += avg.source(ti, pi)["rows"][1]
        _, peak = tracemalloc.get_traced_memory()
    finally:
        tracemalloc.stop()
    assert rows > 0
    bound = reciprocity_bytes(g, threads)
    node = RECIPROCITY_NODE_BYTES * level // (4 * g.n_theta_i)
    assert reciprocity_bytes(g) == 2 * level + node
    # The averaging's threads each hold one node's temporaries.
    assert 1 <= threads <= RECIPROCITY_THREADS and bound == 2 * level + threads * node
    assert peak < bound + (4 << 20), (peak, bound)
    assert peak < 2 * K * level / 4, (peak, 2 * K * level)


def test_scratch_files_are_removed_after_success_and_errors(tmp_path, monkeypatch):
    g, K = Grid(30.0), 2
    slices = _random_table(g, K, seed=3)
    with ReciprocalAverage(g, K, PPB, tmp_path) as avg:
        for key, d in slices.items():
            avg.add(*key, d)
        avg.finish()
        where = avg.directory
        assert where.parent == tmp_path and sorted(p.name for p in where.iterdir()) == ["G.f32", "H.f32"]
        avg.source(0, 0)
    assert not where.exists() and list(tmp_path.iterdir()) == []
    # An error (a direction missing) removes them too.
    with pytest.raises(BakeError, match="needs every direction; 1 missing"):
        with ReciprocalAverage(g, K, PPB, tmp_path) as avg:
            for key, d in list(slices.items())[1:]:
                avg.add(*key, d)
            avg.finish()
    assert list(tmp_path.iterdir()) == []
    with ReciprocalAverage(g, K, PPB, tmp_path) as avg:
        with pytest.raises(BakeError, match="do not fit 2 levels"):
            avg.add(0, 0, {**slices[(0, 0)], "H": slices[(0, 0)]["H"][:1]})
        with pytest.raises(RuntimeError, match="finish"):
            avg.source(0, 0)
    # Without a scratch directory: a temporary one, removed as well.
    monkeypatch.setattr(tempfile, "tempdir", str(tmp_path))
    out = reciprocal_average(g, slices, PPB)
    assert len(out) == len(slices) and list(tmp_path.iterdir()) == []


def test_refusals_are_budget_and_disk_limits(tmp_path, monkeypatch):
    g = Grid(2.0)
    need = reciprocity_bytes(g)
    # A full 2 deg table: about one level of H and G (8100 directions x 16200 bins, float32).
    assert 2 * 4 * 8100 * 16200 <= need < 1.5e9
    reciprocity.check_memory(g, 11, tmp_path, MemoryBudget(need, "test"))
    with pytest.raises(BakeError, match=r"needs about 1.\d+ GiB of memory .* budget of 1 GiB \(test\)"):
        reciprocity.check_memory(g, 11, tmp_path, MemoryBudget(1 << 30, "test"))
    free = 10 * 10 ** 9
    monkeypatch.setattr(reciprocity.shutil, "disk_usage", lambda p: type("U", (), {"free": free})())
    with pytest.raises(BakeError, match=rf"needs 11.5 GB of disk in {tmp_path} for its scratch files \(10.0 GB free\)"):
        reciprocity.check_memory(g, 11, tmp_path, MemoryBudget(need, "test"))
    # A resume directory also takes the chunks it does not hold yet (uncompressed): all of them
    # on an empty one, none once every direction is there.
    free = 30 * 10 ** 9
    full = reciprocity.scratch_bytes(g, 11) + 8100 * reciprocity.chunk_bytes(g, 11)
    assert 23.1e9 < full < 23.2e9
    reciprocity.check_memory(g, 11, tmp_path, MemoryBudget(need, "test"), chunks=True)
    free = 20 * 10 ** 9
    with pytest.raises(BakeError, match=r"needs 23.2 GB of disk .* for its scratch files and chunks \(20.0 GB free\)"):
        reciprocity.check_memory(g, 11, tmp_path, MemoryBudget(need, "test"), chunks=True)
    for ti in range(45):
        for pi in range(180):
            tmp_path.joinpath(f"d{ti:04d}_{pi:04d}.npz").touch()
    reciprocity.check_memory(g, 11, tmp_path, MemoryBudget(need, "test"), chunks=True)
    free = 10 * 10 ** 9
    # A resume directory that does not exist yet is checked on its nearest parent.
    with pytest.raises(BakeError, match=rf"in {tmp_path} "):
        reciprocity.check_memory(g, 11, tmp_path / "partial" / "key", MemoryBudget(need, "test"))
    reciprocity.check_memory(g, 9, tmp_path, MemoryBudget(need, "test"))     # 9.4 GB fits


def test_bake_refuses_before_tracing(tmp_path, monkeypatch):
    from usdfiber.bake import tracer

    def no_tracing(*args, **kwargs):
        raise AssertionError("traced before refusing")

    monkeypatch.setattr(tracer, "trace_many", no_tracing)
    st = BakeSettings(resolution_deg=30, photons=16, estimator="reciprocity", incoming="box")
    prof = profiles.ellipse(0.5, 0.3)
    monkeypatch.setenv("USDFIBER_MEMORY_BUDGET", "64K")
    with pytest.raises(BakeError, match=r"more than the memory budget of 64 KiB \(\$USDFIBER_MEMORY_BUDGET\)"):
        bake_table(prof, ETA, 10.0, None, st)
    monkeypatch.delenv("USDFIBER_MEMORY_BUDGET")
    monkeypatch.setattr(reciprocity.shutil, "disk_usage", lambda p: type("U", (), {"free": 1000})())
    with pytest.raises(BakeError, match=rf"of disk in {tmp_path / 'resume'} for its scratch files and chunks "):
        tmp_path.joinpath("resume").mkdir()
        bake_table(prof, ETA, 10.0, None, st, resume_dir=tmp_path / "resume")


@pytest.mark.parametrize("shape", ["ellipse", "circle"])
def test_bake_equals_the_dense_average_of_its_chunks(shape, tmp_path, monkeypatch):
    """A bake with the estimator against the dense averaging of the same chunks, assembled
    alike: the same table (float32 storage: no rounding between them)."""
    prof = profiles.ellipse(0.5, 0.3) if shape == "ellipse" else profiles.circle()
    st = BakeSettings(resolution_deg=30, photons=2000, batches=2, incoming="box", estimator="reciprocity",
                      storage="float32", levels=(0.0, 0.5, 2.0))
    resume = tmp_path / "resume"
    t = bake_table(prof, ETA, 15.0, None, st, resume_dir=resume)
    assert sorted(p.name for p in resume.iterdir() if not p.name.startswith("d")) == ["bake.json"]
    ctx = bake_context(prof, ETA, 15.0, None, st)
    rd = ResumeDirectory(resume, resume_fingerprint(ctx, prof))
    g = ctx.grid
    slices = {(ti, pi): rd.load(ti, pi) for ti in range(g.n_theta_i) for pi in range(g.n_phi_i)}
    assert t.header["photons"]["total"] == sum(d["photons"] for d in slices.values())
    ref = _dense_reference(g, slices, st.photons_per_batch)
    want = assemble(g, ctx.levels_um, (g.n_theta_i, g.n_phi_i), lambda ti, pi: ref[(ti, pi)], ctx.width_env, {},
                    band_tail=st.band_tail, storage=st.storage)
    for name in ("p", "p_scale", "lbar", "band_start", "albedo", "albedo_lbar", "rel_error", "photons"):
        np.testing.assert_allclose(t.arrays[name], want.arrays[name], rtol=1e-5, atol=1e-7, err_msg=name)
    # An error after the averaging (here in the assembly) removes its scratch files too.
    from usdfiber.bake import baker

    def broken(*args, **kwargs):
        raise RuntimeError("assembly failed")

    with monkeypatch.context() as m:
        m.setattr(baker, "assemble", broken)
        with pytest.raises(RuntimeError, match="assembly failed") as err:
            bake_table(prof, ETA, 15.0, None, st, resume_dir=resume)
    # (while the error, and with it the bake's frames, is still held)
    assert err.value is not None
    assert sorted(p.name for p in resume.iterdir() if not p.name.startswith("d")) == ["bake.json"]
    # Without a resume directory the scratch files go to a temporary directory, then away.
    monkeypatch.setattr(tempfile, "tempdir", str(tmp_path / "tmp"))
    (tmp_path / "tmp").mkdir()
    t2 = bake_table(prof, ETA, 15.0, None, st)
    np.testing.assert_array_equal(t2.arrays["p"], t.arrays["p"])
    assert list((tmp_path / "tmp").iterdir()) == []


def test_a_damaged_chunk_read_ahead_is_traced_again(tmp_path):
    """The averaging reads each chunk while the previous one is being added: a damaged chunk
    met that way is reported and traced again, and the table equals the undamaged bake's."""
    prof = profiles.ellipse(0.5, 0.3)
    st = BakeSettings(resolution_deg=30, photons=2000, batches=2, incoming="box", estimator="reciprocity",
                      storage="float32", levels=(0.0, 0.5, 2.0))
    resume = tmp_path / "resume"
    t = bake_table(prof, ETA, 15.0, None, st, resume_dir=resume)
    chunk = resume / "d0001_0003.npz"
    chunk.write_bytes(chunk.read_bytes()[:-100])
    with pytest.warns(RuntimeWarning, match="d0001_0003.npz: unusable partial bake chunk"):
        again = bake_table(prof, ETA, 15.0, None, st, resume_dir=resume)
    for name in ("p", "p_scale", "lbar", "albedo", "rel_error", "photons"):
        np.testing.assert_array_equal(again.arrays[name], t.arrays[name], err_msg=name)


def test_threads_follow_the_budget_and_change_nothing(tmp_path):
    """The averaging takes a second thread only where the budget holds its node's
    temporaries, and the threads' table equals one thread's bit for bit (each node is
    averaged from the level as read, whatever the order)."""
    g, K = Grid(30.0), 3
    slices = _random_table(g, K, seed=9)
    tight = MemoryBudget(reciprocity_bytes(g, 1), "test")
    wide = MemoryBudget(reciprocity_bytes(g, RECIPROCITY_THREADS), "test")
    out = {}
    for name, budget, force in (("one", tight, None), ("many", wide, None), ("forced", wide, 2)):
        with ReciprocalAverage(g, K, PPB, tmp_path, budget) as avg:
            if force:
                avg.threads = force
            assert avg.threads == (1 if name == "one" else force or RECIPROCITY_THREADS)
            for key, d in slices.items():
                avg.add(*key, d)
            avg.finish()
            out[name] = {k: avg.source(*k) for k in slices}
    for name in ("many", "forced"):
        for k in slices:
            for a in ("H", "G"):
                np.testing.assert_array_equal(out[name][k][a], out["one"][k][a])
            assert out[name][k]["rows"] == out["one"][k]["rows"]
            assert out[name][k]["rel_error"] == out["one"][k]["rel_error"]


def test_a_resumed_bake_equals_the_unstopped_one(tmp_path, monkeypatch):
    """Directions traced now go to the averaging as they are traced (never read back), those
    of an earlier run are read from their chunks after the last group: the same table."""
    prof = profiles.ellipse(0.5, 0.3)
    st = BakeSettings(resolution_deg=30, photons=2000, batches=2, incoming="box", estimator="reciprocity",
                      storage="float32", levels=(0.0, 0.5, 2.0))
    loads: list[tuple[int, int]] = []
    real_load = ResumeDirectory.load

    def load(self, ti, pi):
        loads.append((ti, pi))
        return real_load(self, ti, pi)

    monkeypatch.setattr(ResumeDirectory, "load", load)
    whole = bake_table(prof, ETA, 15.0, None, st, resume_dir=tmp_path / "whole")
    assert loads == []
    resume = tmp_path / "resumed"
    bake_table(prof, ETA, 15.0, None, st, resume_dir=resume)
    chunks = sorted(resume.glob("d*_*.npz"))
    for c in chunks[::2]:   # half the directions lost: traced again, the rest read back
        c.unlink()
    again = bake_table(prof, ETA, 15.0, None, st, resume_dir=resume)
    assert sorted(resume / chunk_name(*d) for d in loads) == chunks[1::2]
    assert again.header["photons"]["total"] == whole.header["photons"]["total"]
    for name in ("p", "p_scale", "lbar", "albedo", "rel_error", "photons"):
        np.testing.assert_array_equal(again.arrays[name], whole.arrays[name], err_msg=name)
    assert sorted(p.name for p in resume.iterdir() if not p.name.startswith("d")) == ["bake.json"]


_HOLD = """
import sys, time
from usdfiber.bake.grid import Grid
from usdfiber.bake.reciprocity import ReciprocalAverage
avg = ReciprocalAverage(Grid(30.0), 2, 1000, sys.argv[1])
print(avg.directory, flush=True)
time.sleep(120)
"""


@pytest.mark.skipif(reciprocity.fcntl is None, reason="no flock on this platform")
def test_a_killed_averagings_scratch_files_are_removed_a_live_ones_kept(tmp_path):
    """A process killed before it could remove its scratch files leaves them; the next
    averaging (or bake) in that directory removes them, and never those of a live one."""
    import signal
    import subprocess
    import sys
    import time

    proc = subprocess.Popen([sys.executable, "-c", _HOLD, str(tmp_path)], stdout=subprocess.PIPE, text=True)
    try:
        held = tmp_path / os.path.basename(proc.stdout.readline().strip())
        assert held.is_dir() and (held / "H.f32").exists()
        # Alive: kept, by a function call and by a new averaging beside it.
        assert reciprocity.remove_stale_scratch(tmp_path) == [] and held.is_dir()
        with ReciprocalAverage(Grid(30.0), 2, PPB, tmp_path) as mine:
            assert held.is_dir()
            assert reciprocity.remove_stale_scratch(tmp_path) == []
        assert not mine.directory.exists()
        proc.send_signal(signal.SIGKILL)
        proc.wait(timeout=60)
    finally:
        proc.kill()
        proc.stdout.close()
    assert held.is_dir()                      # what a killed bake leaves
    # A directory still being made (no H file yet) is left alone for a while, then removed.
    young = tmp_path / (reciprocity.SCRATCH_PREFIX + "young")
    young.mkdir()
    old = tmp_path / (reciprocity.SCRATCH_PREFIX + "old")
    old.mkdir()
    past = time.time() - 2 * reciprocity._UNLOCKED_GRACE_S
    os.utime(old, (past, past))
    assert sorted(reciprocity.remove_stale_scratch(tmp_path)) == sorted([held, old])
    assert sorted(p.name for p in tmp_path.iterdir()) == [young.name]
    # A bake in a resume directory removes them before it checks its disk.
    resume = tmp_path / "resume"
    resume.mkdir()
    stale = resume / (reciprocity.SCRATCH_PREFIX + "stale")
    stale.mkdir()
    (stale / "H.f32").write_bytes(b"\0" * 64)
    prof = profiles.ellipse(0.5, 0.3)
    st = BakeSettings(resolution_deg=30, photons=500, batches=2, incoming="box", estimator="reciprocity",
                      levels=(0.0, 0.5))
    bake_table(prof, ETA, 15.0, None, st, resume_dir=resume)
    assert sorted(p.name for p in resume.iterdir() if not p.name.startswith("d")) == ["bake.json"]


def test_a_damaged_scratch_file_is_named(tmp_path):
    """A scratch file cut short (its disk failing under it) stops the averaging with an error
    naming that file, never a silent average of zeros."""
    g, K = Grid(30.0), 2
    slices = _random_table(g, K, seed=5)
    with ReciprocalAverage(g, K, PPB, tmp_path) as avg:
        for key, d in slices.items():
            avg.add(*key, d)
        h = avg.directory / "H.f32"
        os.truncate(h, h.stat().st_size // 2)
        with pytest.raises(OSError, match=rf"{re.escape(str(h))}: scratch file shorter than written"):
            avg.finish()
    assert list(tmp_path.iterdir()) == []
