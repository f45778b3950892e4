"""The schema plugin: generated files in sync with schema.usda, the CMake job, registration."""
from __future__ import annotations

import os
import shutil
import subprocess
import sys
from pathlib import Path

import pytest

ROOT = Path(__file__).resolve().parents[2]


def _usdgenschema() -> str:
    import pxr.Usd

    return str(Path(pxr.Usd.__file__).parent / "usdGenSchema.py")


def _validate(schema_dir: Path) -> subprocess.CompletedProcess:
    pytest.importorskip("jinja2")
    return subprocess.run(
        [sys.executable, _usdgenschema(), "--validate", "--quiet",
         str(schema_dir / "schema.usda"), str(schema_dir / "generated")],
        capture_output=True, text=True,
    )


def _stale_copy(tmp_path: Path) -> Path:
    copy = tmp_path / "src"
    shutil.copytree(ROOT / "schema", copy / "schema")
    usda = copy / "schema" / "schema.usda"
    text = usda.read_text()
    assert "uniform int yarn:plies = 2" in text
    usda.write_text(text.replace("uniform int yarn:plies = 2", "uniform int yarn:plies = 3"))
    return copy


def test_generated_files_are_current():
    res = _validate(ROOT / "schema")
    assert res.returncode == 0, res.stdout + res.stderr


def test_stale_generated_files_are_detected(tmp_path):
    res = _validate(_stale_copy(tmp_path) / "schema")
    assert res.returncode != 0
    assert "diffs found" in res.stdout + res.stderr


@pytest.mark.skipif(shutil.which("cmake") is None, reason="cmake not installed")
@pytest.mark.parametrize("stale", [False, True])
def test_cmake_job_checks_and_installs(tmp_path, stale):
    pytest.importorskip("jinja2")
    src = _stale_copy(tmp_path) if stale else tmp_path / "src"
    if not stale:
        shutil.copytree(ROOT / "schema", src / "schema")
    shutil.copy(ROOT / "CMakeLists.txt", src / "CMakeLists.txt")
    shutil.copy(ROOT / "usdFiber.py", src / "usdFiber.py")  # installed beside the package
    build, prefix = tmp_path / "build", tmp_path / "prefix"
    run = lambda *a: subprocess.run(list(a), capture_output=True, text=True)  # noqa: E731
    cfg = run("cmake", "-S", str(src), "-B", str(build), f"-DPython3_EXECUTABLE={sys.executable}",
              f"-DCMAKE_INSTALL_PREFIX={prefix}")
    assert cfg.returncode == 0, cfg.stdout + cfg.stderr
    bld = run("cmake", "--build", str(build))
    if stale:
        assert bld.returncode != 0, "a stale generated schema must fail the build"
        return
    assert bld.returncode == 0, bld.stdout + bld.stderr
    inst = run("cmake", "--install", str(build))
    assert inst.returncode == 0, inst.stdout + inst.stderr
    res = prefix / "usdfiber" / "resources" / "usdFiber"
    assert (res / "plugInfo.json").read_text() == (ROOT / "schema/generated/plugInfo.json").read_text()
    assert (res / "generatedSchema.usda").is_file()


def _py(code: str, env: dict | None = None) -> subprocess.CompletedProcess:
    return subprocess.run([sys.executable, "-c", code], capture_output=True, text=True,
                          env={**os.environ, **(env or {})}, cwd=ROOT)


def test_import_registers_schemas():
    res = _py(
        "import usdfiber\n"
        "from pxr import Usd\n"
        "s = Usd.Stage.CreateInMemory(); p = s.DefinePrim('/c', 'BasisCurves')\n"
        "for n in ('FiberAPI', 'FiberYarnAPI'): assert p.CanApplyAPI(n), n\n"
        "p.ApplyAPI('FiberAPI'); print(p.GetAttribute('fiber:diameter').Get())\n"
        "assert not s.DefinePrim('/m', 'Mesh').CanApplyAPI('FiberAPI')\n"
    )
    assert res.returncode == 0, res.stderr
    assert res.stdout.strip() == "10.0"


def test_stage_opened_before_import_fails_clearly():
    res = _py(
        "from pxr import Usd\n"
        "Usd.Stage.CreateInMemory().DefinePrim('/a', 'BasisCurves')\n"
        "import usdfiber\n"
    )
    assert res.returncode != 0
    assert "SchemaRegistrationError" in res.stderr
    assert "PXR_PLUGINPATH_NAME" in res.stderr


def test_plugin_path_lets_programs_open_stages_first():
    paths = subprocess.run([sys.executable, "-m", "usdfiber", "plugin-path"], capture_output=True,
                           text=True, cwd=ROOT, check=True).stdout.strip()
    assert all((Path(p) / "plugInfo.json").is_file() for p in paths.split(os.pathsep))
    res = _py(
        "from pxr import Usd\n"
        "s = Usd.Stage.CreateInMemory(); p = s.DefinePrim('/a', 'BasisCurves')\n"
        "assert p.ApplyAPI('FiberAPI') and p.GetAttribute('fiber:kind').Get() == 'polyester'\n"
        "import usdfiber\n",
        env={"PXR_PLUGINPATH_NAME": paths},
    )
    assert res.returncode == 0, res.stderr
