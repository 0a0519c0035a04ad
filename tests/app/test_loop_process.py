"""The loop's start-up and its process: what `run` promises (docs/safety.md, README)."""

from __future__ import annotations

import os
import signal
import subprocess
import sys
import threading
import time
from pathlib import Path

WARM = "first run: compiled the loop's kernels"


def _run(cache: Path, until: str = "dashboard at") -> tuple[str, str]:
    """`omniformation run` on the simulator (no recording) with numba's cache in ``cache``, until a line
    with ``until`` and a second of ticks; then Ctrl-C. Its stdout and stderr."""
    env = dict(os.environ, NUMBA_CACHE_DIR=str(cache), PYTHONUNBUFFERED="1")
    proc = subprocess.Popen([sys.executable, "-m", "app.cli", "run", "--port", "0", "--no-record", "--feedback",
                             "truth"], stdout=subprocess.PIPE, stderr=subprocess.PIPE, text=True, env=env)
    assert proc.stdout is not None
    lines = []
    watchdog = threading.Timer(600.0, proc.kill)  # a run that never says so fails, it does not hang
    watchdog.start()
    for line in proc.stdout:
        lines.append(line)
        if until in line:
            break
    watchdog.cancel()
    time.sleep(1.0)
    proc.send_signal(signal.SIGINT)
    out, err = proc.communicate(timeout=120)
    assert proc.returncode == 0, err
    return "".join(lines) + out, err


def test_a_fresh_cache_is_compiled_before_the_clock_starts_and_only_once(tmp_path: Path) -> None:
    out, err = _run(tmp_path, WARM)
    assert out.count(WARM) == 1, out  # one line, with how long it took
    assert "compiled while the loop's clock ran" not in err, err  # no kernel left for a paced tick to compile
    out, err = _run(tmp_path)
    assert WARM not in out, out  # the cache keeps them: the second run says nothing
    assert "compiled while the loop's clock ran" not in err, err
