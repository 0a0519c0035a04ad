"""A replay opened from the live page, served from a process of its own at the lowest priority.

A replay playing at 8x decodes and draws eight ticks for every one of the loop's, and viser encodes
them: served from the page's process (`run`'s default), on the same two CPUs as the loop, it took
the loop to 24.9 Hz of its 30 and brought its alarms (`run --one-process` keeps everything, its
replays too, in the one process it is). Here it runs in a process
that is the leader of a session of its own, hence of an autogroup of its own (sched(7)), whose nice
value is set to 19: the kernel then gives the whole replay a weight of 15 against the loop's 1024,
so it runs on what the loop leaves (it still runs: it is not SCHED_IDLE, which a busy machine could
starve). The process reads the file, checks it as the live page did in-process (a file that cannot
be replayed is one line, a ValueError, and no process is left), serves the replay with its own
credentials and ends when the live page closes it, or when the page's process ends (its pipe
closes).
"""

from __future__ import annotations

import contextlib
import json
import os
import subprocess
import sys
import threading
from dataclasses import dataclass
from pathlib import Path
from typing import Any

READY_S = 120.0  # how long opening a replay may take (reading a long recording) before it is given up
NICE = 19


@dataclass(frozen=True)
class ReplayedFile:
    """What the live page's Recordings panel says of the file (as app.recording.reader.Recording does)."""

    path: Path
    note: str

    def loss_note(self) -> str:
        return self.note


class ReplayProcess:
    """A replay in a process of its own (app.dashboard.recordings_panel.ServedReplay). A child
    process started as a command (the page's process is a daemon, which multiprocessing does not let
    have children); what it is asked goes on its stdin as one JSON line (the tokens never in its
    command line), what it answers is one JSON line on its stdout; its stdin closed is its end."""

    def __init__(self, path: Path, host: str, token: str | None, viewer_token: str | None) -> None:
        """Start the process and wait until it serves; ValueError (one line) if the file cannot be
        replayed, OSError if the replay cannot serve."""
        self._proc = subprocess.Popen([sys.executable, "-m", "app.services.replay_process"], stdin=subprocess.PIPE,
                                      stdout=subprocess.PIPE, stderr=subprocess.DEVNULL, text=True,
                                      start_new_session=True)  # a session, hence an autogroup, of its own
        assert self._proc.stdin is not None and self._proc.stdout is not None
        answer: dict[str, Any] = {"failed": "os", "why": "the replay's process ended before it served"}
        timer = threading.Timer(READY_S, self._proc.kill)  # a replay that never answers is given up
        timer.start()
        try:
            self._proc.stdin.write(json.dumps({"path": str(path), "host": host, "token": token,
                                               "viewer_token": viewer_token}) + "\n")
            self._proc.stdin.flush()
            line = self._proc.stdout.readline()
            answer = json.loads(line) if line.strip() else answer
        except (OSError, ValueError):
            pass
        finally:
            timer.cancel()
        if "url" not in answer:
            self.close()
            raise (ValueError if answer.get("failed") == "file" else OSError)(str(answer.get("why")))
        self.url, self.viewer_url = str(answer["url"]), str(answer["viewer_url"])
        self.rec = ReplayedFile(path, str(answer.get("note", "")))

    @property
    def pid(self) -> int:
        return int(self._proc.pid)

    def start(self) -> None:
        """It plays from the moment it serves (nothing more to start)."""

    def close(self) -> None:
        with contextlib.suppress(OSError, ValueError):
            assert self._proc.stdin is not None
            self._proc.stdin.close()  # its end
        try:
            self._proc.wait(10.0)
        except subprocess.TimeoutExpired:
            self._proc.kill()
            self._proc.wait(10.0)


def lower_priority() -> None:
    """This process at the lowest priority against the loop's: its autogroup (its session's, of its
    own) at nice 19, which is the weight the kernel gives it against the loop's, and its threads at 19
    within it."""
    with contextlib.suppress(OSError), open("/proc/self/autogroup", "w") as f:  # Linux with autogroups only
        f.write(str(NICE))
    with contextlib.suppress(OSError):
        os.setpriority(os.PRIO_PROCESS, 0, NICE)


def main() -> None:
    """The replay's process: read, check and serve the recording until its stdin closes."""
    import signal

    signal.signal(signal.SIGINT, signal.SIG_IGN)  # Ctrl-C is the loop's process's: it closes this one
    lower_priority()
    asked = json.loads(sys.stdin.readline() or "{}")
    from app.recording.reader import check_ticks, read_recording
    from app.services.replay import ReplayService

    answers = os.fdopen(os.dup(1), "w")  # the answer's own line: whatever else would print goes nowhere
    os.dup2(2, 1)

    def say(answer: dict[str, Any]) -> None:
        answers.write(json.dumps(answer) + "\n")
        answers.flush()

    try:
        rec = read_recording(Path(asked["path"]))
        check_ticks(rec)
    except ValueError as exc:  # no recording, a damaged one: said in one line by the panel
        say({"failed": "file", "why": str(exc)})
        return
    try:
        service = ReplayService(rec, host=asked["host"], port=0, token=asked["token"],
                                viewer_token=asked["viewer_token"])
    except OSError as exc:
        say({"failed": "os", "why": str(exc)})
        return
    try:
        service.start()
        say({"url": service.url, "viewer_url": service.viewer_url, "note": rec.loss_note()})
        with contextlib.suppress(OSError, ValueError):
            sys.stdin.read()  # until the live page closes it, or its process ends
    finally:
        service.close()
    os._exit(0)  # what it serves is closed; no interpreter teardown to wait for


if __name__ == "__main__":
    main()
