"""Whole lines on the console whichever thread prints them (app.console): the command's lines and
the loop's, printed at once, never run into each other."""

from __future__ import annotations

import subprocess
import sys
import threading
import time

from app.console import WholeLines, whole_lines
from tests.helpers import ROOT


class SlowStream:
    """A console that takes a moment over each write (a terminal, a full pipe): the other thread
    gets the interpreter between print's text and its line end."""

    def __init__(self) -> None:
        self.parts: list[str] = []

    def write(self, text: str) -> int:
        self.parts.append(text)
        time.sleep(0.0005)
        return len(text)

    def flush(self) -> None:
        pass


def _print_at_once(stream, lines: int = 200) -> list[str]:
    def say(who: str) -> None:
        for k in range(lines):
            print(f"omniformation: {who} line {k} " + who * 20, file=stream)

    threads = [threading.Thread(target=say, args=(who,)) for who in "AB"]
    for t in threads:
        t.start()
    for t in threads:
        t.join()
    return "".join(stream.parts if isinstance(stream, SlowStream) else stream.stream.parts).splitlines()


def _whole(line: str) -> bool:
    who = line.split(" ")[1] if line.count("omniformation:") == 1 else ""
    return who in ("A", "B") and line.endswith(" " + who * 20)


def test_two_threads_printing_at_once_write_whole_lines():
    raw = _print_at_once(SlowStream())
    assert not all(_whole(line) for line in raw), "the console here must be slow enough to show the fault"
    lines = _print_at_once(WholeLines(SlowStream()))  # type: ignore[arg-type]  # a console, as print takes one
    assert len(lines) == 400 and all(_whole(line) for line in lines), [x for x in lines if not _whole(x)][:3]
    for who in "AB":  # each thread's lines in its own order
        assert [int(x.split()[3]) for x in lines if x.split()[1] == who] == list(range(200))


def test_text_without_a_line_end_is_written_on_flush_and_when_the_console_is_put_back():
    out = SlowStream()
    sys_stream = WholeLines(out)  # type: ignore[arg-type]
    sys_stream.write("ready? ")
    assert out.parts == []  # held: its line has not ended
    sys_stream.flush()
    assert out.parts == ["ready? "]
    other = threading.Thread(target=sys_stream.write, args=("from another thread",))
    other.start()
    other.join()
    sys_stream.release()
    assert out.parts == ["ready? ", "from another thread"]


def test_a_real_pipe_gets_whole_lines_from_two_threads():
    """The command line's own console (a pipe, unbuffered), two threads printing at once."""
    code = (
        "import threading\n"
        "from app.console import whole_lines\n"
        "def say(who):\n"
        "    for k in range(2000):\n"
        "        print(f'omniformation: {who} line {k} ' + who * 20, flush=True)\n"
        "with whole_lines():\n"
        "    ts = [threading.Thread(target=say, args=(w,)) for w in 'AB']\n"
        "    [t.start() for t in ts]\n"
        "    [t.join() for t in ts]\n"
    )
    out = subprocess.run([sys.executable, "-u", "-c", code], capture_output=True, text=True, cwd=ROOT, timeout=120)
    assert out.returncode == 0, out.stderr
    lines = out.stdout.splitlines()
    assert len(lines) == 4000 and all(_whole(line) for line in lines), [x for x in lines if not _whole(x)][:3]


def test_the_console_is_as_it_was_after_a_command():
    before = sys.stdout, sys.stderr
    with whole_lines():
        assert isinstance(sys.stdout, WholeLines) and isinstance(sys.stderr, WholeLines)
        with whole_lines():  # nested: not wrapped twice
            assert not isinstance(sys.stdout.stream, WholeLines)
    assert (sys.stdout, sys.stderr) == before
