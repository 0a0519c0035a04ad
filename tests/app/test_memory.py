"""The soak's accounts of memory (app.memory): they follow what a process really holds."""

from __future__ import annotations

import os
import sys

import pytest

from app.memory import native_heap_mb, python_heap_mb
from tests.helpers import ROOT

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


_COLLECTOR = """
import gc, threading, app.memory as m
gc.disable()  # no automatic collection: only the collector's can free the cycle below
m.FREEZE_AFTER_S, m.COLLECT_EVERY_S = 0.2, 0.2
full = []
gc.callbacks.append(lambda phase, info: full.append(1) if phase == "stop" and info["generation"] == 2 else None)
assert gc.get_freeze_count() == 0
m.bound_python_heap()
m.bound_python_heap()  # once per process
waited = threading.Event()
for _ in range(1200):  # start-up is frozen first (within a minute); what is made after is the collector's
    if gc.get_freeze_count() > 0 or waited.wait(0.05):
        break
freed = threading.Event()
class Node:
    def __del__(self):
        freed.set()
a, b = Node(), Node()
a.other, b.other = b, a  # a cycle: reference counting never frees it
del a, b
print("freed" if freed.wait(60.0) else "kept", len(full) >= 1,
      sum(t.name == "omniformation-gc" for t in threading.enumerate()))
"""


def test_the_collector_freezes_start_up_and_frees_cycles_no_automatic_collection_would():
    # A subprocess: freezing and a collector thread are for the process's life, not pytest's.
    import subprocess

    out = subprocess.run([sys.executable, "-c", _COLLECTOR], capture_output=True, text=True, timeout=120, cwd=ROOT)
    assert out.returncode == 0, out.stderr
    assert out.stdout.split() == ["freed", "True", "1"]
