"""Stopping child processes as a person stops them: one helper for every command and test that starts some."""

from __future__ import annotations

import signal
import subprocess


def interrupt(*procs: subprocess.Popen, grace_s: float = 30.0) -> None:  # type: ignore[type-arg]
    """Ctrl-C (SIGINT) to every process still running, all first (they shut down side by side),
    then wait for each; one that has not ended within ``grace_s`` is killed."""
    for p in procs:
        if p.poll() is None:
            p.send_signal(signal.SIGINT)
    for p in procs:
        try:
            p.wait(grace_s)
        except subprocess.TimeoutExpired:
            p.kill()
            p.wait(10)
