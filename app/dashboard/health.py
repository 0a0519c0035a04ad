"""The page's health banner: what an operator must not miss, in red until acknowledged.

An alarm is raised when the loop runs below ``RATE_SHARE`` of its rate for ``RATE_HOLD_S``, when
ticks are skipped, when frame-to-command exceeds one period, when a robot's watchdog stopped it,
or when the link is lost. Each alarm is raised once while its cause lasts (an event for each
listener, the recording's among them) and stays on the banner until someone acknowledges it.

Worth trusting: a condition judged tick by tick (frame to command over a period, ticks skipped)
must hold on ``HOLD`` of the last ``WINDOW`` ticks before it is an alarm (one long tick on a busy
machine is none; a browser on the same two CPUs once raised one every few seconds), and the banner
has one line per kind, with how often it happened in the last minute and its last value ("frame
to command over one period (33 ms): 7 times in the last minute, last 94 ms"), rewritten in place,
never a growing paragraph. A robot's watchdog and a lost link are facts, not noise: at once.
"""

from __future__ import annotations

import math
import threading
from collections import deque
from collections.abc import Callable
from dataclasses import dataclass, field

from app.tick import TickState

RATE_SHARE = 0.95  # the loop below this share of its rate ...
RATE_HOLD_S = 2.0  # ... this long is an alarm
HOLD = 3  # a tick-by-tick condition must hold on this many ...
WINDOW = 30  # ... of the last this many ticks (one second at 30 Hz)
MINUTE_S = 60.0  # the banner counts each kind over this much of the session
KINDS = ("rate", "skipped", "latency", "watchdog", "link")  # the banner's order


@dataclass
class _Kind:
    """One kind of alarm: what the banner says of it, how often it happened lately."""

    label: str = ""
    last: str = ""
    times: deque[tuple[float, int]] = field(default_factory=deque)  # (session time, how many) in the last minute
    held: deque[int] = field(default_factory=deque)  # ticks of the last WINDOW on which the condition held
    active: bool = False  # its cause holds now (raised once while it lasts)
    shown: bool = False  # on the banner until acknowledged

    def count(self, t: float) -> int:
        while self.times and (self.times[0][0] < t - MINUTE_S or self.times[0][0] > t):  # (a reset: t went back)
            self.times.popleft()
        return sum(n for _, n in self.times)


class Health:
    """Judges each tick; ``alarms`` are the unacknowledged kinds (one line each, for people)."""

    def __init__(self, target_hz: float = 0.0, dropped: Callable[[], int] | None = None) -> None:
        """``target_hz``: the loop's rate (0: not judged); ``dropped``: ticks the loop skipped so far."""
        self.target_hz = target_hz
        self.dropped = dropped
        self.alarms: list[str] = []
        self.listeners: list[Callable[[float, str], None]] = []  # (session time, alarm) as each is raised
        self._kinds = {k: _Kind() for k in KINDS}
        self._slow_since = math.nan
        self._dropped_seen = 0
        self._skipped_told = 0  # skipped ticks already in an event (each event says how many since the last)
        self._lock = threading.Lock()

    def acknowledge(self) -> None:
        with self._lock:
            for kind in self._kinds.values():
                kind.shown = False
            self.alarms = []

    def check(self, s: TickState) -> None:
        raised: list[str] = []
        period_ms = 1000.0 / self.target_hz if self.target_hz > 0 else math.inf
        slow = False
        if self.target_hz > 0 and math.isfinite(s.rate_hz) and s.rate_hz > 0:
            if s.rate_hz < RATE_SHARE * self.target_hz:
                self._slow_since = s.t if math.isnan(self._slow_since) or s.t < self._slow_since else self._slow_since
                slow = s.t - self._slow_since >= RATE_HOLD_S
            else:
                self._slow_since = math.nan
        rate = self._kinds["rate"]
        if slow and not rate.active:
            rate.times.append((s.t, 1))
        self._judge(s, "rate", slow, slow, f"loop below {RATE_SHARE:.0%} of its {self.target_hz:g} Hz for"
                    f" {RATE_HOLD_S:g} s", f"{s.rate_hz:.1f} Hz",
                    f"loop {s.rate_hz:.1f} Hz, below {RATE_SHARE:.0%} of its {self.target_hz:g} Hz for {RATE_HOLD_S:g} s",
                    raised)
        skipped = 0
        if self.dropped is not None:
            dropped = self.dropped()
            skipped, self._dropped_seen = max(0, dropped - self._dropped_seen), max(dropped, self._dropped_seen)
        kind = self._kinds["skipped"]
        if skipped:
            kind.times.append((s.t, skipped))
            kind.held.extend([s.tick] * min(skipped, HOLD))
        held = self._window(kind, s.tick)
        told = self._dropped_seen - self._skipped_told
        if self._judge(s, "skipped", bool(skipped), held, "ticks skipped (the loop fell behind)", "",
                       f"{told} ticks skipped (the loop fell behind)", raised):
            self._skipped_told = self._dropped_seen
        late = math.isfinite(s.latency_ms) and s.latency_ms > period_ms
        kind = self._kinds["latency"]
        if late:
            kind.times.append((s.t, 1))
            kind.held.append(s.tick)
        self._judge(s, "latency", late, self._window(kind, s.tick),
                    f"frame to command over one period ({period_ms:.0f} ms)", f"{s.latency_ms:.0f} ms",
                    f"frame to command {s.latency_ms:.0f} ms, longer than one period ({period_ms:.0f} ms)", raised)
        stopped = "watchdog" in s.link_detail
        names = [part.split(" ")[0].strip() for part in s.link_detail.split(";") if "watchdog" in part]
        text = f"a watchdog stopped {', '.join(names) or 'a robot'}"
        kind = self._kinds["watchdog"]
        if stopped and not kind.active:
            kind.times.append((s.t, 1))
        self._judge(s, "watchdog", stopped, stopped, "a robot's watchdog stopped it", ", ".join(names) or "a robot",
                    text, raised)
        lost = "lost" in s.link_state.split("(")[0]
        kind = self._kinds["link"]
        if lost and not kind.active:
            kind.times.append((s.t, 1))
        self._judge(s, "link", lost, lost, "link lost", s.link_state, f"link lost: {s.link_state}", raised)
        with self._lock:
            self.alarms = [self._line(k, s.t) for k in KINDS if self._kinds[k].shown]
        for text in raised:
            for fn in self.listeners:
                fn(s.t, text)

    @staticmethod
    def _window(kind: _Kind, tick: int) -> bool:
        while kind.held and not tick - WINDOW < kind.held[0] <= tick:  # (a tick number from before a restart too)
            kind.held.popleft()
        return len(kind.held) >= HOLD

    def _judge(self, s: TickState, key: str, happened: bool, holds: bool, label: str, value: str, event: str,
               raised: list[str]) -> bool:
        """One kind on this tick: its banner line's label and last value when it ``happened``; raised
        (its ``event`` heard) when it ``holds`` and did not on the tick before; whether it was raised."""
        kind = self._kinds[key]
        if happened:
            kind.label = label
            kind.last = value or kind.last
        if holds and not kind.active:
            kind.active = kind.shown = True
            raised.append(event)
            return True
        kind.active = holds
        return False

    def _line(self, key: str, t: float) -> str:
        kind = self._kinds[key]
        n = kind.count(t)
        counted = (f"{n} in the last minute" if key == "skipped" else
                   f"{n} time{'s' if n != 1 else ''} in the last minute")
        return f"{kind.label}: {counted}" + (f", last {kind.last}" if kind.last else "")
