"""The cost of a bake, estimated before it starts (usdfiber.bake.cost), against real bakes;
and what ``usdfiber bake`` prints of it (``--dry-run``, the long-bake warning)."""
from __future__ import annotations

import json
import math
import os
import re
import subprocess
import sys
from pathlib import Path

import pytest

import usdfiber  # noqa: F401 - registers the schema
from usdfiber.bake.baker import table_directions
from usdfiber.bake.cache import TableCache
from usdfiber.bake.cost import PROBE_LAUNCH_PHOTONS, estimate, estimate_request, launch_model, launch_shape, probe
from usdfiber.bake.requests import requests_from_preset
from usdfiber.bake.settings import BakeSettings, directions_per_group

REPO = Path(__file__).resolve().parents[2]
#: Small tables: seconds to bake.
SMALL = BakeSettings(resolution_deg=15, photons=2000, batches=2)


def run(*args):
    env = dict(os.environ)
    env["PYTHONPATH"] = str(REPO) + os.pathsep + env.get("PYTHONPATH", "")
    return subprocess.run([sys.executable, "-m", "usdfiber", *map(str, args)], capture_output=True, text=True,
                          env=env, cwd=REPO, timeout=600)


@pytest.fixture(scope="module")
def silk_bake(tmp_path_factory):
    """A silk variant's estimate, then its real bake into the same cache."""
    cache = TableCache(tmp_path_factory.mktemp("cost"))
    req = requests_from_preset("silk")[1]
    est = estimate_request(req, SMALL, cache)
    res = cache.get_or_bake(req, SMALL)
    return req, est, res, cache


def test_work_is_exact_and_size_within_five_percent(silk_bake):
    """Directions, photons and launches of a fixed-photon bake are known exactly; the size on
    disk, from the probe directions written as a table is, is within 5 % of the file."""
    req, est, res, _ = silk_bake
    photons = res.table.arrays["photons"]
    assert est.exact
    assert est.directions == photons.size == len(table_directions(req, SMALL))
    assert est.photons_per_direction == int(photons.min()) == int(photons.max())
    assert est.photons == int(res.table.header["photons"]["total"])
    group = directions_per_group(SMALL)
    assert est.launches == math.ceil(est.directions / group) * SMALL.batches
    size = os.path.getsize(res.path)
    assert abs(est.disk_bytes / size - 1.0) < 0.05, (est.disk_bytes, size)
    assert est.peak_bytes == SMALL.table_bytes()
    assert est.seconds > 0 and est.key == res.key


def test_probe_is_kept_per_fiber_and_remade_when_damaged(silk_bake):
    """A second estimate of the fiber reads the probe kept in the cache (variant 0 stands for
    every variant); a damaged probe file is measured again, never trusted."""
    req, est, _, cache = silk_bake
    files = list((cache.root / "probes").glob("*.json"))
    assert len(files) == 1
    other = requests_from_preset("silk")[3]
    again = probe(other, SMALL, cache.root)
    assert json.loads(files[0].read_text())["key"] == again.key
    assert again.seconds == pytest.approx(est.probe_seconds)   # the kept measurement, not a new one
    files[0].write_text("{not json")
    fresh = probe(other, SMALL, cache.root)
    assert fresh.key == again.key and json.loads(files[0].read_text())["key"] == fresh.key


def test_target_error_predicts_photons_from_the_probe_error(silk_bake):
    """In target-error mode the photons follow rel = c / sqrt(N) from the probe's c: a target
    4x smaller needs about 16x the photons, never fewer than the first amount nor more than
    the cap; such an estimate is not exact."""
    req, _, _, cache = silk_bake
    pr = probe(req, SMALL, cache.root)
    loose = estimate(req, BakeSettings(resolution_deg=15, photons=2000, batches=2, target_error=0.2), pr)
    tight = estimate(req, BakeSettings(resolution_deg=15, photons=2000, batches=2, target_error=0.05), pr)
    capped = estimate(req, BakeSettings(resolution_deg=15, photons=2000, batches=2, target_error=1e-4,
                                        max_photons=100_000), pr)
    assert not loose.exact and loose.photons_per_direction >= 2000
    need = (pr.error_constant / 0.05) ** 2
    assert need <= tight.photons_per_direction <= 1.05 * need + 1000
    assert capped.photons_per_direction == 100_000


def test_launch_model_is_the_line_through_two_launches_bounded_against_noise():
    """t(N) = a + N / rate through two timed launches (in either order); timings that noise
    put out of order or too close give the larger launch's mean rate or at most 4 times it,
    never a negative fixed cost or an unbounded rate."""
    a, rate = launch_model(100_000, 0.5 + 100_000 / 1e6, 250_000, 0.5 + 250_000 / 1e6)
    assert a == pytest.approx(0.5) and rate == pytest.approx(1e6)
    assert launch_model(250_000, 0.5 + 250_000 / 1e6, 100_000, 0.5 + 100_000 / 1e6) == pytest.approx((a, rate))
    assert launch_model(100_000, 1.0, 250_000, 0.9) == (0.0, pytest.approx(250_000 / 0.9))
    a, rate = launch_model(100_000, 1.0, 250_000, 1.0 + 1e-12)
    assert rate == pytest.approx(4 * 250_000 / 1.0) and a == pytest.approx(0.75)
    assert launch_model(1000, 0.2, 1000, 0.3) == (0.0, pytest.approx(1000 / 0.3))


def test_timed_launch_is_shaped_like_the_bakes():
    """The probe's timed launch: the bake's photons per batch for as many directions as make
    PROBE_LAUNCH_PHOTONS, within a group and the table's directions."""
    default = BakeSettings()                                     # 125k photons per batch
    assert launch_shape(default, 45) == (PROBE_LAUNCH_PHOTONS // 125_000, 125_000)
    render = BakeSettings(resolution_deg=6, photons=100_000, batches=4)
    assert launch_shape(render, 900) == (PROBE_LAUNCH_PHOTONS // 25_000, 25_000)
    assert launch_shape(render, 3) == (3, 25_000)
    huge = BakeSettings(photons=16_000_000, batches=4)             # one direction fills a launch
    assert launch_shape(huge, 8100) == (1, PROBE_LAUNCH_PHOTONS)
    assert launch_shape(SMALL, 144) == (min(directions_per_group(SMALL), 144), 1000)


def test_dry_run_prints_time_and_size_of_each_missing_table(tmp_path):
    out = run("bake", "--preset", "silk", "--resolution", "30", "--photons", "1000", "--batches", "2",
              "--dry-run", "--cache-dir", tmp_path)
    assert out.returncode == 0, out.stderr
    lines = out.stdout.strip().splitlines()
    tables = [l for l in lines if "  to bake:" in l]
    assert len(tables) == 4, out.stdout           # silk: four cross-section variants
    for l in tables:
        assert re.search(r"about [\d.]+ (s|min|h), [\d.]+ (B|KiB|MiB|GiB) on disk", l), l
        assert "directions x 1,000 photons" in l
    assert re.search(r"4 tables, 4 to bake: about [\d.]+ (s|min|h) on this machine", lines[-1]), lines[-1]
    assert not list((tmp_path / "tables").glob("*.npz"))       # nothing baked


def test_long_bake_warning_above_the_threshold(tmp_path):
    """The estimate is printed before baking; over --long-bake seconds a one-line warning says
    how to get a cheaper table. The default threshold (10 min) is far above this bake."""
    args = ["bake", "--preset", "polyester", "--resolution", "30", "--photons", "1000", "--batches", "2",
            "--no-progress"]
    out = run(*args, "--cache-dir", tmp_path / "a", "--long-bake", "1e-6")
    assert out.returncode == 0, out.stderr
    assert re.search(r"estimate: polyester/round variant 0: about .* on disk", out.stderr), out.stderr
    warn = [l for l in out.stderr.splitlines() if "warning: this bake is estimated" in l]
    assert len(warn) == 1 and "for a cheaper table" in warn[0]
    quiet = run(*args, "--cache-dir", tmp_path / "b")
    assert quiet.returncode == 0 and "estimate: polyester" in quiet.stderr
    assert "this bake is estimated" not in quiet.stderr


def test_bake_command_estimator_option(tmp_path):
    """``--estimator expected`` reaches the table (its header and cache key); a fiber with cuticle
    scales, which the expected value cannot take, is refused in one line before any bake; an
    unknown name is a one-line usage error."""
    base = ["bake", "--resolution", "30", "--photons", "2000", "--batches", "2", "--no-progress"]
    out = run(*base, "--preset", "polyester", "--estimator", "expected", "--expected-normals", "4",
              "--cache-dir", tmp_path / "a")
    assert out.returncode == 0, out.stderr
    tables = list((tmp_path / "a" / "tables").glob("*.npz"))
    assert len(tables) == 1
    from usdfiber.bake.table import BcsdfTable

    settings = BcsdfTable.load(tables[0]).header["bake"]["settings"]
    assert settings["estimator"] == ["expected"] and settings["expected_normals"] == 4, settings
    assert settings["expected_allocation"] == "adaptive", settings
    out = run(*base, "--preset", "polyester", "--estimator", "expected", "--expected-allocation", "uniform",
              "--cache-dir", tmp_path / "a")
    assert out.returncode == 0, out.stderr
    tables = list((tmp_path / "a" / "tables").glob("*.npz"))
    assert len(tables) == 2       # another key: the uniform allocation's table
    assert {BcsdfTable.load(t).header["bake"]["settings"].get("expected_allocation") for t in tables} == {
        "adaptive", None}
    # Normals from the distribution (the default) are in the header and key; visible ones keep earlier keys.
    assert settings["expected_sampler"] == "ndf", settings
    out = run(*base, "--preset", "polyester", "--estimator", "expected", "--expected-normals", "4",
              "--expected-sampler", "visible", "--cache-dir", tmp_path / "a")
    assert out.returncode == 0, out.stderr
    tables = list((tmp_path / "a" / "tables").glob("*.npz"))
    assert len(tables) == 3 and sum("expected_sampler" not in BcsdfTable.load(t).header["bake"]["settings"]
                                    for t in tables) == 1
    wool = run(*base, "--preset", "wool", "--estimator", "expected", "--cache-dir", tmp_path / "b")
    assert wool.returncode == 1 and len(wool.stderr.strip().splitlines()) == 1, wool.stderr
    assert "cuticle scales" in wool.stderr and "--estimator plain" in wool.stderr
    assert not (tmp_path / "b" / "tables").exists() or not list((tmp_path / "b" / "tables").glob("*.npz"))
    bad = run(*base, "--preset", "polyester", "--estimator", "magic", "--cache-dir", tmp_path / "c")
    assert bad.returncode == 2 and len(bad.stderr.strip().splitlines()) == 1 and "magic" in bad.stderr, bad.stderr
    bad = run(*base, "--preset", "polyester", "--estimator", "expected", "--expected-allocation", "greedy",
              "--cache-dir", tmp_path / "c")
    assert bad.returncode == 2 and len(bad.stderr.strip().splitlines()) == 1 and "greedy" in bad.stderr, bad.stderr
    bad = run(*base, "--preset", "polyester", "--estimator", "expected", "--expected-sampler", "ggx",
              "--cache-dir", tmp_path / "c")
    assert bad.returncode == 2 and len(bad.stderr.strip().splitlines()) == 1 and "ggx" in bad.stderr, bad.stderr


def test_reciprocity_adds_its_averaging_pass(silk_bake):
    """A box-filtered bake with reciprocity costs the same tracing plus one pass of the table's
    H and G through the averaging's scratch files (not probed: a measured rate)."""
    from usdfiber.bake.baker import table_grid
    from usdfiber.bake.cost import RECIPROCITY_BYTES_PER_SECOND
    from usdfiber.bake.reciprocity import scratch_bytes

    req, _, _, cache = silk_bake
    pr = probe(req, SMALL, cache.root)
    box = BakeSettings(resolution_deg=15, photons=2000, batches=2, incoming="box")
    rec = BakeSettings(resolution_deg=15, photons=2000, batches=2, incoming="box", estimator="reciprocity")
    extra = estimate(req, rec, pr).seconds - estimate(req, box, pr).seconds
    want = scratch_bytes(table_grid(req, rec), len(rec.levels)) / RECIPROCITY_BYTES_PER_SECOND
    assert extra == pytest.approx(want, rel=1e-9) and want > 0
