"""Hostile cache states and disks, cache integrity and keys, outputs, and the regressions of
the other "no traceback" defects (profiles, authoring, command-line plumbing)."""
from __future__ import annotations

import copy
import errno
import os
import shutil
import subprocess
import sys
import warnings
from pathlib import Path

import numpy as np
import pytest
from pxr import Usd, UsdGeom

import usdfiber  # noqa: F401 - registers the schemas
from usdfiber import authoring, cli
from usdfiber.bake import cache as cache_module
from usdfiber.bake.cache import TableCache, TableCacheError, TableCacheWarning, cache_key, serves
from usdfiber.bake.chunks import SCALARS, ResumeDirectory
from usdfiber.bake.profiles import ProfileError, validate_loops
from usdfiber.bake.requests import requests_from_preset
from usdfiber.bake.settings import BakeSettings

ASKED = BakeSettings(resolution_deg=10, photons=20000, batches=4)   # what a render asks for


@pytest.fixture
def request_():
    return requests_from_preset("polyester")[0]


def _cached(cache: TableCache, table, request, settings: BakeSettings, *, photons: int | None = None) -> str:
    """Store ``table`` in ``cache`` as the bake of ``request`` with ``settings``; its key."""
    t = copy.copy(table)
    t.header = copy.deepcopy(table.header)
    key = cache_key(request.inputs, request.variant, settings)
    t.header.update({"cache_key": key, "inputs": request.inputs, "variant": request.variant})
    t.header["bake"]["settings"] = settings.result_inputs()
    if photons is not None:
        t.header["photons"]["min_per_direction"] = photons
    path = cache.table_path(key)
    path.parent.mkdir(parents=True, exist_ok=True)
    t.save(path)
    return key


def _no_tracing(*args, **kwargs):
    raise AssertionError("traced although the cache cannot be written")


# ---- cache keys ------------------------------------------------------------------------------------

def test_equal_settings_have_one_key(request_):
    a, b = BakeSettings(resolution_deg=10), BakeSettings(resolution_deg=10.0)
    assert a == b and hash(a) == hash(b)
    assert cache_key(request_.inputs, 0, a) == cache_key(request_.inputs, 0, b)
    assert BakeSettings(photons=np.int64(5000)).result_inputs() == BakeSettings(photons=5000).result_inputs()
    # The canonical types are those the command line always used: existing keys stay valid.
    assert BakeSettings(resolution_deg=2.0, photons=1_000_000).result_inputs()["resolution_deg"] == 2.0
    with pytest.raises(ValueError, match="photons must be an integer, got 4.5"):
        BakeSettings(photons=4.5)
    with pytest.raises(ValueError, match="seed must be an integer from 0 to 2"):
        BakeSettings(seed=-1)


def test_a_table_at_least_as_good_serves_the_request(tmp_path, circle_table, request_):
    """Tables made by `usdfiber bake` (8 batches, finer grids, more photons) serve a render's
    request (4 batches) for the same fiber; poorer or other tables do not."""
    cache = TableCache(tmp_path)
    assert cache.get_or_bake(request_, ASKED, bake_missing=False) is None
    baked = _cached(cache, circle_table, request_, BakeSettings(resolution_deg=10, photons=40000, batches=8),
                    photons=40000)
    res = cache.get_or_bake(request_, ASKED, bake_missing=False)
    assert res is not None and res.key == baked and not res.baked
    assert cache.find_serving(request_, ASKED) == baked
    # Not good enough: more photons asked, or a coarser grid.
    assert cache.get_or_bake(request_, BakeSettings(resolution_deg=10, photons=80000), bake_missing=False) is None
    assert cache.find_serving(request_, BakeSettings(resolution_deg=5, photons=1000)) is None
    # Other physics (another fiber) is never served.
    silk = requests_from_preset("silk")[0]
    assert cache.find_serving(silk, ASKED) is None
    # The exact key wins over an equivalent table.
    exact = _cached(cache, circle_table, request_, ASKED, photons=20000)
    assert cache.get_or_bake(request_, ASKED, bake_missing=False).key == exact
    header = {"bake": {"settings": {"resolution_deg": 5.0}}, "photons": {"min_per_direction": 10},
              "error_estimate": {"max": 0.02}}
    assert serves(header, BakeSettings(resolution_deg=10, photons=10, target_error=0.05))
    assert not serves(header, BakeSettings(resolution_deg=10, photons=10, target_error=0.01))


# ---- cache integrity ---------------------------------------------------------------------------------

def test_a_table_without_its_key_serves_no_key(tmp_path, circle_table, request_):
    cache = TableCache(tmp_path)
    key = cache.key(request_, ASKED)
    for header_key in (None, "0" * 64):
        t = copy.copy(circle_table)
        t.header = {k: v for k, v in circle_table.header.items() if k != "cache_key"}
        if header_key:
            t.header["cache_key"] = header_key
        cache.table_path(key).parent.mkdir(parents=True, exist_ok=True)
        t.save(cache.table_path(key))
        with pytest.warns(TableCacheWarning, match="written for another cache key; baking it again"):
            assert cache.load(key) is None
        assert not cache.table_path(key).exists()


def _chunk(n: int = 3) -> dict:
    data = {"rows": (0, 2), "H": np.ones((2, 2, n)), "G": np.ones((2, 2, n))}
    data.update({k: 1 for k in SCALARS})
    return data


def test_a_chunk_names_its_bake_and_direction(tmp_path):
    rd = ResumeDirectory(tmp_path / "p", {"bake": 1})
    rd.save(0, 0, _chunk())
    rd.save(0, 1, _chunk())
    assert rd.load(0, 0) is not None
    shutil.copy(rd.chunk_path(0, 0), rd.chunk_path(0, 1))     # copied over another direction's chunk
    with pytest.warns(RuntimeWarning, match=r"holds direction \[0, 0\], not \[0, 1\]\); tracing that direction again"):
        assert rd.load(0, 1) is None
    other = ResumeDirectory(tmp_path / "q", {"bake": 2})
    other.save(0, 2, _chunk())
    shutil.copy(other.chunk_path(0, 2), rd.chunk_path(0, 2))  # another bake's chunk
    with pytest.warns(RuntimeWarning, match="written by another bake"):
        assert rd.load(0, 2) is None
    rd.chunk_path(1, 1).write_bytes(b"garbage")
    with pytest.warns(RuntimeWarning, match="unusable partial bake chunk"):
        assert rd.load(1, 1) is None
    (rd.path / "bake.json").write_text("{not the same bake")
    ResumeDirectory(tmp_path / "p", {"bake": 1})               # another fingerprint: chunks removed
    assert not list(rd.path.glob("d*.npz"))


@pytest.mark.parametrize("name, change, reason", [
    ("nan-H", lambda d: d["H"].__setitem__((0, 0, 0), np.nan), "H holds values that are not finite"),
    ("negative-G", lambda d: d["G"].__setitem__((1, 1, 1), -1.0), "G holds values that are not finite"),
    ("inf-norm", lambda d: d.update(norm=np.inf), "scalars holds values that are not finite"),
    ("negative-photons", lambda d: d.update(photons=-3), "scalars holds values that are not finite"),
    ("integer-H", lambda d: d.update(H=np.ones((2, 2, 3), np.int32)), "H holds values that are not finite"),
    ("other-levels", lambda d: d.update(H=np.ones((5, 2, 3)), G=np.ones((5, 2, 3))),
     r"H has shape \(5, 2, 3\) at rows \[0, 2\], not \(2, rows, 3\) within 4 rows"),
    ("other-columns", lambda d: d.update(H=np.ones((2, 2, 7)), G=np.ones((2, 2, 7))),
     r"H has shape \(2, 2, 7\) at rows \[0, 2\], not \(2, rows, 3\)"),
    ("rows-beyond-grid", lambda d: d.update(rows=(3, 5)),
     r"H has shape \(2, 2, 3\) at rows \[3, 5\], not .* within 4 rows"),
    ("rows-negative", lambda d: d.update(rows=(-2, 0)), r"H has shape \(2, 2, 3\) at rows \[-2, 0\]"),
])
def test_a_chunk_whose_checksums_hold_but_whose_values_cannot_be_used(tmp_path, name, change, reason):
    """A chunk written with valid checksums (a hand-edited file, a bug in an older version)
    whose sums are not finite or do not fit the bake's histograms is traced again, never used."""
    rd = ResumeDirectory(tmp_path / "p", {"bake": 1}, histogram=(2, 4, 3))
    rd.save(0, 0, _chunk())
    assert rd.load(0, 0) is not None
    data = _chunk()
    data["H"], data["G"] = data["H"].copy(), data["G"].copy()
    change(data)
    rd.save(0, 1, data)
    with pytest.warns(RuntimeWarning, match=rf"d0000_0001.npz: unusable partial bake chunk \({reason}"):
        assert rd.load(0, 1) is None


def test_a_chunks_scalars_alone_are_verified(tmp_path):
    """``load_scalars`` gives what ``load`` gives of a chunk's scalars, without its histograms,
    and refuses what ``load`` refuses of them: another direction's or bake's chunk, damage,
    negative counts. A damaged histogram it does not read is not its concern."""
    rd = ResumeDirectory(tmp_path / "p", {"bake": 1}, histogram=(2, 4, 3))
    rd.save(0, 0, {**_chunk(), "photons": 7, "rel_error": 0.25})
    full, alone = rd.load(0, 0), rd.load_scalars(0, 0)
    assert alone == {k: full[k] for k in SCALARS} and alone["photons"] == 7
    shutil.copy(rd.chunk_path(0, 0), rd.chunk_path(0, 1))
    with pytest.warns(RuntimeWarning, match=r"d0000_0001.npz: unusable partial bake chunk \(holds direction"
                                            r" \[0, 0\], not \[0, 1\]\); not used"):
        assert rd.load_scalars(0, 1) is None
    other = ResumeDirectory(tmp_path / "q", {"bake": 2})
    other.save(0, 2, _chunk())
    shutil.copy(other.chunk_path(0, 2), rd.chunk_path(0, 2))
    with pytest.warns(RuntimeWarning, match="written by another bake"):
        assert rd.load_scalars(0, 2) is None
    rd.save(0, 3, {**_chunk(), "photons": -3})
    with pytest.warns(RuntimeWarning, match="scalars holds values that are not finite"):
        assert rd.load_scalars(0, 3) is None
    rd.chunk_path(1, 1).write_bytes(b"garbage")
    with pytest.warns(RuntimeWarning, match="unusable partial bake chunk"):
        assert rd.load_scalars(1, 1) is None
    rd.save(1, 2, {**_chunk(), "H": np.full((2, 2, 3), np.nan)})
    with pytest.warns(RuntimeWarning, match="H holds values that are not finite"):
        assert rd.load(1, 2) is None
    assert rd.load_scalars(1, 2)["photons"] == 1


def test_an_error_estimate_of_infinity_is_a_usable_chunk(tmp_path):
    """A direction that no light leaves has an infinite error estimate: its chunk is kept."""
    rd = ResumeDirectory(tmp_path / "p", {"bake": 1}, histogram=(2, 4, 3))
    rd.save(0, 0, {**_chunk(), "rel_error": np.inf})
    assert rd.load(0, 0)["rel_error"] == np.inf


def test_a_bake_traces_again_a_chunk_with_nan_sums(tmp_path):
    """End to end: a resumed bake replaces a NaN chunk of its own key by a fresh trace and the
    table equals a bake from scratch."""
    from usdfiber.bake import profiles
    from usdfiber.bake.baker import bake_table
    from usdfiber.bake.settings import BakeSettings
    from usdfiber.table_format import read_table, write_table

    settings = BakeSettings(resolution_deg=30, photons=400, batches=2)
    reference = bake_table(profiles.circle(), 1.55, 8.0, None, settings, resume_dir=tmp_path / "r")
    chunk = tmp_path / "r" / "d0001_0000.npz"
    header, arrays = read_table(chunk, container="usdfiber-bake-chunk")
    arrays["H"] = np.full_like(arrays["H"], np.nan)
    write_table(chunk, {k: v for k, v in header.items() if k not in ("arrays", "checksums")}, arrays,
                container="usdfiber-bake-chunk")
    with pytest.warns(RuntimeWarning, match="d0001_0000.npz: unusable partial bake chunk"):
        again = bake_table(profiles.circle(), 1.55, 8.0, None, settings, resume_dir=tmp_path / "r")
    assert np.all(np.isfinite(again.arrays["p"].astype(np.float32)))
    np.testing.assert_array_equal(again.arrays["p"], reference.arrays["p"])


def test_a_chunk_that_cannot_be_written_stops_the_bake(tmp_path, monkeypatch):
    """Chunks are written while the next group traces: a write that fails (a full disk) stops
    the bake with that error, and the chunks written before it are kept."""
    from usdfiber.bake import profiles
    from usdfiber.bake.baker import bake_table

    monkeypatch.setattr("usdfiber.bake.settings.GROUP_DIRECTIONS", 2)
    real, calls = ResumeDirectory.save, []

    def save(self, ti, pi, data):
        calls.append((ti, pi))
        if len(calls) == 3:
            raise OSError(errno.ENOSPC, "No space left on device")
        real(self, ti, pi, data)

    monkeypatch.setattr(ResumeDirectory, "save", save)
    settings = BakeSettings(resolution_deg=30, photons=400, batches=2)
    with pytest.raises(OSError, match="No space left"):
        bake_table(profiles.circle(), 1.55, 8.0, None, settings, resume_dir=tmp_path / "r")
    # The first group's two chunks, written before the failure (three directions: groups of
    # two and one); the second group's write failed and reached the caller.
    assert sorted(p.name for p in (tmp_path / "r").glob("d*.npz")) == ["d0000_0000.npz", "d0001_0000.npz"]
    assert len(calls) == 3


# ---- cache and disk states ---------------------------------------------------------------------------

def test_tables_being_a_file_fails_before_tracing(tmp_path, request_, monkeypatch):
    monkeypatch.setattr(cache_module, "bake_request", _no_tracing)
    (tmp_path / "tables").write_text("not a directory")
    with pytest.raises(TableCacheError, match=r"tables: .*a file where the cache keeps a directory.*--cache-dir"):
        TableCache(tmp_path).get_or_bake(request_, ASKED)


def test_a_lock_path_that_is_a_directory(tmp_path, request_, monkeypatch):
    monkeypatch.setattr(cache_module, "bake_request", _no_tracing)
    cache = TableCache(tmp_path)
    cache.lock_path(cache.key(request_, ASKED)).mkdir(parents=True)
    with pytest.raises(TableCacheError, match=r"\.lock: Is a directory \(a directory where the cache keeps a file\)"):
        cache.get_or_bake(request_, ASKED)


def test_a_table_path_that_is_a_directory(tmp_path, request_):
    cache = TableCache(tmp_path)
    cache.table_path(cache.key(request_, ASKED)).mkdir(parents=True)
    with pytest.raises(TableCacheError, match=r"\.npz: is a directory, where the cache keeps a file; remove it"):
        cache.get_or_bake(request_, ASKED)


def test_a_read_only_cache(tmp_path, request_, monkeypatch):
    """A read-only file system (simulated: root ignores permission bits)."""
    monkeypatch.setattr(cache_module, "bake_request", _no_tracing)

    def read_only(self, *args, **kwargs):
        raise OSError(errno.EROFS, os.strerror(errno.EROFS), str(self))

    monkeypatch.setattr(Path, "mkdir", read_only)
    with pytest.raises(TableCacheError, match=r"locks: Read-only file system; the table cache .* must be a writable"):
        TableCache(tmp_path).get_or_bake(request_, ASKED)


def test_a_full_disk_leaves_no_half_written_table(tmp_path, request_, circle_table, monkeypatch):
    monkeypatch.setattr(cache_module, "bake_request", lambda *a, **k: copy.deepcopy(circle_table))

    def full(fd):
        raise OSError(errno.ENOSPC, os.strerror(errno.ENOSPC))

    monkeypatch.setattr("usdfiber.atomic_file.os.fsync", full)
    cache = TableCache(tmp_path)
    with pytest.raises(TableCacheError, match="No space left on device"):
        cache.get_or_bake(request_, ASKED)
    assert list((tmp_path / "tables").iterdir()) == []      # no table, no temporary file


def test_cache_errors_are_one_line_on_the_command_line(tmp_path, capsys):
    (tmp_path / "tables").write_text("")
    rc = cli.main(["bake", "--preset", "silk", "--resolution", "30", "--photons", "100", "--no-progress",
                   "--cache-dir", str(tmp_path)])
    err = capsys.readouterr().err
    errors = [line for line in err.splitlines() if line.startswith("usdfiber: error:")]
    # the bake's estimate lines may come first; the error itself is one line, no traceback
    assert rc == 1 and len(errors) == 1 and "a file where the cache keeps a directory" in errors[0]
    assert "Traceback" not in err and err.endswith(errors[0] + "\n")


# ---- outputs -----------------------------------------------------------------------------------------

def test_an_output_that_cannot_be_written_is_refused_before_rendering(tmp_path, capsys):
    from usdfiber.translators.mitsuba.render import RenderJob, RenderRefused, render_stage

    stage = str(Path(__file__).resolve().parents[1] / "corpus" / "bad" / "diameter_negative.usda")
    with pytest.raises(RenderRefused, match=r"cannot write .*out.exr: the folder .*nowhere does not exist"):
        render_stage(RenderJob(stage=stage, output=tmp_path / "nowhere" / "out.exr"))
    (tmp_path / "dir.png").mkdir()
    with pytest.raises(RenderRefused, match=r"dir.png: it is a directory"):
        render_stage(RenderJob(stage=stage, output=tmp_path / "o.exr", png=tmp_path / "dir.png"))


def test_an_image_writer_that_writes_nothing_is_an_error(tmp_path, monkeypatch):
    import OpenImageIO as oiio

    from usdfiber import image_output

    class Silent:
        def open(self, *a):
            return True

        def write_image(self, *a):
            return True

        def close(self):
            return True

    monkeypatch.setattr(oiio.ImageOutput, "create", staticmethod(lambda fmt: Silent()))
    with pytest.raises(image_output.ImageOutputError, match=r"cannot write .*x.png: the image writer left an empty"):
        image_output.write_display_png(tmp_path / "x.png", np.full((4, 4, 3), 0.5, np.float32))
    assert not (tmp_path / "x.png").exists()


# ---- command-line plumbing -----------------------------------------------------------------------------

def test_a_closed_pipe_ends_quietly():
    """`usdfiber ... | head -1`: the reader goes away; no BrokenPipeError traceback."""
    p = subprocess.Popen([sys.executable, "-m", "usdfiber", "presets"], stdout=subprocess.PIPE,
                         stderr=subprocess.PIPE)
    p.stdout.close()
    err = p.stderr.read().decode()
    assert p.wait(timeout=120) == 141
    assert "Traceback" not in err and "BrokenPipe" not in err


def test_python_warnings_are_one_line(capsys):
    with warnings.catch_warnings():
        cli.main(["presets", "silk"])
        assert warnings.showwarning is cli.show_warning_line
        capsys.readouterr()
        warnings.warn("a cached table\nis damaged", UserWarning)
    err = capsys.readouterr().err
    assert err == "usdfiber: warning: a cached table is damaged\n"


# ---- profiles ----------------------------------------------------------------------------------------------

def test_a_fine_circle_is_not_self_intersecting():
    for n in (30_000, 100_000):
        t = 2 * np.pi * np.arange(n) / n
        circle = np.stack([np.cos(t), np.sin(t)], 1)
        validate_loops([circle], "circle")
        validate_loops([circle * 1e-4 + 500.0], "small circle far from the origin")
    # One vertex pushed across the far side of a 100k-point wavy loop is still found.
    n = 100_000
    t = 2 * np.pi * np.arange(n) / n
    r = 1 + 0.3 * np.cos(50 * t)
    wavy = np.stack([r * np.cos(t), r * np.sin(t)], 1)
    validate_loops([wavy], "wavy")
    wavy[5000] = 0.5 * (wavy[60000] + wavy[60001])
    with pytest.raises(ProfileError, match="self-intersection between edges 4999 and 60000"):
        validate_loops([wavy], "wavy")


# ---- authoring -----------------------------------------------------------------------------------------------

def test_authoring_refuses_values_the_validators_refuse():
    stage = Usd.Stage.CreateInMemory()
    prim = UsdGeom.BasisCurves.Define(stage, "/C").GetPrim()
    with pytest.raises(authoring.AuthoringError, match=r"/C.fiber:diameter: -5.0 is out of range; expected a value "
                                                       r"in \(0, 1000\] um"):
        authoring.apply_fiber(prim, "cotton", diameter=-5)
    assert not prim.HasAPI("FiberAPI")                                     # nothing half-authored
    with pytest.raises(authoring.AuthoringError, match=r"depthOfShade: -1.0 is out of range"):
        authoring.apply_fiber(prim, "cotton", dye="reactiveRed", depth_of_shade=-1)
    authoring.apply_fiber(prim, "cotton", dye="reactiveRed", depth_of_shade=1.0)
    with pytest.raises(authoring.AuthoringError, match=r"depthOfShade: 50.0 is out of range; expected a value "
                                                       r"in \[0, 10\] %"):
        authoring.add_depth_of_shade_variants(prim, {"pale": 0.5, "absurd": 50.0})
    assert not prim.GetVariantSets().GetNames()                            # checked before authoring


def test_adding_shades_keeps_the_selection():
    stage = Usd.Stage.CreateInMemory()
    prim = UsdGeom.BasisCurves.Define(stage, "/C").GetPrim()
    authoring.apply_fiber(prim, "cotton", dye="reactiveRed", depth_of_shade=1.0)
    authoring.add_depth_of_shade_variants(prim, {"pale": 0.1, "deep": 4.0}, default="deep")
    vset = authoring.add_depth_of_shade_variants(prim, {"medium": 2.0})
    assert vset.GetVariantSelection() == "deep"
    assert sorted(vset.GetVariantNames()) == ["deep", "medium", "pale"]
    assert prim.GetAttribute("fiber:dye:depthOfShade").Get() == pytest.approx(4.0)
