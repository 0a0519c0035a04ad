"""Fixtures several test modules share (helpers without pytest's machinery: tests/helpers.py)."""

from __future__ import annotations

import faulthandler
import math
import os
import sys
from collections.abc import Iterator

import pytest

from tests.helpers import EmulatorThread


@pytest.fixture
def emulated() -> Iterator[EmulatorThread]:
    """Three emulated followers on a real pty, served from this process."""
    em = EmulatorThread()
    yield em
    em.close()


# A run whose process does not end once its report is printed (a thread that is not a daemon, a
# library's runtime that never lets go at exit) would hold CI until its time limit with nothing to
# say. pytest-timeout covers each test, not the exit: this does.
EXIT_GRACE_S = 120.0
EXIT_GRACE_VAR = "OMNIFORMATION_TEST_EXIT_GRACE_S"
_GRACE = pytest.StashKey[float]()  # the run's, once checked


def pytest_configure(config: pytest.Config) -> None:
    """The exit's grace (EXIT_GRACE_VAR, seconds), checked before any test runs."""
    text = os.environ.get(EXIT_GRACE_VAR, str(EXIT_GRACE_S))
    try:
        grace = float(text)
    except ValueError:
        grace = math.nan
    if not 0 < grace < 86400:  # (NaN too)
        raise pytest.UsageError(f"{EXIT_GRACE_VAR} must be a number of seconds above 0 and under a day (got {text!r})")
    config.stash[_GRACE] = grace


def pytest_unconfigure(config: pytest.Config) -> None:
    """The run is over and reported: if the process is still there the grace later, every
    thread's stack goes to stderr and the process ends with status 1 (faulthandler)."""
    faulthandler.dump_traceback_later(config.stash.get(_GRACE, EXIT_GRACE_S), exit=True, file=sys.__stderr__)
