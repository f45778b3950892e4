"""``usdfiber bake --shard I/N``: shards as separate processes, in any order, repeated, interrupted."""
from __future__ import annotations

import json
import os
import signal

import pytest

import usdfiber  # noqa: F401
from farm_util import COARSE_ARGS, Processes, run_usdfiber, same_table, wait_until
from usdfiber.bake.table import BcsdfTable

TASK = ["--task-photons", "64000"]      # 5 tasks of <= 32 directions: shard 1/3 gets 2, 2/3 2, 3/3 1


def shard(stage, spec, cache):
    r = run_usdfiber("bake", stage, "--shard", spec, "--json", *COARSE_ARGS, *TASK, "--cache-dir", cache)
    assert r.returncode == 0, r.stderr
    return json.loads(r.stdout)


def test_shards_in_any_order_and_twice_give_the_table(stage, reference, tmp_path):
    cache = tmp_path / "cache"
    s3 = shard(stage, "3/3", cache)
    assert s3["tasks"] == {"total": 1, "run": 1, "skipped": 0, "failed": 0, "retries": 0}
    assert s3["tables"][0]["status"] == "waiting" and s3["tables"][0]["missing_directions"] == 144 - 32
    s1 = shard(stage, "1/3", cache)
    assert s1["tasks"]["run"] == 2 and s1["tables"][0]["status"] == "waiting"
    again = shard(stage, "1/3", cache)                     # run twice: nothing new to trace
    assert again["tasks"]["run"] == 0 and again["tasks"]["skipped"] == 2
    s2 = shard(stage, "2/3", cache)                        # the last one assembles
    assert s2["tasks"]["run"] == 2 and s2["tables"][0]["status"] == "assembled"
    assert same_table(BcsdfTable.load(s2["tables"][0]["path"]), reference)
    late = shard(stage, "3/3", cache)                      # after the end: the table is there
    assert late["tasks"]["run"] == 0 and late["tables"][0]["status"] == "cached"


@pytest.mark.slow   # about a minute on 2 busy cores
def test_interrupted_shard_resumes(stage, reference, tmp_path):
    cache = tmp_path / "cache"
    with Processes(tmp_path / "logs") as procs:
        p = procs.usdfiber(["bake", stage, "--shard", "1/3", *COARSE_ARGS, *TASK, "--cache-dir", cache], "shard1")
        # Its first task's 32 chunks are written together; stop it before the second finishes.
        wait_until(lambda: len(list((cache / "partial").glob("*/d*.npz"))) >= 32 or p.poll() is not None, 300,
                   "the first task of shard 1/3")
        os.killpg(p.pid, signal.SIGKILL)
        p.wait(timeout=30)
    kept = len(list((cache / "partial").glob("*/d*.npz")))
    if kept >= 64:
        pytest.fail("shard 1/3 finished before it could be interrupted; make its tasks longer")
    rerun = shard(stage, "1/3", cache)
    assert rerun["tasks"]["run"] == 1 and rerun["tasks"]["skipped"] == 1, rerun
    shard(stage, "2/3", cache)
    last = shard(stage, "3/3", cache)
    assert last["tables"][0]["status"] == "assembled"
    assert same_table(BcsdfTable.load(last["tables"][0]["path"]), reference)


@pytest.mark.parametrize("spec", ["0/3", "4/3", "x/3", "1/0"])
def test_bad_shard_specs_are_one_line(stage, tmp_path, spec):
    r = run_usdfiber("bake", stage, "--shard", spec, *COARSE_ARGS, "--cache-dir", tmp_path)
    assert r.returncode == 2 and r.stderr.count("\n") == 1 and "--shard" in r.stderr, r.stderr
    r = run_usdfiber("bake", stage, "--shard", "1/2", "--scheduler", "local:1", *COARSE_ARGS, "--cache-dir", tmp_path)
    assert r.returncode == 2 and "exclude each other" in r.stderr
