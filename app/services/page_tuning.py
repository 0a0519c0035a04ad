"""The Tuning panel with the page in a process of its own: its step tests and sweeps run on the
loop's side (they step the loop's team and read the loop's store); the page's panel sends what its
buttons ask as plain values and draws what comes back (docs/safety.md, "The page in a process of
its own").

* page -> loop: ``("tuning", call, action, args)``; ``action`` is ``test`` (a step test's fields),
  ``sweep`` (a SweepAsk's and a step test's fields), ``cancel_test`` or ``cancel_sweep``. The loop's
  side builds the test and the sweep from the values, checks them as the panel in one process
  does (core.control.tuning.check_step_test, StepTests.request, LiveBench.start_sweep) and answers
  ``("tuning", "reply", call, why | None)``. A message of any other shape is refused in the answer
  and starts nothing. Gains set from a trial or a sweep point go as the panel's parameter changes
  (the "update" messages, the store's validation).
* loop -> page: ``("tuning", "trial", Trial)`` for each row, ``("tuning", "status", text)`` when
  the runner's status changes, ``("tuning", "progress", done, total)`` and ``("tuning", "sweep",
  SweepResult)``; the page draws the figures. A new page after a crash is sent every row and the
  last sweep.
"""

from __future__ import annotations

import itertools
import threading
from collections.abc import Callable
from typing import Any

from core.control.tuning import StepTest

from app.dashboard.tuning_panel import LiveBench, SweepAsk

REPLY_S = 10.0  # how long the page waits for the loop's side to answer a button


def test_from(values: Any) -> StepTest:
    """A step test from plain values (kind, follower, size, formation, window_s); TypeError if the
    values are not of that shape (their ranges are checked where the test is run)."""
    if not isinstance(values, dict) or set(values) != {"kind", "follower", "size", "formation", "window_s"}:
        raise TypeError("a step test is kind, follower, size, formation and window_s")
    kind, follower, size, formation, window = (values[k] for k in ("kind", "follower", "size", "formation", "window_s"))
    if not (isinstance(kind, str) and isinstance(formation, str) and type(follower) is int
            and all(isinstance(v, (int, float)) and not isinstance(v, bool) for v in (size, window))):
        raise TypeError("a step test's kind and formation are texts, its follower a whole number, its size and"
                        " window numbers")
    return StepTest(kind, follower, float(size), formation, float(window))


def ask_from(values: Any) -> SweepAsk:
    """A sweep's description from plain values (five texts); TypeError if it is not one."""
    names = ("gain1", "range1", "gain2", "range2", "feedback")
    if not isinstance(values, dict) or set(values) != set(names) or not all(isinstance(values[k], str) for k in names):
        raise TypeError(f"a sweep is {', '.join(names)}, each a text")
    return SweepAsk(*(values[k] for k in names))


def _plain(test: StepTest) -> dict[str, Any]:
    return {"kind": test.kind, "follower": test.follower, "size": test.size, "formation": test.formation,
            "window_s": test.window_s}


class TuningServer:
    """The loop's side: answers the page's tuning messages with ``bench`` and posts back what the
    bench reports (``post``: queues a message for the page, never blocks the loop)."""

    def __init__(self, bench: LiveBench, post: Callable[[tuple[Any, ...]], None]) -> None:
        self.bench = bench
        self.post = post
        self.refused = 0  # messages of no known shape (each answered, none acted on)
        self._status = ""
        bench.tests.listeners.append(lambda trial: self.post(("tuning", "trial", trial)))
        bench.sweeps.on_progress.append(lambda done, total: self.post(("tuning", "progress", done, total)))
        bench.sweeps.on_done.append(lambda result: self.post(("tuning", "sweep", result)))

    def new_page(self) -> None:
        """A page just started: every row so far and the last sweep."""
        self._status = ""
        for trial in list(self.bench.tests.trials):
            self.post(("tuning", "trial", trial))
        if self.bench.sweeps.last is not None:
            self.post(("tuning", "sweep", self.bench.sweeps.last))

    def each_tick(self) -> None:
        """The runner's status, when it changed."""
        status = self.bench.tests.status
        if status != self._status:
            self._status = status
            self.post(("tuning", "status", status))

    def receive(self, msg: tuple[Any, ...]) -> None:
        """One message from the page: act on it as its button would, and answer."""
        call = msg[1] if len(msg) > 1 and type(msg[1]) is int else -1
        try:
            if len(msg) not in (3, 4):
                raise TypeError("a tuning message is (tuning, call, action) or (tuning, call, action, values)")
            why = self._act(*msg[2:])
        except (TypeError, ValueError, OverflowError) as exc:
            self.refused += 1
            why = f"refused: {exc}"
        self.post(("tuning", "reply", call, why))

    def _act(self, action: Any, args: Any = None) -> str | None:
        if action == "test":
            return self.bench.tests.request(test_from(args))
        if action == "sweep" and isinstance(args, dict) and set(args) == {"ask", "test"}:
            return self.bench.start_sweep(ask_from(args["ask"]), test_from(args["test"]))
        if action == "cancel_test" and args is None:
            return None if self.bench.tests.cancel() else "no step test is running"
        if action == "cancel_sweep" and args is None:
            return None if self.bench.sweeps.cancel() else "no sweep is running"
        raise TypeError(f"no tuning action {action!r} with these values")


def serve_tuning(page: Any, bench: LiveBench) -> TuningServer:
    """Serve the page's Tuning panel from ``bench`` (``page``: app.services.page_process.PageProcess,
    not started yet)."""
    server = TuningServer(bench, page.post)
    page.serve("tuning", server.receive)
    page.before_send.append(server.each_tick)
    page.new_page.append(server.new_page)
    page.tuning = (True, bench.vision_offered)
    return server


class _PageTests:
    """The page's view of the loop's step tests: the rows and status it was sent; run and cancel
    go to the loop's side."""

    def __init__(self, bench: PageBench) -> None:
        self.bench = bench
        self.trials: list[Any] = []
        self.listeners: list[Callable[[Any], None]] = []
        self.status = "idle"

    def request(self, test: StepTest) -> str | None:
        return self.bench.call("test", _plain(test))

    def cancel(self) -> bool:
        return self.bench.call("cancel_test") is None


class _PageSweeps:
    """The page's view of the loop's sweeps: progress and results as they come back."""

    def __init__(self, bench: PageBench) -> None:
        self.bench = bench
        self.on_progress: list[Callable[[int, int], None]] = []
        self.on_done: list[Callable[[Any], None]] = []
        self.last: Any = None

    def cancel(self) -> bool:
        return self.bench.call("cancel_sweep") is None


class PageBench:
    """The Tuning panel's bench in the page's process (TuningPanel's ``bench``); ``send`` puts one
    message on the pipe to the loop."""

    def __init__(self, send: Callable[[tuple[Any, ...]], bool], vision_offered: bool) -> None:
        self.send = send
        self.vision_offered = vision_offered
        self.tests = _PageTests(self)
        self.sweeps = _PageSweeps(self)
        self._calls = itertools.count(1)
        self._waiting: dict[int, tuple[threading.Event, list[str | None]]] = {}
        self._lock = threading.Lock()

    def start_sweep(self, ask: SweepAsk, test: StepTest) -> str | None:
        return self.call("sweep", {"ask": dict(vars(ask)), "test": _plain(test)})

    def call(self, action: str, args: Any = None) -> str | None:
        """Ask the loop's side and wait for its answer (why not, or None)."""
        done, answer = threading.Event(), [None]  # type: tuple[threading.Event, list[str | None]]
        with self._lock:
            call = next(self._calls)
            self._waiting[call] = (done, answer)
        try:
            if not self.send(("tuning", call, action, args)):
                return "the loop's process is gone"
            if not done.wait(REPLY_S):
                return f"the loop did not answer within {REPLY_S:g} s"
            return answer[0]
        finally:
            with self._lock:
                self._waiting.pop(call, None)

    def receive(self, msg: tuple[Any, ...]) -> None:
        """One message from the loop's side (on the page's receiving thread)."""
        what = msg[1]
        if what == "reply":
            with self._lock:
                waiting = self._waiting.get(msg[2])
            if waiting is not None:
                waiting[1][0] = msg[3]
                waiting[0].set()
        elif what == "trial":
            trial = msg[2]
            self.tests.trials = [t for t in self.tests.trials if t.number != trial.number] + [trial]
            self.tests.trials.sort(key=lambda t: t.number)
            for on_trial in list(self.tests.listeners):
                on_trial(trial)
        elif what == "status":
            self.tests.status = str(msg[2])
        elif what == "progress":
            for fn in list(self.sweeps.on_progress):
                fn(int(msg[2]), int(msg[3]))
        elif what == "sweep":
            self.sweeps.last = msg[2]
            for done_fn in list(self.sweeps.on_done):
                done_fn(msg[2])
