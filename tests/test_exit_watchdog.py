"""A test run whose process hangs at exit ends, by the suite's own conftest (tests/conftest.py),
with every thread's stack and a failing status, not at CI's time limit."""

from __future__ import annotations

import os
import subprocess
import sys
import textwrap
from pathlib import Path

ROOT = Path(__file__).resolve().parents[1]


def _run(tmp_path: Path, body: str, grace: str = "2") -> subprocess.CompletedProcess[str]:
    test = tmp_path / "test_exit.py"
    test.write_text(textwrap.dedent(body))
    env = {**os.environ, "OMNIFORMATION_TEST_EXIT_GRACE_S": grace}
    # tests.conftest as a plugin: the hook as the suite has it, on a file outside the suite
    return subprocess.run([sys.executable, "-m", "pytest", "-q", "-p", "no:cacheprovider", "-p", "tests.conftest",
                           "--rootdir", str(tmp_path), str(test)], cwd=ROOT, env=env, capture_output=True,
                          text=True, timeout=120)


def test_a_run_held_at_exit_by_a_thread_ends_failed_and_names_the_thread(tmp_path: Path) -> None:
    run = _run(tmp_path, """
        import threading

        def hold_forever():
            threading.Event().wait()

        def test_leaves_a_thread_behind():
            threading.Thread(target=hold_forever, name="never-ends", daemon=False).start()
    """)
    assert "1 passed" in run.stdout  # the report came first
    assert run.returncode == 1, (run.returncode, run.stderr[-2000:])
    assert "Timeout" in run.stderr and "hold_forever" in run.stderr, run.stderr[-2000:]


def test_a_run_that_ends_keeps_its_status(tmp_path: Path) -> None:
    passed = _run(tmp_path, "def test_fine():\n    pass\n")
    assert passed.returncode == 0, passed.stderr[-2000:]
    failed = _run(tmp_path, "def test_wrong():\n    assert 1 == 2\n")
    assert failed.returncode == 1 and "1 failed" in failed.stdout


def test_a_grace_that_is_not_a_time_is_refused_in_one_line_before_any_test(tmp_path: Path) -> None:
    for bad in ("soon", "0", "-5", "nan", "1e999"):
        run = _run(tmp_path, "def test_fine():\n    pass\n", grace=bad)
        lines = [ln for ln in run.stderr.splitlines() if ln.strip()]
        assert run.returncode == 4 and "passed" not in run.stdout, (bad, run.returncode, run.stdout, run.stderr)
        assert len(lines) == 1 and "OMNIFORMATION_TEST_EXIT_GRACE_S" in lines[0] and repr(bad) in lines[0], (bad, lines)
