"""What one page client may send and how often the gate speaks of it (docs/page-access.md, "How
much a client may send"): a connection's budget, a throttle for log lines and notices, and one
line of anything a client sent. Used by the gate (app.dashboard.gate) and the scene's camera."""

from __future__ import annotations

import math
import threading
import time

LOG_EVERY_S = 1.0  # an address's refused messages (and refused requests of one kind) are logged this often at most
RATE = 100.0  # messages a second a connection may send (viser's page sends its camera at most 50 a second, a
# control's value at most 20, a click or a drag at most 50 and 20: a person uses one or two at once)
BURST = 300  # and at once
STRIKES = 3  # messages dropped in this many consecutive seconds: the connection is closed


class Budget:
    """One connection's allowance (a token bucket: ``rate`` a second, ``burst`` at once), and
    whether it stays over it: messages dropped in ``strikes`` consecutive seconds."""

    def __init__(self, now: float, rate: float = RATE, burst: int = BURST, strikes: int = STRIKES) -> None:
        self.rate, self.burst, self.strikes = rate, float(burst), strikes
        self.tokens, self.at, self.start = float(burst), now, now
        self._second, self._streak = -2, 0

    def take(self, now: float) -> bool:
        """Whether one more message fits now (if not, it counts towards staying over)."""
        self.tokens = min(self.burst, self.tokens + max(0.0, now - self.at) * self.rate)
        self.at = now
        if self.tokens >= 1.0:
            self.tokens -= 1.0
            return True
        second = int(now - self.start)
        if second != self._second:
            self._streak = self._streak + 1 if second == self._second + 1 else 1
            self._second = second
        return False

    @property
    def over(self) -> bool:
        return self._streak >= self.strikes


class Throttle:
    """At most one log line per key every ``every_s``; the line says how many were not logged."""

    def __init__(self, every_s: float = LOG_EVERY_S) -> None:
        self.every_s = every_s
        self._last: dict[object, tuple[float, int]] = {}
        self._lock = threading.Lock()

    def due(self, key: object) -> int:
        """-1: stay quiet; else how many were held back since the last line for this key."""
        now = time.monotonic()
        with self._lock:
            last, held = self._last.get(key, (-math.inf, 0))
            if now - last < self.every_s:
                self._last[key] = (last, held + 1)
                return -1
            if len(self._last) > 4096:  # keys come and go with clients: forget the old ones
                self._last = {k: v for k, v in self._last.items() if now - v[0] < self.every_s}
            self._last[key] = (now, 0)
            return held


def one_line(text: str, limit: int = 200) -> str:
    """Anything a client sent, safe for one log line."""
    flat = " ".join(str(text).split())
    return flat if len(flat) <= limit else flat[:limit - 3] + "..."
