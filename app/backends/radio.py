"""`omniformation radio`: one emulated radio that several leaders share (a fleet on real robots).

Each leader gets a pseudo-terminal of its own (its serial link, as a radio dongle would be);
every frame a leader writes reaches every follower and every other leader on the medium, and
every follower's reply reaches every leader (a leader's own link sorts out what answers it). The medium loses a frame
with probability ``drop`` and delivers the rest ``delay`` later, in order. A leader's link can
be cut for a while (:meth:`Radio.cut`): nothing it writes goes out, nothing reaches it.

The followers are :mod:`core.link.follower` (the reference firmware's rules, protocol 2
ownership included: one owner with a lease; docs/follower-protocol.md), stepped in real time.
Each robot counts what ownership is for: DRIVEs obeyed from two leaders within 100 ms
(``two_owners``, never expected) and the refusals it sent. The robots speak protocol 3: they
obey only authenticated, fresh frames (``auth``: the fleet's radio key and leaders, or the open
key), and count what they refuse without a word; ``older`` robots speak protocol 2 only.
"""

from __future__ import annotations

import heapq
import itertools
import json
import select
import threading
import time
from collections.abc import Callable
from dataclasses import dataclass, field
from pathlib import Path
from typing import Any

import numpy as np

from core.link import protocol as p

from core.link.follower import RadioAuth

from app.backends.emulator import STEP_S, FollowerEmulator, PtyEndpoint


@dataclass
class RadioStats:
    from_leaders: list[int] = field(default_factory=list)  # frames each leader sent on the air
    to_leaders: list[int] = field(default_factory=list)  # frames each leader was given (replies, others' frames)
    dropped: int = 0  # frames the medium lost
    cut: int = 0  # frames that met a cut link (not sent, or not delivered)
    unread: list[int] = field(default_factory=list)  # frames a leader's port did not take (nobody reading it)


class Radio:
    """``leaders`` pseudo-terminals and followers at addresses 1..``followers`` on one medium."""

    def __init__(self, leaders: int, followers: int, drop: float = 0.0, delay_s: float = 0.0, seed: int = 0,
                 clock: Callable[[], float] = time.monotonic, robots: FollowerEmulator | None = None,
                 auth: RadioAuth | None = None, older: tuple[int, ...] = ()) -> None:
        """``robots``: followers someone else steps (the arena's, moving in its world); by default
        the radio's own, stepped in real time by :meth:`run`, provisioned with ``auth`` (None:
        protocol 2 robots that know no key), the ``older`` ones speaking protocol 2 only."""
        self.robots = robots if robots is not None else FollowerEmulator(list(range(1, followers + 1)), auth=auth,
                                                                       older=older)
        self._steps_robots = robots is None
        self.endpoints = [PtyEndpoint() for _ in range(leaders)]
        self.paths = [e.path for e in self.endpoints]
        self._parsers = [p.FrameParser() for _ in range(leaders)]
        self._replies = p.FrameParser()
        self.drop, self.delay_s = drop, delay_s
        self._rng = np.random.default_rng(seed)
        self._clock = clock
        self._air: list[tuple[float, int, int, bytes]] = []  # (deliver at, order, to: -1 robots / leader i, bytes)
        self._order = itertools.count()
        self._cut_until = [-float("inf")] * leaders
        self._lock = threading.Lock()
        self.stats = RadioStats([0] * leaders, [0] * leaders, unread=[0] * leaders)

    def cut(self, leader: int, seconds: float) -> None:
        """Cut leader ``leader``'s link (0-based) for ``seconds`` from now."""
        with self._lock:
            self._cut_until[leader] = self._clock() + seconds

    def _is_cut(self, leader: int, now: float) -> bool:
        return now < self._cut_until[leader]

    def _send(self, to: int, data: bytes, now: float) -> None:
        """Put one frame on the air (under the lock): lost, or delivered ``delay_s`` later."""
        if self._rng.random() < self.drop:
            self.stats.dropped += 1
            return
        heapq.heappush(self._air, (now + self.delay_s, next(self._order), to, data))

    def _from_leader(self, i: int, data: bytes, now: float) -> None:
        with self._lock:
            for frame in self._parsers[i].feed(data):
                if self._is_cut(i, now):
                    self.stats.cut += 1
                    continue
                self.stats.from_leaders[i] += 1
                raw = p.encode_frame(frame)
                self._send(-1, raw, now)
                for j in range(len(self.endpoints)):  # the other leaders hear it too: one medium
                    if j != i:
                        self._send(j, raw, now)

    def _deliver(self, now: float) -> list[tuple[int, bytes]]:
        """What is due now: frames to the robots are answered (the replies go on the air);
        replies are handed to every leader whose link is not cut."""
        out: list[tuple[int, bytes]] = []
        with self._lock:
            while self._air and self._air[0][0] <= now:
                _, _, to, data = heapq.heappop(self._air)
                if to < 0:
                    for reply in self._replies.feed(self.robots.receive(data)):
                        raw = p.encode_frame(reply)  # each reply a frame of its own on the air
                        for i in range(len(self.endpoints)):
                            self._send(i, raw, now)
                elif self._is_cut(to, now):
                    self.stats.cut += 1
                else:
                    self.stats.to_leaders[to] += 1
                    out.append((to, data))
        return out

    def run(self, stop: threading.Event) -> None:
        """Carry frames and step the robots in real time until ``stop``."""
        fds = {e.master: i for i, e in enumerate(self.endpoints)}
        last = self._clock()
        while not stop.is_set():
            ready, _, _ = select.select(list(fds), [], [], STEP_S / 2)
            now = self._clock()
            for fd in ready:
                i = fds[fd]
                data = self.endpoints[i].read(0.0)
                if data:
                    self._from_leader(i, data, now)
            for i, data in self._deliver(now):
                if not self.endpoints[i].offer(data):  # a leader that does not read misses it; the medium goes on
                    self.stats.unread[i] += 1
            while self._steps_robots and now - last >= STEP_S:
                self.robots.step(STEP_S)
                last += STEP_S

    def summary(self) -> dict[str, Any]:
        """Each robot's owner and counts, and the medium's (for `radio --summary`)."""
        robots = self.robots.snapshot()
        return {
            "robots": {f"R{a}": {"owner": s.owner, "two_owners": s.two_owners, "nacks": s.nacks,
                                 "moving": s.moving, "refused": vars(s.refusals)} for a, s in sorted(robots.items())},
            "two_owners": sum(s.two_owners for s in robots.values()),
            "from_leaders": list(self.stats.from_leaders), "to_leaders": list(self.stats.to_leaders),
            "dropped": self.stats.dropped, "cut": self.stats.cut, "unread": list(self.stats.unread),
        }

    def close(self) -> None:
        for e in self.endpoints:
            e.close()


def run_radio(leaders: int, followers: int, drop: float, delay_ms: float, seed: int,
              summary_path: Path | None = None, minutes: float | None = None, auth: RadioAuth | None = None,
              older: tuple[int, ...] = ()) -> int:
    """`omniformation radio` (arguments: app.cli.emulator)."""
    import signal
    import sys

    radio = Radio(leaders, followers, drop, delay_ms / 1000.0, seed, auth=auth, older=older)
    stop = threading.Event()
    for sig in (signal.SIGINT, signal.SIGTERM):
        signal.signal(sig, lambda *_: stop.set())
    keys = "protocol 2, no key" if auth is None else (
        "the open key: any leader" if auth.keys == RadioAuth().keys else f"the fleet's key, leaders {list(auth.leaders)}")
    print(f"omniformation: radio with followers 1..{followers}, {leaders} leader links (drop {drop:g},"
          f" delay {delay_ms:g} ms; robots: {keys}" + (f"; R{', R'.join(map(str, older))} protocol 2 only" if older
                                                       else "") + ")", flush=True)
    for i, path in enumerate(radio.paths):
        print(f"leader {i + 1}: {path}", flush=True)
    if minutes is not None:
        timer = threading.Timer(minutes * 60, stop.set)
        timer.daemon = True
        timer.start()
    try:
        radio.run(stop)
    finally:
        s = radio.summary()
        radio.close()
        if summary_path is not None:
            summary_path.write_text(json.dumps(s, indent=1) + "\n")
        print(f"omniformation: radio stopped: {sum(s['from_leaders'])} frames from leaders, {s['dropped']} lost,"
              f" robots obeying two owners within 100 ms: {s['two_owners']}", file=sys.stderr, flush=True)
    return 0
