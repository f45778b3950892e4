"""Fixtures shared by the test files, and the session's checks and options.

The baked tables here are session-scoped: each is traced once per test run, however many
files use it. Tables are immutable once baked (recolouring returns a new object), and the
bake is deterministic for its settings and seed on a given machine, so sharing one changes
nothing a test sees. Imports are inside the fixtures so that a file that needs none of them
does not pay for, or depend on, the baker.
"""
from __future__ import annotations

import os
from pathlib import Path
from typing import TYPE_CHECKING

import pytest

if TYPE_CHECKING:
    from usdfiber.bake.table import BcsdfTable

ETA = 1.55  # the index of refraction of every shared table


@pytest.fixture(scope="session")
def circle_table() -> BcsdfTable:
    """A round fiber, beta 8 deg, on a 10 degree grid, 20k photons per direction (about 1 s)."""
    from usdfiber.bake import profiles
    from usdfiber.bake.baker import bake_table
    from usdfiber.bake.settings import BakeSettings

    return bake_table(profiles.circle(), ETA, 8.0, None, BakeSettings(resolution_deg=10, photons=20000, batches=2))


@pytest.fixture(scope="session")
def silk_render_table() -> BcsdfTable:
    """The built-in silk cross section at its own size (non-round: it passes some rays),
    beta 8 deg, on a 15 degree grid, 1500 photons per direction: quick to bake, for
    rendering and BSDF tests in Mitsuba (about 1 s)."""
    from usdfiber.bake import profiles
    from usdfiber.bake.baker import bake_table
    from usdfiber.bake.settings import BakeSettings

    prof = profiles.builtin_profiles("silk", 1)[0]
    return bake_table(prof, ETA, 8.0, None, BakeSettings(resolution_deg=15, photons=1500, batches=2))


@pytest.fixture(scope="session")
def silk_table() -> BcsdfTable:
    """The silk cross section scaled to a 1 um diameter, beta 6.5 deg, on a 30 degree grid,
    12k photons per direction in 4 batches: a non-round, fairly smooth fiber for the
    recolouring and evaluation tests (about 1 s)."""
    from usdfiber.bake import profiles
    from usdfiber.bake.baker import bake_table
    from usdfiber.bake.settings import BakeSettings

    silk = profiles.builtin_profiles("silk", 1)[0].centered().scaled_to_diameter(1.0)
    return bake_table(silk, ETA, 6.5, None, BakeSettings(resolution_deg=30, photons=12000, batches=4))


@pytest.fixture(scope="session")
def table_cache_dir(tmp_path_factory: pytest.TempPathFactory) -> Path:
    """One table cache root for the run's translation and render tests: a table (request and
    bake settings) is baked once per run, whichever file asks first. Tests of the cache
    itself, which damage or count its files, use their own."""
    return tmp_path_factory.mktemp("table-cache")


def pytest_configure(config: pytest.Config) -> None:
    """USDFIBER_TEST_VECTOR_WIDTH=8 or 16: compile Dr.Jit's LLVM kernels for a machine of that
    SIMD width (docs/testing.md). Set here, before any test module compiles a kernel."""
    width = os.environ.get("USDFIBER_TEST_VECTOR_WIDTH")
    if width:
        from vector_width import force_vector_width

        if not width.isdigit():
            raise pytest.UsageError(f"USDFIBER_TEST_VECTOR_WIDTH={width!r}: expected 8 or 16")
        try:
            force_vector_width(int(width))
        except (ValueError, RuntimeError) as e:
            raise pytest.UsageError(str(e)) from None


def pytest_report_header(config: pytest.Config) -> str:
    """The SIMD width the Monte-Carlo tests run at: results differ between widths."""
    from vector_width import current_target

    try:
        cpu, width = current_target()
    except Exception as e:  # no LLVM on this machine: the tests that need it say so
        return f"Dr.Jit LLVM target: unavailable ({e})"
    return f"Dr.Jit LLVM target: {cpu}, {width} float lanes (USDFIBER_TEST_VECTOR_WIDTH=8|16 to change)"


def pytest_sessionstart(session: pytest.Session) -> None:
    """Refuse to test another checkout's code: ``usdfiber`` and ``usdfiber.translators`` must
    be imported from this checkout (an editable install of another clone would serve its
    modules silently)."""
    import importlib
    from pathlib import Path

    root = Path(__file__).resolve().parents[1]
    for name, own in (("usdfiber", root / "usdfiber"), ("usdfiber.translators", root / "translators")):
        try:
            module = importlib.import_module(name)
        except ImportError as e:
            raise pytest.UsageError(f"{name} cannot be imported ({e}): run `pip install -e .` in {root}") from None
        where = Path(module.__file__ or "").resolve().parent
        if where != own:
            raise pytest.UsageError(f"{name} is imported from {where}, not from this checkout ({own}): "
                                    f"run `pip install -e .` in {root}")
