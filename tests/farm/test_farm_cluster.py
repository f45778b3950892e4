"""``usdfiber bake --scheduler`` against a scheduler and workers started as separate processes
(``dask scheduler``, ``dask worker`` on 127.0.0.1), with faults: a worker SIGKILLed mid-task,
the scheduler killed mid-bake, a worker that does not see the cache, no scheduler at all."""
from __future__ import annotations

import json
import os
import shutil
import signal
import subprocess
import time

import pytest

import usdfiber  # noqa: F401
from farm_util import (COARSE_ARGS, Processes, free_port, run_usdfiber, same_table,
                       wait_until)
from usdfiber.bake.table import BcsdfTable
from usdfiber.farm.progress import EVENT_TOPIC

TASK = ["--task-photons", "64000"]      # 32 of the table's 144 directions per task


def test_worker_killed_mid_task_loses_only_that_task(stage, reference, tmp_path):
    from distributed import Client

    cache = tmp_path / "cache"
    with Processes(tmp_path / "logs") as procs:
        addr = procs.scheduler(free_port())
        for name in ("w1", "w2"):
            procs.worker(addr, name)
        with Client(addr, timeout=30) as obs:
            obs.wait_for_workers(2, timeout=120)
            pids = obs.run(os.getpid)
            bake = procs.usdfiber(["bake", stage, "--scheduler", addr, "--json", *COARSE_ARGS, *TASK,
                                   "--cache-dir", cache], "bake")

            def running_task():
                # A trace task that started less than a second ago and is still on its worker.
                proc = obs.processing()
                for ts, msg in reversed(obs.get_events(EVENT_TOPIC)):
                    w = msg.get("worker")
                    if (msg.get("event") == "start" and msg["task"] in proc.get(w, ())
                            and time.time() - ts < 1.0):
                        return w
                return None

            victim = wait_until(running_task, 240, "a trace task running on a worker", poll=0.05)
            os.kill(pids[victim], signal.SIGKILL)
            bake.wait(timeout=600)
        out = procs.log("bake")
    assert bake.returncode == 0, out
    summary = json.loads(out[out.index("{"):out.rindex("}") + 1])
    assert summary["ok"] and summary["tasks"]["retries"] >= 1 and summary["workers"] == 2, summary
    assert "was retried" in out
    assert same_table(BcsdfTable.load(summary["tables"][0]["path"]), reference)


@pytest.mark.slow   # about a minute on 2 busy cores
def test_scheduler_killed_mid_bake_loses_nothing_finished(stage, reference, tmp_path):
    cache = tmp_path / "cache"
    with Processes(tmp_path / "logs") as procs:
        port = free_port()
        addr = procs.scheduler(port)
        procs.worker(addr, "w1")
        bake = procs.usdfiber(["bake", stage, "--scheduler", addr, *COARSE_ARGS, *TASK, "--cache-dir", cache], "bake")
        wait_until(lambda: len(list((cache / "partial").glob("*/d*.npz"))) >= 32, 300, "a finished task's chunks")
        sched = procs.procs[0]
        os.killpg(sched.pid, signal.SIGKILL)
        bake.wait(timeout=120)
        out = procs.log("bake")
    assert bake.returncode == 2 and "lost the Dask scheduler" in out, out
    kept = len(list((cache / "partial").glob("*/d*.npz")))
    assert 32 <= kept < 144
    # Rerun (here without a farm): only what is missing is traced; the same table.
    again = run_usdfiber("bake", stage, *COARSE_ARGS, "--json", "--cache-dir", cache)
    assert again.returncode == 0, again.stderr
    t = json.loads(again.stdout)["tables"][0]
    assert t["status"] == "baked" and t["resumed_directions"] >= 32
    assert same_table(BcsdfTable.load(t["path"]), reference)


def test_worker_that_does_not_see_the_cache_is_an_error(stage, tmp_path):
    if shutil.which("unshare") is None or subprocess.run(["unshare", "-m", "true"]).returncode != 0:
        pytest.skip("needs unshare -m (a mount namespace) to give a worker its own view of the filesystem")
    cache = tmp_path / "shared" / "cache"
    cache.mkdir(parents=True)
    hide = f"mount -t tmpfs none {tmp_path / 'shared'} && exec \"$0\" \"$@\""
    with Processes(tmp_path / "logs") as procs:
        addr = procs.scheduler(free_port())
        procs.worker(addr, "elsewhere", wrapper=["unshare", "-m", "--propagation", "private", "sh", "-c", hide])
        r = run_usdfiber("bake", stage, "--scheduler", addr, *COARSE_ARGS, "--cache-dir", cache, timeout=300)
    assert r.returncode == 2, r.stderr
    line = r.stderr.strip()
    assert "\n" not in line and "does not see the cache directory" in line and "worker tcp://127.0.0.1" in line and str(cache) in line
    assert not list(cache.glob("tables/*.npz"))


def test_unreachable_scheduler_is_one_line(stage, tmp_path):
    port = free_port()          # nothing listens there
    r = run_usdfiber("bake", stage, "--scheduler", f"127.0.0.1:{port}", *COARSE_ARGS, "--cache-dir", tmp_path,
                     timeout=120)
    assert r.returncode == 2
    assert r.stderr.count("\n") == 1 and "cannot reach the Dask scheduler at tcp://127.0.0.1" in r.stderr
    bad = run_usdfiber("bake", stage, "--scheduler", "local:0", *COARSE_ARGS, "--cache-dir", tmp_path)
    assert bad.returncode == 2 and "local:N needs 1 <= N" in bad.stderr and bad.stderr.count("\n") == 1
