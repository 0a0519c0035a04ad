"""Whole lines on the console, whichever thread prints them.

``print`` writes its text and its line's end in two writes, so two threads printing at once can
put one line inside another: a fresh-clone run's test read "...?token=...omniformation: CPU 1
kept for the loop's thread..." as one line (the command's viewer URL and the loop's kept-CPU line,
printed from two threads). While :func:`whole_lines` is in force, each thread's text is held until
its line ends (or it flushes) and then written whole, one thread at a time. The command line runs
every command in it (app.cli.main)."""

from __future__ import annotations

import sys
import threading
from collections.abc import Iterator
from contextlib import contextmanager
from typing import Any, TextIO, cast


class WholeLines:
    """A text stream in front of ``stream`` that writes only whole lines, each in one write."""

    def __init__(self, stream: TextIO) -> None:
        self.stream = stream
        self._lock = threading.Lock()
        self._held: dict[int, str] = {}  # by thread: text written since that thread's last line end

    def write(self, text: str) -> int:
        me = threading.get_ident()
        with self._lock:
            held = self._held.pop(me, "") + text
            cut = held.rfind("\n") + 1
            if cut < len(held):
                self._held[me] = held[cut:]
            if cut:
                self.stream.write(held[:cut])
        return len(text)

    def flush(self) -> None:
        """What this thread wrote, line ended or not, then the stream's own flush."""
        with self._lock:
            rest = self._held.pop(threading.get_ident(), "")
            if rest:
                self.stream.write(rest)
            self.stream.flush()

    def release(self) -> None:
        """Every thread's held text, written (this stream is being put aside)."""
        with self._lock:
            for rest in self._held.values():
                self.stream.write(rest)
            self._held.clear()
            self.stream.flush()

    def __getattr__(self, name: str) -> Any:  # the rest (fileno, isatty, encoding, buffer) is the stream's
        return getattr(self.stream, name)


@contextmanager
def whole_lines() -> Iterator[None]:
    """sys.stdout and sys.stderr write whole lines while the block runs; then they are as they were."""
    saved = sys.stdout, sys.stderr
    made: list[WholeLines] = []

    def wrapped(stream: TextIO | None) -> TextIO | None:
        if stream is None or isinstance(stream, WholeLines):
            return stream
        made.append(WholeLines(stream))
        return cast(TextIO, made[-1])

    sys.stdout, sys.stderr = wrapped(sys.stdout), wrapped(sys.stderr)
    try:
        yield
    finally:
        sys.stdout, sys.stderr = saved
        for stream in made:
            try:
                stream.release()
            except (OSError, ValueError):  # a closed pipe (`| head`): nothing more can be said there
                pass
