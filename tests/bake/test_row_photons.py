"""A per-row photon schedule (``BakeSettings.row_photons``): each theta_i row gets its own
photons exactly, shared among its batches, the cache key records the schedule, the cost
estimate counts it exactly, and a schedule that does not fit the table is refused before any
tracing."""
from __future__ import annotations

import math

import numpy as np
import pytest

import usdfiber  # noqa: F401 - registers the schema
from usdfiber.bake import tracer
from usdfiber.bake.baker import bake_request, table_grid
from usdfiber.bake.cost import estimate_request
from usdfiber.bake.requests import requests_from_preset
from usdfiber.bake.settings import BakeError, BakeSettings

BASE = BakeSettings(resolution_deg=15, photons=2000, batches=2)     # 1000 photons per batch


def _schedule(n_rows: int) -> tuple[int, ...]:
    # Below one direction's minimum (2 full batches), between batches, whole batches.
    pattern = (10, 2500, 6000, 1000)
    return tuple(pattern[i % len(pattern)] for i in range(n_rows))


def test_settings_refuse_bad_schedules():
    for bad in ("12", [0], [1.5], [float("nan")], [float("inf")], [True], [], [-3], [2e12]):
        with pytest.raises(BakeError, match="row_photons"):
            BakeSettings(row_photons=bad)
    with pytest.raises(BakeError, match="target error"):
        BakeSettings(row_photons=[1000], target_error=0.05)
    with pytest.raises(BakeError, match="auto"):
        BakeSettings(row_photons=[1000], auto_resolution=True)
    with pytest.raises(BakeError, match="at least one photon per batch"):
        BakeSettings(batches=4, row_photons=[1000, 3])


def test_cache_key_records_the_schedule():
    """Equal schedules in any integer form have one key; another schedule, or none, another;
    tables without a schedule keep the keys they had."""
    a = BakeSettings(row_photons=[1000, 2000])
    b = BakeSettings(row_photons=(np.int64(1000), 2000.0))
    assert a.result_inputs() == b.result_inputs() and a.row_photons == (1000, 2000)
    assert a.result_inputs() != BakeSettings(row_photons=[1000, 3000]).result_inputs()
    assert "row_photons" not in BakeSettings().result_inputs()
    assert a.result_inputs() != BakeSettings().result_inputs()


def test_rows_get_their_photons_exactly_in_shared_batches():
    s = BakeSettings(photons=2000, batches=2, row_photons=[10, 2500, 6000])
    assert [s.row_batches(i) for i in range(3)] == [2, 3, 6]
    assert [[s.batch_photons(i, b) for b in range(s.row_batches(i))] for i in range(3)] == [
        [5, 5], [834, 833, 833], [1000] * 6]
    assert s.batch_photons(0, 2) == 1000            # past the row's batches: full ones
    plain = BakeSettings(photons=2000, batches=2)
    assert plain.row_batches(5) == 2 and plain.batch_photons(5, 0) == 1000


def test_whole_batch_schedules_keep_their_key():
    """A schedule of whole batches traces what it traced when rows were rounded up to whole
    batches: the same key (chunks and cached tables stay valid). One that shares a row among
    its batches traces other photons: another key."""
    whole = BakeSettings(photons=2000, batches=2, row_photons=[2000, 6000])
    assert whole.whole_batch_schedule() and "row_batches" not in whole.result_inputs()
    for rows in ([2000, 2500], [1000, 6000]):       # a partial batch; fewer than 2 full batches
        shared = BakeSettings(photons=2000, batches=2, row_photons=rows)
        assert not shared.whole_batch_schedule()
        assert shared.result_inputs()["row_batches"] == "shared"
        assert shared.result_inputs() != BakeSettings(photons=2000, batches=2, row_photons=[2000, 6000]).result_inputs()


def test_schedule_of_another_grid_is_refused_before_tracing(monkeypatch):
    req = requests_from_preset("silk")[0]
    n_rows = table_grid(req, BASE).n_theta_i

    def no_tracing(*a, **k):
        raise AssertionError("traced before the schedule was checked")

    monkeypatch.setattr(tracer, "trace_many", no_tracing)
    from dataclasses import replace

    with pytest.raises(BakeError, match=f"row_photons has {n_rows + 1} rows.*{n_rows} theta_i rows"):
        bake_request(req, replace(BASE, row_photons=(1000,) * (n_rows + 1)))


def test_scheduled_bake_and_its_exact_estimate(tmp_path, monkeypatch):
    """Every direction of row ``ti`` traces its row's photons exactly, in ``row_batches(ti)``
    batches; the estimate's photons and tracer launches are those of the real bake (launches
    counted at the tracer)."""
    from dataclasses import replace

    req = requests_from_preset("silk")[1]
    grid = table_grid(req, BASE)
    st = replace(BASE, row_photons=_schedule(grid.n_theta_i))
    est = estimate_request(req, st)
    launches = []
    real = tracer.trace_many

    def counted(*a, **k):
        launches.append(1)
        return real(*a, **k)

    monkeypatch.setattr(tracer, "trace_many", counted)
    table = bake_request(req, st)
    photons = np.asarray(table.arrays["photons"]).reshape(grid.n_theta_i, grid.n_phi_i)
    want = np.array(st.row_photons)
    assert np.array_equal(photons, np.broadcast_to(want[:, None], photons.shape))
    assert est.photons == int(table.header["photons"]["total"]) == int(photons.sum())
    assert est.launches == len(launches)
    assert est.photons_per_direction == round(photons.mean())
    assert table.header["bake"]["settings"]["row_photons"] == list(st.row_photons)
    assert math.isfinite(est.seconds) and est.seconds > 0


def _cli(*args):
    import os
    import subprocess
    import sys
    from pathlib import Path

    repo = Path(__file__).resolve().parents[2]
    env = dict(os.environ)
    env["PYTHONPATH"] = str(repo) + os.pathsep + env.get("PYTHONPATH", "")
    return subprocess.run([sys.executable, "-m", "usdfiber", *map(str, args)], capture_output=True, text=True,
                          env=env, cwd=repo, timeout=600)


def test_bake_command_row_photons(tmp_path):
    """``--row-photons`` from a list or a JSON file reaches the estimate; a schedule with
    another row count than a requested table's grid, or a token that is not a positive
    integer, is one line before any bake."""
    base = ["bake", "--preset", "polyester", "--resolution", "30", "--photons", "1000", "--batches", "2",
            "--dry-run", "--cache-dir", tmp_path / "c"]
    ok = _cli(*base, "--row-photons", "1000,2000,3000")       # polyester at 30 deg: 3 theta_i rows
    assert ok.returncode == 0, ok.stderr
    assert "3 directions x 2,000 photons" in ok.stdout, ok.stdout
    (tmp_path / "rows.json").write_text("[1000, 2e3, 3000]")
    same = _cli(*base, "--row-photons", tmp_path / "rows.json")
    assert same.returncode == 0 and same.stdout.split()[0] == ok.stdout.split()[0], same.stderr  # one key
    wrong = _cli(*base, "--row-photons", "1000,2000")
    assert wrong.returncode == 1 and len(wrong.stderr.strip().splitlines()) == 1, wrong.stderr
    assert "polyester" in wrong.stderr and "2 rows" in wrong.stderr and "3 theta_i rows" in wrong.stderr
    for bad in ("1000,x,3000", "1000,-5,3000", str(tmp_path / "missing.json")):
        out = _cli(*base, "--row-photons", bad)
        assert out.returncode == 2 and len(out.stderr.strip().splitlines()) == 1, out.stderr
        assert "--row-photons" in out.stderr
    few = _cli(*base, "--row-photons", "1000,1,3000")          # fewer photons than batches (2)
    assert few.returncode == 2 and len(few.stderr.strip().splitlines()) == 1, few.stderr
    assert "row_photons" in few.stderr and "one photon per batch" in few.stderr
    assert not list((tmp_path / "c").glob("tables/*.npz"))


def test_shared_batches_weigh_by_their_photons():
    """A box-filtered direction's batches weigh by the power their beam carries, in proportion
    to their photons: its ``norm`` (the sum of its batches' weights) is the bin's power times
    its photons in full batches, whether the row is whole batches or shared unevenly. The
    reciprocity averaging rescales partners by exactly that (photons / photons_per_batch); a
    weight per batch regardless of its photons would mis-scale every row that is no whole
    number of batches."""
    from usdfiber.bake.baker import bake_context, trace_directions
    from usdfiber.bake.statistics import DirectionStatistics

    req = requests_from_preset("silk")[0]
    st = BakeSettings(resolution_deg=30, photons=2000, batches=2, incoming="box", row_photons=(1500, 2500, 4000))
    ctx = bake_context(req.profile(), req.eta, req.beta_deg, None, st)
    dirs = [(0, 0), (1, 3), (2, 5)]
    for (ti, pi), d in zip(dirs, trace_directions(ctx, dirs)):
        assert d["photons"] == st.row_photons[ti]
        power = DirectionStatistics(ctx, ti, pi).box_weight
        assert d["norm"] == pytest.approx(power * st.row_photons[ti] / st.photons_per_batch, rel=1e-12)
        assert math.isfinite(d["rel_error"]) and d["rel_error"] > 0
