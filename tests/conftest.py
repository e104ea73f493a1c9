"""Shared test fixtures: repository paths and the ../shared sample data (skipped when absent)."""
from __future__ import annotations

import os
from pathlib import Path

import pytest

# The test process runs BLAS single-threaded, as every `room stage` process does (cli.stage_blas_limit; the same
# ROOM_BLAS_THREADS, default 1, 0 = the libraries' default).  The suite's numpy work is skinny products and long dot
# products that OpenBLAS splits over threads whose spin-waits can cost more CPU than they save (session 16's machine:
# the 632 common tests took 0.79x the CPU when the process happened to run one BLAS thread,
# benchmarks/results/suite_speed_s16.md; session 17's: no change, suite_speed_s17.md).  It also makes a long dot
# product's rounding the same as in the stages.  Set before anything loads numpy's or SciPy's
# OpenBLAS (each reads the variable when it loads), so children inherit it too, as a stage's would.
_BLAS_THREADS = (os.environ.get("ROOM_BLAS_THREADS", "1").strip() or "1")
if _BLAS_THREADS.isdigit() and int(_BLAS_THREADS) > 0:
    for _var in ("OPENBLAS_NUM_THREADS", "MKL_NUM_THREADS"):
        os.environ.setdefault(_var, _BLAS_THREADS)


def pytest_configure(config):
    """bpy before anything can import pymeshlab: pymeshlab's Embree loaded first breaks bpy's (undefined symbol
    rtcGetSceneTraversable; ../shared/DESIGN.md).  Loading bpy when pytest starts (before it collects any test
    file), when installed, makes every test file independent of the order pytest collects them in
    (test_collision.py decimates with pymeshlab, and test_indirect.py / test_blender.py render with Cycles in the
    same process).  In this hook, not at import, so a child process that imports a test module for one of its
    helpers (test_depth's fresh-process training) does not load bpy for nothing."""
    try:
        import bpy  # noqa: F401
    except ImportError:
        pass


def pytest_addoption(parser):
    parser.addoption("--exhaustive", action="store_true", default=False,
                     help="also run the tests marked 'exhaustive' (every shared real mask through every stage, every "
                          "signal x stage interruption, every carina cut and navigation episode; not timed as a whole)")


def pytest_collection_modifyitems(config, items):
    """The exhaustive tier is skipped, with the reason, unless ``--exhaustive`` (or ROOM_TEST_EXHAUSTIVE=1).

    ``./dev.sh test`` (what CI runs) keeps the representatives each family's parametrisation names (two real masks
    through every stage, two interruptions, two carina cuts, one navigation episode per scene, ...);
    ``--exhaustive`` adds the rest."""
    if config.getoption("--exhaustive") or os.environ.get("ROOM_TEST_EXHAUSTIVE", "") in ("1", "true", "yes"):
        return
    skip = pytest.mark.skip(reason="exhaustive tier: ./dev.sh test --exhaustive runs it")
    for item in items:
        if item.get_closest_marker("exhaustive") is not None:
            item.add_marker(skip)


# Hypothesis draws new examples on every run unless told not to; under CI (CI=true) it derandomises, so a
# clean-clone run is reproducible.  A developer's run stays random and can still find new counter-examples.
try:
    from hypothesis import settings as _hyp_settings

    _hyp_settings.register_profile("ci", derandomize=True)
    if os.environ.get("CI", "").lower() in ("1", "true", "yes"):
        _hyp_settings.load_profile("ci")
except ImportError:
    pass

REPO = Path(__file__).resolve().parents[1]
SHARED_DATA = Path(os.environ.get("ROOM_SHARED_DATA", REPO.parent / "shared" / "data"))


def shared_path(*parts: str) -> Path:
    """A file under ../shared/data, or skip the test with the reason."""
    p = SHARED_DATA.joinpath(*parts)
    if not p.exists():
        pytest.skip(f"shared sample data not available: {p}")
    return p


@pytest.fixture
def repo() -> Path:
    return REPO
