"""``usdfiber check``: output, exit status, file errors, JSON, and the 100k-curve runs."""
from __future__ import annotations

import json
import os
import subprocess
import sys
import time
from pathlib import Path

import pytest

import usdfiber  # noqa: F401  (registers the schemas before any stage exists)
from usdfiber.cli import main
from usdfiber.stage_io import StageOpenError, captured_stderr, open_stage
from usdfiber.validation.runner import check_stage

from large_stages import HEAD, curves_as_prims, curves_in_one_prim

REPO = Path(__file__).resolve().parents[2]
BAD = REPO / "tests" / "corpus" / "bad"


def fiber_prim(name: str, extra: str = "", width: float = 0.01) -> str:
    return f"""
def BasisCurves "{name}" (
    prepend apiSchemas = ["FiberAPI"]
)
{{
    uniform token basis = "bspline"
    int[] curveVertexCounts = [4]
    point3f[] points = [(0, 0, 0), (1, 1, 0), (2, 1, 0), (3, 0, 0)]
    float[] widths = [{width}] (
        interpolation = "constant"
    )
    {extra}
}}
"""


@pytest.fixture
def stages(tmp_path: Path) -> dict[str, Path]:
    """A clean stage, one with a warning only, one with errors."""
    files = {
        "clean": HEAD + fiber_prim("Fiber", 'uniform token fiber:kind = "polyester"'),
        "warn": HEAD + fiber_prim("Fiber", "float fiber:dye:depthOfShade = 2"),
        "bad": HEAD + fiber_prim("Fiber", "uniform float fiber:diameter = -5\n"
                                          "    float fiber:dye:depthOfShade = 2"),
        "sampled": HEAD + fiber_prim(
            "Fiber", 'token fiber:dye:class = "reactive"\n'
                     "    color3f fiber:dye:extinction = (0.001, 0.01, 0.01)\n"
                     "    float fiber:dye:depthOfShade.timeSamples = { 1: 1, 3: 12 }"),
    }
    out = {}
    for name, text in files.items():
        out[name] = tmp_path / f"{name}.usda"
        out[name].write_text(text)
    return out


def run(capfd, *args: str) -> tuple[int, str, str]:
    code = main(["check", *map(str, args)])
    out, err = capfd.readouterr()
    return code, out, err


# --------------------------------------------------------------------------------------
# Exit status and text
# --------------------------------------------------------------------------------------

def test_clean_stage_exits_0(capfd, stages):
    code, out, err = run(capfd, stages["clean"])
    assert code == 0 and err == ""
    assert out.splitlines() == [f"{stages['clean']}: 0 errors, 0 warnings",
                                "checked 1 stage: 0 errors, 0 warnings"]


def test_warnings_exit_0_unless_warnings_are_errors(capfd, stages):
    code, out, err = run(capfd, stages["warn"])
    assert code == 0 and err == ""
    assert "  warnings:" in out and "IgnoredValue" in out and "  errors:" not in out
    code, _, _ = run(capfd, "--warnings-as-errors", stages["warn"])
    assert code == 1


def test_errors_exit_1_grouped_errors_then_warnings(capfd, stages):
    code, out, err = run(capfd, stages["bad"], stages["clean"])
    assert code == 1 and err == ""
    lines = out.splitlines()
    assert lines[0] == f"{stages['bad']}: 1 error, 1 warning"
    assert lines[1] == "  errors:"
    assert lines[2].startswith("    /Fiber.fiber:diameter: ValueOutOfRange: fiber:diameter = -5 um;")
    assert lines[3] == "  warnings:"
    assert lines[4].startswith("    /Fiber.fiber:dye:depthOfShade: IgnoredValue:")
    assert lines[5] == f"{stages['clean']}: 0 errors, 0 warnings"
    assert lines[-1] == "checked 2 stages: 1 error, 1 warning"


def test_time_option(capfd, stages):
    code, out, _ = run(capfd, stages["sampled"])
    assert code == 1 and "/Fiber.fiber:dye:depthOfShade @ 3: ValueOutOfRange" in out
    assert run(capfd, "--time", "1", stages["sampled"])[0] == 0
    code, out, _ = run(capfd, "--time", "3", stages["sampled"])
    assert code == 1 and "@ 3: ValueOutOfRange" in out


@pytest.mark.parametrize("args", [["--time", "abc", "x.usda"], ["--time", "nan", "x.usda"],
                                  [], ["--bogus", "x.usda"]])
def test_usage_errors_exit_2(capfd, args):
    with pytest.raises(SystemExit) as exc:
        main(["check", *args])
    assert exc.value.code == 2
    out, err = capfd.readouterr()
    assert "Traceback" not in err
    assert err.strip().splitlines()[-1].startswith(("usdfiber check: error:", "usdfiber: error:"))


# --------------------------------------------------------------------------------------
# File errors: one line, exit 2, never a traceback, no USD noise
# --------------------------------------------------------------------------------------

FILE_ERRORS = [
    ("empty.usda", "EmptyFile", "empty file; expected a USD layer"),
    ("garbage_bytes.usdc", "NotUsd", "not a valid binary USD (usdc) file: "
                                     "Sdf crate bootstrap section corrupt"),
    ("not_usd.usda", "NotUsd", "not a text USD (usda) file: it does not start with "
                               "'#usda 1.0' (text)"),
    ("syntax_error.usda", "SyntaxError", "syntax error at line 14, column 9: Expected } at "
                                         "'uniform float fiber:diameter = ' in </World/Fibers>"),
]


@pytest.mark.parametrize("name,code,reason", FILE_ERRORS)
def test_unusable_file_is_one_line(capfd, name, code, reason):
    path = BAD / name
    with pytest.raises(StageOpenError) as exc:
        open_stage(path)
    assert exc.value.code == code and str(exc.value) == f"{path}: {reason}"
    status, out, err = run(capfd, path)
    assert status == 2
    assert err == f"usdfiber: error: {path}: {reason}\n"
    assert out == "checked 1 stage: 0 errors, 0 warnings, 1 could not be opened\n"


def test_missing_file_and_directory(capfd, tmp_path):
    missing, folder = tmp_path / "missing.usda", tmp_path / "folder.usda"
    folder.mkdir()
    status, _, err = run(capfd, missing, folder)
    assert status == 2
    assert err.splitlines() == [
        f"usdfiber: error: {missing}: no such file",
        f"usdfiber: error: {folder}: is a directory; expected a USD file "
        f"(.usd, .usda, .usdc, .usdz)"]


def test_unknown_extension(tmp_path):
    path = tmp_path / "notes.txt"
    path.write_text("#usda 1.0\n")
    with pytest.raises(StageOpenError) as exc:
        open_stage(path)
    assert exc.value.code == "UnknownFormat"


def test_unreadable_file(tmp_path, monkeypatch):
    path = tmp_path / "locked.usda"
    path.write_text(HEAD)
    if os.geteuid() != 0:  # root reads anything: then simulate the denial
        path.chmod(0)
    else:
        real_open = open

        def deny(file, *a, **k):
            if Path(file) == path:
                raise PermissionError(13, "Permission denied")
            return real_open(file, *a, **k)

        monkeypatch.setattr("builtins.open", deny)
    with pytest.raises(StageOpenError) as exc:
        open_stage(path)
    assert exc.value.code == "PermissionDenied"
    assert str(exc.value) == f"{path}: permission denied; cannot read the file"


def test_missing_sublayer_is_an_error_of_the_check_and_silent(capfd):
    status, out, err = run(capfd, BAD / "missing_sublayer.usda")
    assert status == 1 and err == ""  # USD's own warning is not shown
    assert "/: MissingSublayer: Could not load sublayer" in out


def test_command_line_process_never_shows_a_traceback(tmp_path):
    env = dict(os.environ, PYTHONPATH=str(REPO))
    for target in (tmp_path / "missing.usda", BAD / "garbage_bytes.usdc",
                   BAD / "syntax_error.usda", BAD / "missing_reference.usda"):
        proc = subprocess.run([sys.executable, "-m", "usdfiber", "check", str(target)],
                              capture_output=True, text=True, env=env, timeout=120)
        assert "Traceback" not in proc.stderr and "Warning:" not in proc.stderr
        assert len(proc.stderr.splitlines()) <= 1, proc.stderr
        assert proc.returncode in (1, 2)


def test_captured_stderr_catches_fd_writes():
    with captured_stderr() as lines:
        os.write(2, b"from C++\n")
    assert lines == ["from C++"]


# --------------------------------------------------------------------------------------
# JSON
# --------------------------------------------------------------------------------------

def test_json_document(capfd, stages, tmp_path):
    missing = tmp_path / "missing.usda"
    status, out, err = run(capfd, "--json", stages["sampled"], stages["clean"], missing)
    assert status == 2 and err == f"usdfiber: error: {missing}: no such file\n"
    doc = json.loads(out)
    assert doc["format"] == "usdfiber-check" and doc["version"] == 1
    assert doc["summary"] == {"stages": 3, "errors": 1, "warnings": 0, "unreadable": 1}
    sampled, clean, gone = doc["stages"]
    assert sampled["stage"] == str(stages["sampled"]) and sampled["error"] is None
    assert (sampled["errors"], sampled["warnings"]) == (1, 0)
    (p,) = sampled["problems"]
    assert set(p) == {"code", "severity", "layer", "prim", "attribute", "time", "message"}
    assert (p["code"], p["severity"], p["prim"], p["attribute"], p["time"]) == (
        "ValueOutOfRange", "error", "/Fiber", "fiber:dye:depthOfShade", 3.0)
    assert p["layer"] == str(stages["sampled"])
    assert clean["problems"] == [] and clean["error"] is None
    assert gone == {"stage": str(missing), "error": f"{missing}: no such file",
                    "error_code": "FileNotFound", "errors": 0, "warnings": 0, "problems": []}


def test_report_api(stages):
    report = check_stage(stages["bad"])
    assert [p.code for p in report.errors] == ["ValueOutOfRange"]
    assert [p.code for p in report.warnings] == ["IgnoredValue"]
    assert not report.ok()
    doc = json.loads(report.to_json())
    assert [s["stage"] for s in doc["stages"]] == [str(stages["bad"])]
    assert report.to_text().splitlines()[0] == f"{stages['bad']}: 1 error, 1 warning"


def test_examples_check_clean(capfd):
    examples = sorted((REPO / "examples").glob("*.usda"))
    if not examples:
        pytest.skip("no examples/*.usda yet")
    status, out, err = run(capfd, *examples)
    assert status == 0, out
    assert err == ""


# --------------------------------------------------------------------------------------
# 100k curves: as 100k prims and as one prim (correctness runs; timings are printed)
# --------------------------------------------------------------------------------------

@pytest.mark.slow  # about a minute on 2 cores; timings: bench/check_bench.py
def test_100k_fiber_prims(tmp_path, capsys):
    path = tmp_path / "many.usda"
    curves_as_prims(path, 100_000, bad_every=1000)
    t0 = time.perf_counter()
    report = check_stage(path)
    elapsed = time.perf_counter() - t0
    assert {(p.code, p.attribute) for p in report.problems} == {
        ("ValueOutOfRange", "fiber:dye:depthOfShade")}
    assert len(report.errors) == 100
    assert report.warnings == []
    with capsys.disabled():
        print(f"\n[timing] check_stage, 100k BasisCurves prims with FiberAPI: {elapsed:.1f} s")


def test_100k_curves_in_one_prim(tmp_path, capsys):
    path = tmp_path / "one.usdc"
    curves_in_one_prim(path, 100_000)
    t0 = time.perf_counter()
    report = check_stage(path)
    elapsed = time.perf_counter() - t0
    assert report.problems == [], report.to_text()
    with capsys.disabled():
        print(f"\n[timing] check_stage, 100k curves in one BasisCurves prim: {elapsed:.1f} s")
