"""``BakeSettings.table_bytes`` bounds a whole baking process: the peak resident memory
(``VmHWM``: anonymous and file-backed pages) of a process that bakes a table from start to
saved file, with the estimators that need the most (the expected value and reciprocity
averaging through scratch files), stays below it. ``usdfiber bake`` holds that bound against
the memory budget before it traces anything."""
from __future__ import annotations

import json
import subprocess
import sys
import textwrap
from pathlib import Path

import pytest

from usdfiber.bake.settings import PROCESS_BYTES, BakeSettings

_CHILD = textwrap.dedent("""
    import json, sys
    from pathlib import Path
    import usdfiber
    from usdfiber.bake.baker import bake_request
    from usdfiber.bake.requests import requests_from_preset
    from usdfiber.bake.settings import BakeSettings

    st = BakeSettings(**json.loads(sys.argv[1]))
    d = Path(sys.argv[2])
    table = bake_request(requests_from_preset("silk")[0], st, resume_dir=d / "chunks")
    table.save(d / "table.npz")
    status = dict(line.split(":", 1) for line in open("/proc/self/status"))
    print(json.dumps({"hwm_bytes": int(status["VmHWM"].split()[0]) * 1024,
                      "array_bytes": sum(a.nbytes for a in table.arrays.values())}))
""")


def _bake_in_child(kw: dict, tmp_path: Path) -> dict:
    out = subprocess.run([sys.executable, "-c", _CHILD, json.dumps(kw), str(tmp_path)],
                         capture_output=True, text=True, timeout=1800)
    assert out.returncode == 0, out.stderr[-2000:]
    return json.loads(out.stdout.strip().splitlines()[-1])


@pytest.mark.skipif(not Path("/proc/self/status").exists(), reason="reads VmHWM from /proc")
@pytest.mark.slow
def test_whole_bake_stays_below_table_bytes(tmp_path):
    """A 5 deg table (1,296 directions) with the expected value and reciprocity: the part of the
    bound that grows with the table (its arrays, one averaged level) is exercised, not only the
    constants."""
    kw = {"resolution_deg": 5, "photons": 4096, "batches": 4, "incoming": "box",
          "estimator": ["expected", "reciprocity"]}
    bound = BakeSettings(**kw).table_bytes()
    got = _bake_in_child(kw, tmp_path)
    assert got["hwm_bytes"] <= bound, (got, bound)
    # The bound is not vacuous: the table itself is a sizeable part of it.
    assert got["array_bytes"] > 0.1 * (bound - PROCESS_BYTES)


@pytest.mark.skipif(not Path("/proc/self/status").exists(), reason="reads VmHWM from /proc")
def test_small_bake_stays_below_table_bytes(tmp_path):
    """The same at 15 deg (the bound's constants dominate): a quick check of the whole path."""
    kw = {"resolution_deg": 15, "photons": 2048, "batches": 2, "incoming": "box",
          "estimator": ["expected", "reciprocity"]}
    bound = BakeSettings(**kw).table_bytes()
    got = _bake_in_child(kw, tmp_path)
    assert got["hwm_bytes"] <= bound, (got, bound)
