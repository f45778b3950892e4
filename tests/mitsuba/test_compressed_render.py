"""A render served by a compressed table of the cache agrees with the render of the same table
uncompressed: within the compression bound plus the renders' noise."""
from __future__ import annotations

import math
import shutil

import numpy as np

import usdfiber  # noqa: F401  (registers schemas first)
from pxr import UsdLux

from usdfiber.bake.table import BcsdfTable
from usdfiber.cli import main
from usdfiber.image_output import read_exr_channels
from stage_util import add_side_camera, single_fiber_stage
from stats_util import FALSE_FAILURE, satterthwaite_dof, t_limit

FAST = ["--bake-resolution", "15", "--bake-photons", "1000"]
BOUND = 0.01
SEEDS = 4          # renders per cache (disjoint seeds)
BLOCK = 4          # pixels per block side


def _stage(path) -> str:
    """A dyed silk fiber (non-round: its table has azimuthal lobes) under a white dome,
    seen from the side by an orthographic camera, 1 pixel per 2 um at 40 x 20."""
    stage, prim = single_fiber_stage(path, "silk", dye="reactiveRed", depth_of_shade=1.0)
    prim.GetAttribute("fiber:profile:variantCount").Set(1)      # one table to bake and compress
    UsdLux.DomeLight.Define(stage, "/World/Dome").CreateIntensityAttr(1.0)
    add_side_camera(stage)
    stage.GetRootLayer().Save()
    return str(path)


def _render(path: str, out, seed: int) -> np.ndarray:
    assert main(["render", path, "-o", str(out), "--no-png", "--resolution", "40x20", "--spp", "8",
                 "--no-progress", "--float", "--seed", str(seed), "--no-bake", *FAST]) == 0
    ch = read_exr_channels(out)
    return np.stack([ch["R"], ch["G"], ch["B"]], -1).astype(np.float64)


def _blocks(img: np.ndarray) -> np.ndarray:
    """Sum over each BLOCK x BLOCK block and the channels (one pixel's channels share paths)."""
    h, w, c = img.shape
    return img.reshape(h // BLOCK, BLOCK, w // BLOCK, BLOCK, c).sum(axis=(1, 3, 4)).ravel()


def test_render_from_a_compressed_cache_entry_agrees(tmp_path, monkeypatch, capsys):
    path = _stage(tmp_path / "silk.usda")
    raw_cache, small_cache = tmp_path / "raw", tmp_path / "small"
    # The table baked directly (a render would first probe the fiber's bake cost); the renders
    # then find it (same physics, as good as they ask) and bake nothing.
    from pxr import Usd

    from usdfiber.bake.cache import TableCache
    from usdfiber.bake.requests import tables_for_stage
    from usdfiber.bake.settings import BakeSettings

    (req,) = tables_for_stage(Usd.Stage.Open(path))
    TableCache(raw_cache).get_or_bake(req, BakeSettings(resolution_deg=15, photons=1000, batches=2))
    monkeypatch.setenv("USDFIBER_CACHE_DIR", str(raw_cache))
    raw = [_blocks(_render(path, tmp_path / f"raw{s}.exr", s)) for s in range(SEEDS)]
    shutil.copytree(raw_cache / "tables", small_cache / "tables")
    assert main(["table", "compress", "--cache", "--cache-dir", str(small_cache)]) == 0
    files = sorted((small_cache / "tables").glob("*.npz"))
    assert files and all(BcsdfTable.load(f).compressed for f in files)
    before = {f.name: f.read_bytes() for f in files}
    monkeypatch.setenv("USDFIBER_CACHE_DIR", str(small_cache))
    small = [_blocks(_render(path, tmp_path / f"small{s}.exr", SEEDS + s)) for s in range(SEEDS)]
    capsys.readouterr()
    # The compressed tables were used as they are: none refused, re-baked or added.
    assert {f.name: f.read_bytes() for f in sorted((small_cache / "tables").glob("*.npz"))} == before

    xa, xb = np.asarray(raw), np.asarray(small)
    d = xb.mean(axis=0) - xa.mean(axis=0)
    va, vb = xa.var(axis=0, ddof=1) / SEEDS, xb.var(axis=0, ddof=1) / SEEDS
    v = va + vb
    dof_b = np.where(v > 0, v * v / np.maximum((va * va + vb * vb) / (SEEDS - 1), 1e-300), 1.0)
    dof = satterthwaite_dof(v, dof_b)
    total = float(xa.mean(axis=0).sum())
    diff, sd = float(d.sum()), math.sqrt(float(v.sum()))
    print(f"\n[compressed render] image sum {total:.4g}, difference {diff / total:+.3%} "
          f"+- {sd / total:.3%} (dof {dof:.0f})")
    assert total > 0
    # The image is a smooth (dome-lit) average of p and the albedo is kept exactly, so the
    # compression moves it by at most the bound on p per direction; the noise term is the
    # t quantile of the pooled block variances (Welch-Satterthwaite dof): false failure 1e-4.
    assert abs(diff) <= BOUND * total + t_limit(dof, FALSE_FAILURE) * sd, (diff, total, sd, dof)
