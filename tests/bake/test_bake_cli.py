"""``usdfiber bake`` and ``usdfiber table``: run as a user would (``python -m usdfiber``)."""
from __future__ import annotations

import json
import os
import subprocess
import sys
from pathlib import Path

import numpy as np
import pytest

import usdfiber  # noqa: F401 - registers the schema
from pxr import Usd

from usdfiber import authoring
from stage_util import straight_curves

REPO = Path(__file__).resolve().parents[2]
COARSE = ["--resolution", "30", "--photons", "2000", "--batches", "2", "--no-progress"]


def run(*args, cache=None, cwd=None):
    env = dict(os.environ)
    env["PYTHONPATH"] = str(REPO) + os.pathsep + env.get("PYTHONPATH", "")
    if cache is not None:
        env["USDFIBER_CACHE_DIR"] = str(cache)
    return subprocess.run([sys.executable, "-m", "usdfiber", *map(str, args)], capture_output=True, text=True,
                          env=env, cwd=cwd or REPO, timeout=600)


def _curves(stage, path):
    return straight_curves(stage, path, width=0.01)


@pytest.fixture(scope="module")
def stage_file(tmp_path_factory):
    """A tiny stage: three curves inheriting one polyester class (two dyes), and a yarn of it."""
    d = tmp_path_factory.mktemp("stage")
    path = d / "tiny.usda"
    stage = Usd.Stage.CreateNew(str(path))
    authoring.define_fiber_class(stage, "/_classes/Poly", "polyester", dye="disperseRed")
    for i in range(3):
        authoring.inherit(_curves(stage, f"/World/Fiber{i}"), "/_classes/Poly")
    blue = _curves(stage, "/World/Blue")
    authoring.inherit(blue, "/_classes/Poly")
    authoring.apply_fiber(blue, None, dye="disperseBlue", depth_of_shade=3.0)
    yarn = _curves(stage, "/World/Yarn")
    authoring.apply_fiber(yarn, "polyester")
    authoring.apply_yarn(yarn, "Skala 360")
    stage.GetRootLayer().Save()
    return path


@pytest.fixture(scope="module")
def baked(stage_file, tmp_path_factory):
    cache = tmp_path_factory.mktemp("cache")
    r = run("bake", stage_file, *COARSE, "--cache-dir", cache)
    return r, cache


def test_bake_stage_bakes_exactly_what_it_needs(baked, stage_file):
    r, cache = baked
    assert r.returncode == 0, r.stderr
    lines = [l for l in r.stdout.splitlines() if l.strip()]
    assert len(lines) == 1, r.stdout            # five prims, one distinct table
    key, path = lines[0].split()[:2]
    assert len(key) == 64 and Path(path).exists() and Path(path).parent == cache / "tables"
    assert "photons=6000" in lines[0] and "error=" in lines[0] and "time=" in lines[0] and "baked" in lines[0]
    # Again: found in the cache.
    again = run("bake", stage_file, *COARSE, "--cache-dir", cache)
    assert again.returncode == 0 and "cached" in again.stdout and key in again.stdout
    dry = run("bake", stage_file, *COARSE, "--cache-dir", cache, "--dry-run")
    assert dry.returncode == 0 and "cached" in dry.stdout and "1 table" in dry.stdout


def test_bake_preset_and_params(tmp_path, baked):
    _, cache = baked
    # The polyester preset is the stage's fiber: the same table, from the cache.
    r = run("bake", "--preset", "polyester", *COARSE, cache=cache)
    assert r.returncode == 0, r.stderr
    assert "cached" in r.stdout and "preset:polyester" in r.stdout
    # A parameter file with a user cross section (an ellipse) and a progress bar on stderr.
    t = np.linspace(0, 2 * np.pi, 24, endpoint=False)
    params = {"preset": "silk", "beta": 8.0,
              "profiles": [{"loops": [[[float(10 * np.cos(a)), float(6 * np.sin(a))] for a in t]], "smooth": True}]}
    pf = tmp_path / "fiber.json"
    pf.write_text(json.dumps(params))
    r = run("bake", "--params", pf, "--resolution", "30", "--photons", "1000", "--batches", "2",
            "--cache-dir", tmp_path / "c")
    assert r.returncode == 0, r.stderr
    assert len(r.stdout.strip().splitlines()) == 1 and "baked" in r.stdout
    assert "36/36" in r.stderr                   # the bar reached the end (3 x 12 directions)


def test_bake_plot_writes_the_error_figure_beside_the_table(baked):
    _, cache = baked
    r = run("bake", "--preset", "polyester", *COARSE, "--plot", cache=cache)
    assert r.returncode == 0, r.stderr
    table_line, plot_line = r.stdout.strip().splitlines()
    table = Path(table_line.split()[1])
    assert plot_line == f"wrote {table.with_suffix('.errors.png')}" and table.with_suffix(".errors.png").stat().st_size
    refused = run("bake", "--preset", "polyester", *COARSE, "--plot", "--shard", "1/2", cache=cache)
    assert refused.returncode == 2 and "--plot" in refused.stderr and len(refused.stderr.strip().splitlines()) == 1


def test_table_inspect_and_plot(baked, tmp_path):
    r, _ = baked
    path = r.stdout.split()[1]
    ins = run("table", "inspect", path)
    assert ins.returncode == 0, ins.stderr
    for word in ("geometry:", "inputs:", "eta=", "deg", "resolution:", "photons:", "error:", "albedo:",
                 "rotationally symmetric"):
        assert word in ins.stdout, word
    js = run("table", "inspect", path, "--json")
    doc = json.loads(js.stdout)
    assert doc["header"]["resolution"]["phi_i"] == 1 and doc["summary"]["albedo"]["max"] <= 1.0 + 1e-6
    out = tmp_path / "slice.png"
    pl = run("table", "plot", path, "--theta-i", "-45", "--phi-i", "0", "--psi", "90", "--dye", "disperseRed",
             "-o", out)
    assert pl.returncode == 0, pl.stderr
    import OpenImageIO as oiio

    img = oiio.ImageBuf(str(out))
    # the default figure: Figure 3's grid with axes and a colour bar, not one block per bin
    assert img.spec().width > 600 and img.spec().height > 300
    px = img.get_pixels(oiio.FLOAT)
    assert px.max() > 0.5 and px.std() > 0.05   # not a blank image


@pytest.mark.parametrize("args,needle", [
    (["bake", "missing.usda", *COARSE], "missing.usda"),
    (["bake", *COARSE], "nothing to bake"),
    (["bake", "--preset", "nylon", *COARSE], "unknown fiber preset"),
    (["bake", "--preset", "polyester", "--resolution", "7"], "must divide 90"),
    (["bake", "--preset", "polyester", "--photons", "0"], "must be >= 1"),
    (["table", "inspect", "missing.npz"], "missing"),
    (["table", "inspect", "tests/corpus/assets/corrupt_table.npz"], "corrupt"),
    (["table", "plot", "tests/corpus/assets/corrupt_table.npz", "--theta-i", "0", "--phi-i", "0", "-o", "x.png"],
     "corrupt"),
])
def test_bad_input_one_line_exit_2(args, needle, tmp_path):
    r = run(*args, cache=tmp_path)
    assert r.returncode == 2, (r.stdout, r.stderr)
    lines = r.stderr.strip().splitlines()
    assert len(lines) == 1, r.stderr
    assert lines[0].startswith("usdfiber") and needle in lines[0], lines[0]


def test_bad_params_file_one_line(tmp_path):
    bad = tmp_path / "bad.json"
    bad.write_text(json.dumps({"preset": "silk", "diamter": 5}))
    r = run("bake", "--params", bad, *COARSE, cache=tmp_path)
    assert r.returncode == 2 and len(r.stderr.strip().splitlines()) == 1
    assert "diamter" in r.stderr and "bad.json" in r.stderr
    bad.write_text("{not json")
    r = run("bake", "--params", bad, *COARSE, cache=tmp_path)
    assert r.returncode == 2 and "not JSON" in r.stderr and len(r.stderr.strip().splitlines()) == 1
