"""The soak's accounts of memory (app.memory): they follow what a process really holds."""

from __future__ import annotations

import os
import sys

import pytest

from app.memory import native_heap_mb, python_heap_mb

pytestmark = pytest.mark.skipif(not sys.platform.startswith("linux"), reason="glibc and /proc")


def test_pythons_allocator_account_sees_live_objects_come_and_go_and_gives_fd_2_back():
    fd2 = os.fstat(2)
    before = python_heap_mb()
    assert before is not None
    arenas0, objects0, threads = before
    assert 0 < objects0 <= arenas0 and threads >= 1
    held = [{"k": i} for i in range(100_000)]  # ~ 100 k small dicts: well over 10 MB of pymalloc blocks
    during = python_heap_mb()
    assert during is not None and during[1] - objects0 > 10.0 and during[0] >= during[1]
    del held
    after = python_heap_mb()
    assert after is not None and after[1] < during[1] - 10.0
    now = os.fstat(2)
    assert (now.st_dev, now.st_ino) == (fd2.st_dev, fd2.st_ino)  # the report's detour is undone


def test_glibcs_account_sees_a_large_block_held_natively():
    before = native_heap_mb()
    if before is None:
        pytest.skip("not glibc 2.33+")
    block = bytearray(64 * 1024 * 1024)  # one block far over any mmap threshold: glibc maps it
    during = native_heap_mb()
    assert during is not None and during[2] - before[2] >= 60.0
    del block
    after = native_heap_mb()
    assert after is not None and after[2] < during[2] - 60.0
