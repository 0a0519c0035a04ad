"""The page's health banner: what an operator must not miss, in red until acknowledged.

An alarm is raised when the loop runs below ``RATE_SHARE`` of its rate for ``RATE_HOLD_S``, when
ticks are skipped, when frame-to-command exceeds one period, when a robot's watchdog stopped it,
or when the link is lost. Each alarm is raised once while its cause lasts (an event for each
listener, the recording's among them) and stays on the banner until someone acknowledges it.
"""

from __future__ import annotations

import math
import threading
from collections.abc import Callable

from app.tick import TickState

RATE_SHARE = 0.95  # the loop below this share of its rate ...
RATE_HOLD_S = 2.0  # ... this long is an alarm


class Health:
    """Judges each tick; ``alarms`` are the unacknowledged ones (each a line for people)."""

    def __init__(self, target_hz: float = 0.0, dropped: Callable[[], int] | None = None) -> None:
        """``target_hz``: the loop's rate (0: not judged); ``dropped``: ticks the loop skipped so far."""
        self.target_hz = target_hz
        self.dropped = dropped
        self.alarms: list[str] = []
        self.listeners: list[Callable[[float, str], None]] = []  # (session time, alarm) as each is raised
        self._active: set[str] = set()  # causes that hold now (raised once while they last)
        self._slow_since = math.nan
        self._dropped_seen = 0
        self._lock = threading.Lock()

    def acknowledge(self) -> None:
        with self._lock:
            self.alarms = []

    def check(self, s: TickState) -> None:
        causes: dict[str, str] = {}
        if self.target_hz > 0 and math.isfinite(s.rate_hz) and s.rate_hz > 0:
            if s.rate_hz < RATE_SHARE * self.target_hz:
                self._slow_since = s.t if math.isnan(self._slow_since) or s.t < self._slow_since else self._slow_since
                if s.t - self._slow_since >= RATE_HOLD_S:
                    causes["rate"] = (f"loop {s.rate_hz:.1f} Hz, below {RATE_SHARE:.0%} of its {self.target_hz:g} Hz"
                                      f" for {RATE_HOLD_S:g} s")
            else:
                self._slow_since = math.nan
        if self.dropped is not None:
            dropped = self.dropped()
            if dropped > self._dropped_seen:
                causes[f"skip{dropped}"] = f"{dropped - self._dropped_seen} ticks skipped (the loop fell behind)"
                self._dropped_seen = dropped
        if self.target_hz > 0 and math.isfinite(s.latency_ms) and s.latency_ms > 1000.0 / self.target_hz:
            causes["latency"] = (f"frame to command {s.latency_ms:.0f} ms, longer than one period"
                                 f" ({1000.0 / self.target_hz:.0f} ms)")
        if "watchdog" in s.link_detail:
            names = [part.split(" ")[0] for part in s.link_detail.split(";") if "watchdog" in part]
            causes["watchdog"] = f"a watchdog stopped {', '.join(n.strip() for n in names) or 'a robot'}"
        if "lost" in s.link_state.split("(")[0]:
            causes["link"] = f"link lost: {s.link_state}"
        raised = [text for key, text in causes.items() if key not in self._active]
        self._active = {k for k in causes if not k.startswith("skip")}
        if not raised:
            return
        with self._lock:
            self.alarms = [*self.alarms, *(f"{s.t:.1f} s: {text}" for text in raised)][-6:]
        for text in raised:
            for fn in self.listeners:
                fn(s.t, text)
