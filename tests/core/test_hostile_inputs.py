"""A hostile corpus, made at test time: stages, table files, curve files and command lines that
are wrong in every way we could think of. Each gets its specific one-line error (or its
documented warning) from the command that reads it, never a traceback.

Cases run in this process through ``usdfiber.cli.main`` (an exception escaping it, the
traceback, fails the case). Cache states are in tests/bake/test_hostile_cache.py.
"""
from __future__ import annotations

import json
import math
import re
import struct
import zipfile
from dataclasses import dataclass
from pathlib import Path
from typing import Callable

import numpy as np
import pytest

import usdfiber  # noqa: F401 - registers the schemas
from usdfiber.cli import main
from usdfiber.spec.attributes import attributes

CORPUS = Path(__file__).resolve().parents[1] / "corpus"


@dataclass(frozen=True)
class Case:
    """``argv(tmp)`` writes the input under ``tmp`` and gives the command line; the command
    must exit ``rc`` and its stderr (stdout when ``stream`` says so) match ``expect``."""

    id: str
    argv: Callable[[Path], list[str]]
    rc: int
    expect: str
    stream: str = "err"


def run_case(case: Case, tmp: Path, capsys) -> None:
    argv = case.argv(tmp)
    try:
        rc = main(argv)
    except SystemExit as exc:   # argparse's own errors
        rc = exc.code
    out, err = capsys.readouterr()
    assert "Traceback" not in out + err
    text = err if case.stream == "err" else out
    assert rc == case.rc, f"{case.id}: exit {rc}, stderr: {err[-2000:]}"
    assert re.search(case.expect, text), f"{case.id}: expected {case.expect!r} in: {text[-2000:]}"
    if rc == 2:
        # One line: the error is the last line (argparse may print its usage above it).
        last = err.strip().splitlines()[-1]
        assert re.search(case.expect, last) and "error:" in last


# ---- stages --------------------------------------------------------------------------------------

STAGE = '''#usda 1.0
(
    metersPerUnit = 0.001
    upAxis = "Y"
)
def BasisCurves "Fibers" (
    prepend apiSchemas = [{apis}]
)
{{
    uniform token basis = "bspline"
    int[] curveVertexCounts = [4]
    point3f[] points = [(0, 0, 0), (1, 1, 0), (2, 1, 0), (3, 0, 0)]
    float[] widths = [{width}] (interpolation = "constant")
    {extra}
}}
{more}
'''


def _stage(extra: str, *, yarn: bool = False, more: str = "") -> Callable[[Path], list[str]]:
    def argv(tmp: Path) -> list[str]:
        apis = '"FiberAPI", "FiberYarnAPI"' if yarn else '"FiberAPI"'
        (tmp / "s.usda").write_text(STAGE.format(apis=apis, width="0.25" if yarn else "0.01", extra=extra, more=more))
        return ["bake", str(tmp / "s.usda"), "--dry-run", "--cache-dir", str(tmp / "cache")]
    return argv


_CODES = "(ValueOutOfRange|NonFiniteValue|WrongValueType|InvertedRange)"


def _attribute_cases(api: str) -> list[Case]:
    """Each attribute of ``api`` below and above its valid range, NaN, and of the wrong type."""
    cases = []
    yarn = api == "FiberYarnAPI"
    for name, spec in attributes(api).items():
        t, u = spec.type_name, "uniform " if spec.uniform else ""
        if spec.is_relationship or not t:
            continue
        values = []
        if t in ("float", "int") and spec.valid is not None:
            lo, hi = spec.valid.lo, spec.valid.hi
            if lo > -math.inf:
                values.append(("below", f"{u}{t} {name} = {lo - 1 if t == 'int' else lo - 1.0}"))
            # A molar mass is only used with extinctionSource "molar" (a value beyond the range
            # is reported there: tests/corpus/bad/molar_mass_zero.usda).
            if hi < math.inf and name != "fiber:dye:molarMass":
                values.append(("above", f"{u}{t} {name} = {int(hi) + 1 if t == 'int' else hi * 2 + 1}"))
        if t == "float":
            values.append(("nan", f"{u}float {name} = nan"))
        values.append(("string", f'{u}string {name} = "x"'))
        for label, line in values:
            cases.append(Case(f"stage-{name}-{label}", _stage(line, yarn=yarn), 1,
                              rf"{re.escape(name.split(':')[0])}.*: {_CODES}: .*{re.escape(name)}"
                              if label != "string" else rf"{re.escape(name)}: WrongValueType"))
    return cases


PROFILE = '''def Scope "Profile" (
    prepend apiSchemas = ["FiberProfileAPI"]
)
{{
    uniform {type} fiberProfile:points = {points}
    uniform int[] fiberProfile:loopVertexCounts = [{n}]
}}
'''
_USER = '''uniform token fiber:profile = "user"
    rel fiber:profile:sources = </Profile>'''

STAGE_CASES = _attribute_cases("FiberAPI") + _attribute_cases("FiberYarnAPI") + [
    Case("stage-variant-count-int-max", _stage("uniform int fiber:profile:variantCount = 2147483647"), 1,
         r"variantCount = 2147483647; expected a variant count in \[1, 64\]"),
    Case("stage-variant-count-4.5", _stage("uniform float fiber:profile:variantCount = 4.5"), 1,
         r"variantCount is authored as float; expected int"),
    Case("stage-ior-1e30", _stage("float fiber:ior:parallel = 1e30"), 1,
         r"fiber:ior:parallel = 1e\+30; expected a refractive index in \[1, 3\]"),
    Case("stage-ior-inf", _stage("float fiber:ior:perpendicular = inf"), 1, r"fiber:ior:perpendicular: NonFiniteValue"),
    Case("stage-profile-float3", _stage(_USER, more=PROFILE.format(
        type="float3[]", points="[(0, 0, 0), (10, 0, 0), (10, 10, 0), (0, 10, 0)]", n=4)), 1,
        r"fiberProfile:points: WrongValueType: fiberProfile:points is authored as float3\[\]; expected float2\[\]"),
    Case("stage-profile-bowtie", _stage(_USER, more=PROFILE.format(
        type="float2[]", points="[(0, 0), (10, 10), (10, 0), (0, 6)]", n=4)), 1, r"ProfileSelfIntersecting"),
    Case("stage-profile-two-points", _stage(_USER, more=PROFILE.format(type="float2[]", points="[(0, 0), (1, 1)]",
                                                                        n=2)), 1, r"ProfileTooFewPoints"),
    Case("stage-profile-nan", _stage(_USER, more=PROFILE.format(
        type="float2[]", points="[(0, 0), (nan, 0), (10, 10)]", n=3)), 1,
        r"fiberProfile:points: ProfilePointsNotFinite: 1 points contain NaN or Inf \(first: point 1\)"),
    Case("stage-profile-counts-int-max", _stage(_USER, more=PROFILE.format(
        type="float2[]", points="[(0, 0), (10, 0), (10, 10)]", n=2147483647)), 1, r"ProfileCountsMismatch"),
    Case("stage-points-inf", lambda tmp: _write_and_bake(
        tmp, STAGE.format(apis='"FiberAPI"', width="0.01", extra="", more="").replace("(3, 0, 0)", "(inf, 0, 0)")),
        1, r"PointsNotFinite"),
]


def _write_and_bake(tmp: Path, text: str) -> list[str]:
    (tmp / "s.usda").write_text(text)
    return ["bake", str(tmp / "s.usda"), "--dry-run", "--cache-dir", str(tmp / "cache")]


def _corpus_cases() -> list[Case]:
    """Every file of tests/corpus/bad through ``bake --dry-run``: unusable files exit 2, files
    with check errors are refused with check's first error (exit 1), the rest list their
    tables (exit 0; a missing or damaged table asset is what a bake makes)."""
    expected = json.loads((CORPUS / "expected.json").read_text())
    cases = []
    for name, problems in sorted(expected.items()):
        errors = [p for p in problems if p["severity"] == "error"]
        path = str(CORPUS / "bad" / name)

        def argv(tmp: Path, path: str = path) -> list[str]:
            # One cache for the corpus (pytest's temporary root): a dry run writes no
            # table, only the cost probe of each fiber, which the next stage then reuses.
            return ["bake", path, "--dry-run", "--cache-dir", str(tmp.parent / "corpus-cache")]

        unusable = [p for p in errors if p["code"] in ("EmptyFile", "NotUsd", "SyntaxError")]
        blocking = [p for p in errors if p["code"] not in ("TableMissing", "TableUnreadable")]
        if unusable:
            cases.append(Case(f"corpus-{name}", argv, 2, re.escape(Path(name).name)))
        elif blocking:
            cases.append(Case(f"corpus-{name}", argv, 1, rf"not baking:(.|\n)*{re.escape(blocking[0]['message'])}"))
        else:
            cases.append(Case(f"corpus-{name}", argv, 0, r"\d+ tables?(, \d+ to bake: .* on disk)?$|^$", stream="out"))
    return cases


# ---- table files ---------------------------------------------------------------------------------

def _file(name: str, data: bytes | None = None, make: Callable[[Path], None] | None = None,
          command: tuple[str, ...] = ("table", "inspect")) -> Callable[[Path], list[str]]:
    def argv(tmp: Path) -> list[str]:
        p = tmp / name
        if make is not None:
            make(p)
        elif data is not None:
            p.write_bytes(data)
        return [*command, str(p)]
    return argv


def _zip(entries: dict[str, bytes]) -> Callable[[Path], None]:
    def make(p: Path) -> None:
        with zipfile.ZipFile(p, "w") as z:
            for k, v in entries.items():
                z.writestr(k, v)
    return make


TABLE_CASES = [
    Case("table-empty", _file("t.npz", b""), 2, r"t.npz: truncated or corrupt: empty file"),
    Case("table-garbage", _file("t.npz", b"\x00\x01garbage" * 10), 2, r"t.npz: not a usdfiber table \(not an .npz"),
    Case("table-zip-without-header", _file("t.npz", make=_zip({"p.npy": b"xx"})), 2, r"not a usdfiber table \(no header"),
    Case("table-header-not-json", _file("t.npz", make=_zip({"header.json": b"{not json"})), 2,
         r"t.npz: not a usdfiber table \(no header entry\)"),
    Case("table-plain-npz", _file("t.npz", make=lambda p: np.savez(p, a=np.zeros(3))), 2, r"not a usdfiber table"),
    Case("table-directory", _file("t.npz", make=lambda p: p.mkdir()), 2, r"t.npz: not a usdfiber table \(not a regular"),
    Case("table-missing", _file("t.npz"), 2, r"t.npz: missing"),
    Case("table-png-bytes", _file("t.npz", b"\x89PNG\r\n\x1a\n" + b"\0" * 100), 2, r"not a usdfiber table"),
    Case("table-truncated-zip", _file("t.npz", make=lambda p: (_zip({"header.json": b"{}" * 500})(p),
                                                               p.write_bytes(p.read_bytes()[:60]))), 2,
         r"t.npz: truncated or corrupt: File is not a zip file"),
    Case("table-plot-without-output", _file("t.npz", b"garbage", command=("table", "plot")), 2,
         r"required: -o/--output"),
    Case("table-plot-garbage", lambda tmp: (tmp.joinpath("t.npz").write_bytes(b"garbage"),
                                            ["table", "plot", str(tmp / "t.npz"), "--theta-i", "0", "--phi-i", "0",
                                             "-o", str(tmp / "p.png")])[1], 2, r"t.npz: not a usdfiber table"),
]


def _crafted(change: Callable[[dict], None], *, compressed: bool = False) -> Callable[[Path], list[str]]:
    """A small table of the real layout with valid checksums, its arrays changed by ``change``
    after any compression (a hand-edited file: the container cannot tell)."""
    from usdfiber.bake.compression import compress_table
    from usdfiber.bake.grid import Grid
    from usdfiber.bake.storage import LAYOUT, LAYOUT_VERSION, write_table_file
    from usdfiber.bake.table import BcsdfTable

    def argv(tmp: Path) -> list[str]:
        g = Grid(30.0, True, False)
        lv = np.array([0.0, 1.0, 4.0])
        dirs, B = (g.n_theta_i, g.n_phi_i), g.n_theta_o - 2
        shape = (*dirs, len(lv), B, g.n_phi_o)
        p = np.random.default_rng(0).random(shape).astype(np.float16)
        arrays = {"p": p, "p_scale": np.ones((*dirs, len(lv)), np.float32), "lbar": np.ones(shape, np.float16),
                  "band_start": np.ones(dirs, np.int16), "albedo": np.full((*dirs, len(lv)), 0.5, np.float32),
                  "albedo_lbar": np.ones((*dirs, len(lv)), np.float32), "levels": lv,
                  "width": np.ones(720, np.float32), "rel_error": np.zeros(dirs, np.float32),
                  "photons": np.ones(dirs, np.int64)}
        header = {"layout": {"name": LAYOUT, "version": LAYOUT_VERSION}, "resolution": g.to_header(),
                  "baked_diameter_um": 1.0, "geometry_key": "", "inputs": {}, "photons": 1, "error_estimate": 0}
        if compressed:
            header, arrays = compress_table(BcsdfTable(header=header, arrays=arrays), 0.5)
        change(arrays)
        write_table_file(tmp / "t.npz", header, arrays)
        return ["table", "inspect", str(tmp / "t.npz")]
    return argv


def _set(name: str, value) -> Callable[[dict], None]:
    def change(arrays: dict) -> None:
        a = arrays[name].copy()
        a.flat[0] = value
        arrays[name] = a
    return change


#: Tables whose checksums hold and whose shapes fit but whose values cannot be used.
TABLE_CASES += [
    Case("table-crafted-p-nan", _crafted(_set("p", np.nan)), 2, r"t.npz: not a usable table: array p holds NaN"),
    Case("table-crafted-p-negative", _crafted(_set("p", -1.0)), 2, r"t.npz: not a usable table: array p holds neg"),
    Case("table-crafted-p-scale-inf", _crafted(_set("p_scale", np.inf)), 2, r"array p_scale holds NaN or infinite"),
    Case("table-crafted-lbar-negative", _crafted(_set("lbar", -2.0)), 2, r"array lbar holds negative values"),
    Case("table-crafted-width-nan", _crafted(_set("width", np.nan)), 2, r"array width holds NaN or infinite"),
    Case("table-crafted-photons-negative", _crafted(_set("photons", -5)), 2, r"array photons holds negative"),
    Case("table-crafted-p-integers", _crafted(lambda a: a.update(p=a["p"].astype(np.int32))), 2,
         r"not a usable table: array p has dtype int32, expected floats"),
    Case("table-crafted-p-text", _crafted(lambda a: a.update(p=a["p"].astype("U3"))), 2,
         r"not a usable table: array p has dtype <U3, expected floats"),
    Case("table-crafted-band-start-floats", _crafted(lambda a: a.update(band_start=a["band_start"] + 0.5)), 2,
         r"array band_start has dtype float64, expected integers"),
    Case("table-crafted-width-empty", _crafted(lambda a: a.update(width=np.zeros(0, np.float32))), 2,
         r"array width has shape \(0,\), expected \(n,\) with n >= 1"),
    Case("table-crafted-compressed-coef-nan", _crafted(_set("coef", np.nan), compressed=True), 2,
         r"not a usable table: array coef holds NaN or infinite values"),
]


# ---- curve files ---------------------------------------------------------------------------------

def _bcc(n_curves_header: int = 1, curves: list[tuple[int, list]] | None = None, magic: bytes = b"BCC",
         size: int = 0x44, kind: bytes = b"PL", dims: int = 3) -> bytes:
    curves = [(3, [(0, 0, 0), (1, 0, 0), (2, 1, 0)])] if curves is None else curves
    n_points = sum(abs(n) for n, _ in curves)
    head = magic + bytes([size]) + kind + bytes([dims, 1]) + struct.pack("<QQ", n_curves_header, n_points) + b"\0" * 40
    body = b"".join(struct.pack("<i", n) + np.asarray(p, "<f4").tobytes() for n, p in curves)
    return head + body


def _hair(strands: int = 1, points: int = 3, flags: int = 2 | 4, dsegs: int = 2, thickness: float = 1.0,
          pts: list | None = None, thick: list | None = None) -> bytes:
    head = b"HAIR" + struct.pack("<IIII", strands, points, flags, dsegs) + struct.pack("<fff", thickness, 1.0, 0.0)
    head += b"\0" * (128 - len(head))
    pts = [(0, 0, 0), (1, 0, 0), (2, 1, 0)] if pts is None else pts
    thick = [0.1] * len(pts) if thick is None else thick
    body = np.asarray(pts, "<f4").tobytes()
    if flags & 4:
        body += np.asarray(thick, "<f4").tobytes()
    return head + body


def _import(name: str, data: bytes, *extra: str) -> Callable[[Path], list[str]]:
    def argv(tmp: Path) -> list[str]:
        (tmp / name).write_bytes(data)
        return ["import", str(tmp / name), "-o", str(tmp / "out.usda"), *extra]
    return argv


CURVE_CASES = [
    Case("curves-empty", _import("c.bcc", b""), 2, r"c.bcc: empty file; expected a BCC or HAIR curve file"),
    Case("curves-not-curves", _import("c.bcc", b"hello world" * 10), 2, r"c.bcc: not a BCC or HAIR file"),
    Case("bcc-truncated-header", _import("c.bcc", b"BCC\x44C0\x03\x01"), 2, r"truncated header: the file has 8 bytes"),
    Case("bcc-8-byte-values", _import("c.bcc", _bcc(size=0x88)), 2, r"c.bcc: byte count 0x88 is not supported"),
    Case("bcc-unknown-type", _import("c.bcc", _bcc(kind=b"XX")), 2, r"c.bcc: curve type b'XX' is not supported"),
    Case("bcc-2d", _import("c.bcc", _bcc(dims=2)), 2, r"curves have 2 dimensions; only 3D curves are supported"),
    Case("bcc-zero-curves", _import("c.bcc", _bcc(n_curves_header=0)), 2, r"header says 0 curves; nothing to import"),
    Case("bcc-more-curves-than-data", _import("c.bcc", _bcc(n_curves_header=1000)), 2,
         r"c.bcc: header says 1000 curves but the file ends after 1"),
    Case("bcc-curve-count-int-max", _import("c.bcc", _bcc(n_curves_header=2 ** 63)), 2,
         r"c.bcc: header says 9223372036854775808 curves but the file ends after 1"),
    Case("bcc-point-count-beyond-file", _import("c.bcc", _bcc(curves=[(100000, [(0, 0, 0)] * 3)])), 2,
         r"c.bcc: the file ends inside curve 0: it has 100000 control points but the file holds only 3 more"),
    Case("bcc-nan-point", _import("c.bcc", _bcc(curves=[(3, [(0, 0, 0), (np.nan, 0, 0), (2, 1, 0)])])), 2,
         r"curve 0 point 1 has a non-finite coordinate"),
    Case("bcc-inf-point", _import("c.bcc", _bcc(curves=[(3, [(0, 0, 0), (np.inf, 0, 0), (2, 1, 0)])])), 2,
         r"non-finite coordinate"),
    Case("bcc-one-point-polyline", _import("c.bcc", _bcc(curves=[(1, [(0, 0, 0)])])), 2,
         r"curve 0 has 1 control point \(count 1\); an open polyline curve needs at least 2"),
    Case("bcc-catmull-rom-3-points", _import("c.bcc", _bcc(kind=b"C0")), 2,
         r"an open uniform Catmull-Rom curve needs at least 4"),
    Case("bcc-overflowing-scale", _import("c.bcc", _bcc(curves=[(3, [(0, 0, 0), (3e10, 0, 0), (2, 1, 0)])]),
                                          "--units-per-file-unit", "1e10"), 2,
         r"c.bcc: points: coordinate 1 becomes 3e\+20 after scaling; expected magnitudes below 1e\+18 .*; change "
         r"--units-per-file-unit"),
    Case("bcc-overflowing-width", _import("c.bcc", _bcc(), "--width", "1e30"), 2,
         r"widths: width 0 becomes 1e\+30 after scaling; expected magnitudes below 1e\+18.*; change --width"),
    Case("bcc-unknown-preset", _import("c.bcc", _bcc(), "--preset", "kevlar"), 2,
         r"/c/Curves: unknown fiber preset 'kevlar'; valid: polyester"),
    Case("bcc-unknown-yarn", _import("c.bcc", _bcc(), "--yarn", "CNe 9999"), 2,
         r"/c/Curves: unknown yarn preset 'CNe 9999'; valid: Skala 360"),
    Case("bcc-bad-root", _import("c.bcc", _bcc(), "--root", "1 bad name"), 2, r"--root must be a valid prim name"),
    Case("bcc-over-budget", _import("c.bcc", _bcc(), "--memory-budget", "100"), 2,
         r"c.bcc: importing a curve file of \d+ bytes .* needs about .*--memory-budget"),
    Case("bcc-zero-length-curve", _import("c.bcc", _bcc(n_curves_header=2, curves=[
        (3, [(0, 0, 0), (1, 0, 0), (2, 1, 0)]), (2, [(5, 5, 5)] * 2)])), 0,
         r"note: curve 1 has all points equal \(zero length; 1 such curve\): it cannot be shaded"),
    Case("hair-zero-length-strand", _import("h.hair", _hair(pts=[(1, 1, 1)] * 3)), 0,
         r"note: curve 0 has all points equal \(zero length; 1 such curve\)"),
    Case("hair-truncated-header", _import("h.hair", b"HAIR" + b"\0" * 20), 2, r"truncated header: the file has 24 bytes"),
    Case("hair-zero-strands", _import("h.hair", _hair(strands=0)), 2, r"header says 0 strands; nothing to import"),
    Case("hair-no-points-flag", _import("h.hair", _hair(flags=4)), 2, r"say the file has no points array"),
    Case("hair-negative-count", _import("h.hair", _hair(points=2 ** 32 - 5)), 2, r"is negative as a signed 32-bit"),
    Case("hair-ends-early", _import("h.hair", _hair(strands=1, points=30, dsegs=29)), 2, r"the file ends inside the"),
    Case("hair-count-mismatch", _import("h.hair", _hair(strands=2, points=3, dsegs=2)), 2,
         r"header says 3 points but 2 strands of 2 default segments have 6 points"),
    Case("hair-zero-segments", _import("h.hair", _hair(dsegs=0, points=1, pts=[(0, 0, 0)])), 2,
         r"default segment count of 0"),
    Case("hair-negative-thickness", _import("h.hair", _hair(thick=[0.1, -1.0, 0.1])), 2,
         r"thickness of point 1 is -1; thickness must"),
    Case("hair-nan-point", _import("h.hair", _hair(pts=[(0, 0, 0), (0, np.nan, 0), (1, 1, 1)])), 2,
         r"non-finite coordinate"),
    Case("hair-thickness-overflow", _import("h.hair", _hair(thick=[1e30] * 3), "--units-per-file-unit", "1e9"), 2,
         r"widths: width 0 becomes 1e\+39 after scaling"),
    # Finite values a renderer cannot use: beyond 1e18 (float32 squares overflow; above) or below
    # float32's normal range (written as 0: the nominal width of a stage of absurd units drew nothing).
    Case("bcc-scale-underflow", _import("c.bcc", _bcc(), "--units-per-file-unit", "1e-300"), 2,
         r"points: coordinate 1 becomes 1e-300 after scaling; expected magnitudes of at least 1.18e-38"),
    Case("bcc-meters-per-unit-huge", _import("c.bcc", _bcc(), "--meters-per-unit", "1e300"), 2,
         r"widths: width 0 becomes 1e-305 after scaling; .* change --meters-per-unit"),
    Case("curves-directory", lambda tmp: (tmp.joinpath("d.bcc").mkdir(), ["import", str(tmp / "d.bcc"), "-o",
                                                                          str(tmp / "o.usda")])[1], 2,
         r"d.bcc: is a directory, not a curve file"),
    Case("curves-output-not-usd", _import("c.bcc", _bcc(), "-o", "x.txt"), 2, r"x.txt: the output must be a .usd"),
]


# ---- command lines ---------------------------------------------------------------------------------

def _args(*words: str) -> Callable[[Path], list[str]]:
    def argv(tmp: Path) -> list[str]:
        (tmp / "s.usda").write_text("#usda 1.0\n")
        return [w.replace("{tmp}", str(tmp)) for w in words]
    return argv


_RANGE = r"must be an integer from 0 to 4294967295"
CLI_CASES = [
    Case("cli-unknown-command", _args("nosuch"), 2, r"invalid choice: 'nosuch'"),
    Case("cli-bake-seed-negative", _args("bake", "--preset", "silk", "--seed", "-1"), 2, rf"--seed: {_RANGE}, got -1"),
    Case("cli-bake-seed-2^32", _args("bake", "--preset", "silk", "--seed", str(2 ** 32)), 2, rf"--seed: {_RANGE}"),
    Case("cli-bake-seed-text", _args("bake", "--preset", "silk", "--seed", "x"), 2, r"--seed: not an integer: 'x'"),
    Case("cli-render-seed-negative", _args("render", "{tmp}/s.usda", "--seed", "-1"), 2, rf"--seed: {_RANGE}"),
    Case("cli-render-lod-scale-negative", _args("render", "{tmp}/s.usda", "--lod-scale", "-1"), 2,
         r"--lod-scale: must be a number >= 0, got '-1'"),
    Case("cli-render-lod-scale-nan", _args("render", "{tmp}/s.usda", "--lod-scale", "nan"), 2,
         r"--lod-scale: not a finite number"),
    Case("cli-render-resolution-zero", _args("render", "{tmp}/s.usda", "--resolution", "0x0"), 2,
         r"--resolution: expected a positive size of at most 268435456 pixels"),
    Case("cli-render-resolution-huge", _args("render", "{tmp}/s.usda", "--resolution", "100000x100000"), 2,
         r"--resolution: expected a positive size of at most 268435456 pixels"),
    Case("cli-render-resolution-text", _args("render", "{tmp}/s.usda", "--resolution", "big"), 2,
         r"--resolution: expected WIDTHxHEIGHT"),
    Case("cli-render-spp-zero", _args("render", "{tmp}/s.usda", "--spp", "0"), 2, r"--spp: must be >= 1, got 0"),
    Case("cli-render-frame-nan", _args("render", "{tmp}/s.usda", "--frame", "nan"), 2, r"--frame: not a finite"),
    Case("cli-render-max-depth-huge", _args("render", "{tmp}/s.usda", "--max-depth", "100000000"), 2,
         r"--max-depth: expected a path depth of at most 65536"),
    Case("cli-render-scheduler-empty", _args("render", "{tmp}/s.usda", "--frames", "1:2", "--scheduler", ""), 2,
         r"bad --scheduler ''"),
    Case("cli-render-spp-huge", _args("render", "{tmp}/s.usda", "--spp", "100000000000"), 2,
         r"--spp: expected at most 1048576 samples per pixel"),
    Case("cli-render-exposure-huge", _args("render", "{tmp}/s.usda", "--exposure", "1e30"), 2,
         r"--exposure: expected an exposure within \+-100 stops"),
    Case("cli-render-bake-resolution-zero", _args("render", "{tmp}/s.usda", "--bake-resolution", "0"), 2,
         r"--bake-resolution: must be a positive number, got .0."),
    Case("cli-render-png-not-png", _args("render", "{tmp}/s.usda", "-o", "{tmp}/x.exr", "--png", "{tmp}/x.exr"), 2,
         r"--png must name a .png file"),
    Case("cli-render-output-not-exr", _args("render", "{tmp}/s.usda", "-o", "{tmp}/x.png"), 2,
         r"--output must name an .exr file"),
    Case("cli-render-no-stage", _args("render"), 2, r"render: a STAGE is required"),
    Case("cli-render-missing-stage", _args("render", "{tmp}/missing.usda"), 2, r"missing.usda"),
    Case("cli-render-memory-budget-bad", _args("render", "{tmp}/s.usda", "--memory-budget", "lots"), 2,
         r"--memory-budget: not a memory size: 'lots'"),
    Case("cli-render-memory-budget-zero", _args("render", "{tmp}/s.usda", "--memory-budget", "0"), 2,
         r"--memory-budget: a memory size must be at least 1 byte"),
    Case("cli-bake-nothing", _args("bake"), 2, r"nothing to bake: give STAGE files"),
    Case("cli-bake-resolution-7", _args("bake", "--preset", "silk", "--resolution", "7", "--dry-run"), 2,
         r"--resolution 7 deg must divide 90 deg"),
    Case("cli-bake-resolution-negative", _args("bake", "--preset", "silk", "--resolution", "-2"), 2,
         r"--resolution: must be a positive number"),
    Case("cli-bake-photons-zero", _args("bake", "--preset", "silk", "--photons", "0"), 2, r"--photons: must be >= 1"),
    Case("cli-bake-batches-one", _args("bake", "--preset", "silk", "--batches", "1", "--dry-run"), 2,
         r"batches must be from 2 \(the error estimate needs a variance\) to 4096"),
    Case("cli-bake-photons-huge", _args("bake", "--preset", "polyester", "--photons", "99999999999999999999",
                                        "--dry-run"), 2, r"photons must be from 1 to 1e\+12 per direction"),
    Case("cli-bake-max-bounces-2^32", _args("bake", "--preset", "polyester", "--max-bounces", str(2 ** 32),
                                            "--dry-run"), 2, r"max_bounces must be from 1 to 1048576"),
    Case("cli-bake-target-error-tiny", _args("bake", "--preset", "polyester", "--target-error", "1e-300",
                                             "--dry-run"), 2, r"target error must be in \[1e-4, 1\)"),
    Case("cli-bake-resolution-tiny", _args("bake", "--preset", "polyester", "--resolution", "1e-300",
                                           "--dry-run"), 2, r"resolution must be at least 0.1 deg"),
    Case("cli-cloth-spacing-huge", _args("cloth", "plain", "-o", "{tmp}/c.usda", "--spacing", "1e308"), 2,
         r"spacing must be a positive number up to 1e\+06"),
    Case("cli-cloth-satin-floats-huge", _args("cloth", "satin", "-o", "{tmp}/c.usda", "--floats", "1000000"), 2,
         r"floats must be an integer >= 1 and <= 64"),
    Case("cli-bake-target-error-two", _args("bake", "--preset", "silk", "--target-error", "2", "--dry-run"), 2,
         r"--target-error must be below 1, got 2"),
    Case("cli-bake-unknown-preset", _args("bake", "--preset", "nope", "--dry-run"), 2,
         r"unknown fiber preset 'nope'; valid: polyester"),
    Case("cli-bake-params-missing", _args("bake", "--params", "{tmp}/p.json", "--dry-run"), 2, r"p.json: no such file"),
    Case("cli-bake-memory-budget-bad", _args("bake", "--preset", "silk", "--memory-budget=-3G"), 2,
         r"--memory-budget: not a memory size"),
    Case("cli-bake-jobs-zero", _args("bake", "--preset", "silk", "--jobs", "0"), 2, r"--jobs: must be >= 1"),
    Case("cli-cloth-rows-zero", _args("cloth", "stockinette", "--rows", "0", "-o", "{tmp}/c.usda"), 2,
         r"--rows: must be >= 1, got 0"),
    Case("cli-cloth-million-squared", _args("cloth", "stockinette", "--rows", "1000000", "--loops", "1000000", "-o",
                                            "{tmp}/c.usda"), 2, r"16000003000000 control points, written as usda\) needs about"),
    Case("cli-cloth-weave-with-rows", _args("cloth", "plain", "--rows", "3", "-o", "{tmp}/c.usda"), 2,
         r"--rows does not apply to weaves"),
    Case("cli-cloth-output-not-usd", _args("cloth", "plain", "-o", "{tmp}/c.txt"), 2,
         r"--output must be a .usd, .usda or .usdc file"),
    Case("cli-cloth-unknown-yarn", _args("cloth", "plain", "--yarn", "CNe 9999", "-o", "{tmp}/c.usda"), 2,
         r"cloth plain: unknown yarn preset 'CNe 9999'"),
    Case("cli-cloth-over-budget", _args("cloth", "satin", "--memory-budget", "1K", "-o", "{tmp}/c.usda"), 2,
         r"cloth satin of 20 warps x 20 wefts .* more than the memory budget of 1 KiB \(--memory-budget\)"),
    Case("cli-import-no-output", _args("import", "{tmp}/x.bcc"), 2, r"required: -o/--output"),
    Case("cli-import-width-negative", _args("import", "{tmp}/x.bcc", "-o", "{tmp}/o.usda", "--width", "-1"), 2,
         r"--width: must be a positive number"),
    Case("cli-import-scale-inf", _args("import", "{tmp}/x.bcc", "-o", "{tmp}/o.usda", "--units-per-file-unit", "inf"),
         2, r"--units-per-file-unit: not a finite number"),
    Case("cli-dye-light-huge", _args("dye", "--match", "0.1,0.1,0.1", "--fiber", "silk", "--no-bake", "--light",
                                     "1e308,1e308,1e308"), 2,
         r"light '1e308,1e308,1e308': every channel must be from 1e-06 to 1e\+06 \(got R 1e\+308, G 1e\+308"),
    Case("cli-dye-light-subnormal", _args("dye", "--match", "0.1,0.1,0.1", "--fiber", "silk", "--no-bake", "--light",
                                          "1e-320,1,1"), 2,
         r"every channel must be from 1e-06 to 1e\+06 \(got R 9.99989e-321; a channel without light"),
    Case("cli-dye-light-1500K", _args("dye", "--match", "0.1,0.1,0.1", "--fiber", "silk", "--no-bake", "--light",
                                      "1500K"), 2, r"'1500K': every channel must be from 1e-06 to 1e\+06 \(got B 0;"),
    Case("cli-bake-compress-bound-tiny", _args("bake", "--preset", "silk", "--dry-run", "--compress", "1e-300"), 2,
         r"--compress: must be in \[0.0001, 1\) \(relative L2 error of p"),
    Case("cli-check-nothing", _args("check"), 2, r"required: STAGE"),
    Case("cli-table-inspect-nothing", _args("table", "inspect"), 2, r"required: FILE"),
]

#: A dry run refuses the farm options a bake would refuse (it used to list the tables, exit 0).
DRY_RUN_FARM = {
    "shard-out-of-range": (["--shard", "5/2"], r"--shard: shard 5/2: I must be between 1 and N=2"),
    "shard-empty": (["--shard", ""], r"--shard: bad shard '': expected I/N"),
    "scheduler-bad": (["--scheduler", "bogus::x"], r"bad --scheduler 'bogus::x': an IPv6 address needs brackets"),
    "scheduler-empty": (["--scheduler", ""], r"bad --scheduler '': expected an address such as tcp://host:8786"),
    "scheduler-local-zero": (["--scheduler", "local:0"], r"local:N needs 1 <= N <= 256"),
    "shard-and-scheduler": (["--shard", "1/2", "--scheduler", "local:1"], r"exclude each other"),
    "shard-plot": (["--shard", "1/2", "--plot"], r"--plot writes figures next to tables baked here; not with"),
}
CLI_CASES += [Case(f"cli-bake-dry-run-{name}", _args("bake", "--preset", "silk", "--dry-run", *words), 2, expect)
              for name, (words, expect) in DRY_RUN_FARM.items()]

ALL = STAGE_CASES + _corpus_cases() + TABLE_CASES + CURVE_CASES + CLI_CASES


def test_the_corpus_is_large_and_covers_every_category():
    assert len(ALL) >= 150
    assert len({c.id for c in ALL}) == len(ALL)
    kinds = {c.id.split("-")[0] for c in ALL}
    assert {"stage", "corpus", "table", "curves", "bcc", "hair", "cli"} <= kinds


@pytest.mark.parametrize("case", ALL, ids=[c.id for c in ALL])
def test_hostile_input(case, tmp_path, capsys):
    run_case(case, tmp_path, capsys)


#: Command lines argparse refuses: the error is the only line on stderr (no usage block above it).
ARGPARSE_ERRORS = [
    ["cloth", "stockinette", "-o", "{tmp}/c.usda", "--rows", "0"],
    ["cloth", "stockinette", "-o", "{tmp}/c.usda", "--loops", "nan"],
    ["cloth", "satin", "-o", "{tmp}/c.usda", "--warps", "1e9"],
    ["cloth", "satin", "-o", "{tmp}/c.usda", "--spacing", "inf"],
    ["cloth", "satin", "-o", "{tmp}/c.usda", "--floats", "-1"],
    ["cloth", "plain", "-o", "{tmp}/c.usda", "--depth-of-shade", "nan"],
    ["cloth", "tartan", "-o", "{tmp}/c.usda"],
    ["cloth", "plain"],
    ["import", "{tmp}/x.bcc", "-o", "{tmp}/o.usda", "--width", "0"],
    ["import", "{tmp}/x.bcc", "-o", "{tmp}/o.usda", "--meters-per-unit", "nan"],
    ["import", "{tmp}/x.bcc", "-o", "{tmp}/o.usda", "--depth-of-shade", "-1"],
    ["import", "-o", "{tmp}/o.usda"],
    ["import", "{tmp}/x.bcc", "-o", "{tmp}/o.usda", "--bogus"],
    ["check", "--time", "soon", "{tmp}/s.usda"],
    ["presets", "--bogus"],
    ["render", "{tmp}/s.usda", "--device", "tpu"],
    ["nosuch"],
    [],
]


@pytest.mark.parametrize("words", ARGPARSE_ERRORS, ids=[" ".join(w) or "nothing" for w in ARGPARSE_ERRORS])
def test_command_line_errors_are_one_line(words, tmp_path, capsys):
    argv = _args(*words)(tmp_path)
    with pytest.raises(SystemExit) as e:
        main(argv)
    assert e.value.code == 2
    err = capsys.readouterr().err
    assert err.count("\n") == 1 and "error:" in err and "usage:" not in err, err
