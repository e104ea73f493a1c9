"""pytest plugin: each test's CPU seconds (this process + the children it waited for) in its JUnit record.

    PYTHONPATH=scripts:$PYTHONPATH pytest -p pytest_cpu_times --junitxml=A.xml ...

Adds a ``cpu_s`` property to every test case of the JUnit XML: user + system CPU seconds of the pytest process
and of the child processes it reaped, from the start of the test's setup to the end of its teardown
(``resource.getrusage``).  CPU seconds move much less than wall seconds when the machine is shared, so two
commits' suites can be compared on a busy machine: ``python scripts/compare_test_durations.py --cpu A.xml
B.xml``.  Children still running at teardown (none should be) are not counted; a contended core still costs
some CPU time (caches, frequency), so order the runs A B B A and read the pairs' disagreement as the noise.
Not loaded by the suite itself: it is passed with ``-p`` only when timing a commit, including old commits
that predate this file.
"""
from __future__ import annotations

import resource

import pytest

_START = pytest.StashKey[float]()


def _cpu_s() -> float:
    own, kids = resource.getrusage(resource.RUSAGE_SELF), resource.getrusage(resource.RUSAGE_CHILDREN)
    return own.ru_utime + own.ru_stime + kids.ru_utime + kids.ru_stime


@pytest.hookimpl(tryfirst=True)
def pytest_runtest_setup(item):
    item.stash[_START] = _cpu_s()


@pytest.hookimpl(hookwrapper=True)
def pytest_runtest_makereport(item, call):
    # called after each phase has run; the teardown report is the last, and it copies item.user_properties
    if call.when == "teardown" and _START in item.stash:
        item.user_properties.append(("cpu_s", f"{_cpu_s() - item.stash[_START]:.4f}"))
    yield
