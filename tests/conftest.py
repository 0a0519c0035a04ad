"""Fixtures several test modules share (helpers without pytest's machinery: tests/helpers.py)."""

from __future__ import annotations

from collections.abc import Iterator

import pytest

from tests.helpers import EmulatorThread


@pytest.fixture
def emulated() -> Iterator[EmulatorThread]:
    """Three emulated followers on a real pty, served from this process."""
    em = EmulatorThread()
    yield em
    em.close()
