"""One rate-limited voice for every per-message refusal (Foxglove, the page's gate, the bus, ROS 2,
the radio): a log is a resource too, and a party that sends bad messages must not be able to fill it.

Each kind of refusal is said in full the first time a client earns it (at most ``FIRSTS_PER_WINDOW``
such first lines per kind in a window, however many clients a flood comes from); after that it is
only counted, and at most one summary line per kind every ``SUMMARY_EVERY_S`` seconds says how many
were refused and from how many clients. A flood of any size then adds at most
``FIRSTS_PER_WINDOW + 1`` lines per kind per window (docs/safety.md, "Logs that cannot be flooded").

The lines are warnings of the ``omniformation.refused`` logger, or of the logger a part names for
its kinds (the page's gate: its own), on stderr as the service logs."""

from __future__ import annotations

import logging
import threading
import time
from collections.abc import Callable

SUMMARY_EVERY_S = 10.0  # at most one summary line per kind this often
FIRSTS_PER_WINDOW = 5  # first-occurrence lines per kind per window; beyond, counted in the summary
REMEMBERED = 4096  # clients remembered per kind (a flood from ever new addresses forgets the oldest)

log = logging.getLogger("omniformation.refused")


class Refusals:
    """Says each kind's first refusal per client, then counts; ``say`` writes one line."""

    def __init__(self, say: Callable[[str], None] | None = None, every_s: float = SUMMARY_EVERY_S,
                 clock: Callable[[], float] = time.monotonic) -> None:
        self._say = say if say is not None else log.warning
        self.every_s = every_s
        self._clock = clock
        self._lock = threading.Lock()
        self._seen: dict[str, dict[str, None]] = {}  # kind -> clients already named (insertion ordered)
        self._window: dict[str, tuple[float, int]] = {}  # kind -> (window start, first lines said in it)
        self._pending: dict[str, tuple[int, set[str]]] = {}  # kind -> (refusals not said, their clients)
        self._last_summary: dict[str, float] = {}
        self._say_of: dict[str, Callable[[str], None]] = {}  # kind -> where its lines go (a part's logger)
        self._timer: threading.Timer | None = None
        self.total: dict[str, int] = {}  # refusals per kind since start (said or counted)
        self.lines = 0  # lines written

    def refuse(self, kind: str, client: str, detail: str, logger: logging.Logger | None = None) -> None:
        """One refused message of ``kind`` (e.g. ``"foxglove: invalid message"``) from ``client``
        (an address, an identity), ``detail`` what was wrong; said or counted, never raises.
        ``logger``: where this kind's lines go (default: the one given at construction)."""
        now = self._clock()
        out: list[tuple[str, str]] = []
        with self._lock:
            if logger is not None:
                self._say_of[kind] = logger.warning
            self.total[kind] = self.total.get(kind, 0) + 1
            seen = self._seen.setdefault(kind, {})
            start, said = self._window.get(kind, (now, 0))
            if now - start >= self.every_s:
                start, said = now, 0
            if client not in seen and said < FIRSTS_PER_WINDOW:
                seen[client] = None
                if len(seen) > REMEMBERED:
                    del seen[next(iter(seen))]
                self._window[kind] = (start, said + 1)
                out.append((kind, f"{kind} ({client}): {detail} (more of this kind are counted: one line every"
                                  f" {self.every_s:g} s)"))
            else:
                self._window[kind] = (start, said)
                count, clients = self._pending.get(kind, (0, set()))
                if len(clients) < REMEMBERED:
                    clients.add(client)
                self._pending[kind] = (count + 1, clients)
                if now - self._last_summary.get(kind, -float("inf")) >= self.every_s:
                    out.append((kind, self._summary(kind, now)))
                elif self._timer is None:
                    self._timer = threading.Timer(self.every_s, self.flush)
                    self._timer.daemon = True
                    self._timer.start()
        self._write(out)

    def _summary(self, kind: str, now: float) -> str:
        count, clients = self._pending.pop(kind)
        self._last_summary[kind] = now
        who = next(iter(clients)) if len(clients) == 1 else f"{len(clients)} clients"
        return f"{kind}: {count} more from {who} since the last line"

    def flush(self, final: bool = False) -> None:
        """Say every pending count whose kind may speak now (``final``: every one, as a process
        ends); what may not waits for the next timer (one is started while counts wait)."""
        now = self._clock()
        with self._lock:
            self._timer = None
            out = [(kind, self._summary(kind, now)) for kind in list(self._pending)
                   if final or now - self._last_summary.get(kind, -float("inf")) >= self.every_s - 1e-3]
            if self._pending and self._timer is None:
                self._timer = threading.Timer(self.every_s, self.flush)
                self._timer.daemon = True
                self._timer.start()
        self._write(out)

    def _write(self, lines: list[tuple[str, str]]) -> None:
        for kind, line in lines:
            self.lines += 1
            try:
                self._say_of.get(kind, self._say)(line)
            except Exception:  # noqa: BLE001 - a log that cannot be written must not take the refusing part down
                pass


REFUSALS = Refusals()


def refuse(kind: str, client: str, detail: str, logger: logging.Logger | None = None) -> None:
    """The process's refusals (see :class:`Refusals`)."""
    REFUSALS.refuse(kind, client, detail, logger)
