"""`omniformation emulate-follower`: emulated followers behind a real serial port.

With ``--pty`` it opens a pseudo-terminal, prints the path of its serial end (and keeps a
symlink to it with ``--link-path``, so a restarted emulator is found at the same name);
with ``--port PATH`` it serves a real serial device (e.g. a USB-serial adapter or a radio
dongle). The followers are :mod:`core.link.follower` (differential drive, encoders, the
0.5 s watchdog) stepped in real time; every frame addressed to them is answered as
docs/follower-protocol.md says. ``--drop`` and ``--corrupt`` make the line lossy, to see
the service's link statistics work.

The robots speak protocol 3 (authenticated frames): with ``--radio-key ROBOTS.json`` (written by
`omniformation radio-provision`) they obey only the fleet's leaders; without it they hold the
open key (any leader, frames still bound to their replies); ``--protocol 2`` emulates older
robots that know no key at all. Bytes from the wire (:meth:`FollowerEmulator.receive`) go through
these rules; :meth:`FollowerEmulator.handle` is the arena's own in-process path (its bus has its
own access control) and speaks protocol 2.

pty notes: the emulator holds the master end and keeps its own slave fd open, so that
reading the master does not fail with EIO while no service has the port open; the slave
is put in raw mode so nothing alters the bytes.
"""

from __future__ import annotations

import argparse
import errno
import os
import select
import signal
import sys
import threading
import time
import tty
from dataclasses import dataclass
from pathlib import Path
from collections.abc import Callable

import numpy as np

from core.link import protocol as p
from core.link.follower import FollowerHardware, FollowerState, RadioAuth, handle_frame, step_follower

STEP_S = 0.005  # the emulated firmware's control period


@dataclass
class EmulatorStats:
    frames_in: int = 0
    replies: int = 0
    dropped: int = 0
    corrupted: int = 0


class FollowerEmulator:
    """Followers at ``addresses`` answering on a byte stream (fd pair or pyserial port)."""

    def __init__(self, addresses: list[int], hw: FollowerHardware = FollowerHardware(),
                 drop: float = 0.0, corrupt: float = 0.0, seed: int = 0, auth: RadioAuth | None = RadioAuth(),
                 older: tuple[int, ...] = ()) -> None:
        """``auth``: what the robots are provisioned with (None: protocol 2 robots); ``older``:
        addresses of robots that speak only protocol 2 whatever ``auth`` says."""
        self.hw = hw
        self.auth = auth
        self.older = frozenset(older)
        self.followers = {a: FollowerState(a) for a in addresses}
        self.parser = p.FrameParser()
        self.stats = EmulatorStats()
        self.drop, self.corrupt = drop, corrupt
        self._rng = np.random.default_rng(seed)
        self._lock = threading.Lock()

    def receive(self, data: bytes) -> bytes:
        """Bytes from the host in, reply bytes out."""
        out = bytearray()
        with self._lock:
            for frame in self.parser.feed(data):
                for reply in self._handle(frame, wire=True):
                    if self._rng.random() < self.drop:
                        self.stats.dropped += 1
                        continue
                    raw = bytearray(p.encode_frame(reply))
                    if self._rng.random() < self.corrupt:
                        k = int(self._rng.integers(2, len(raw)))
                        raw[k] ^= 1 << int(self._rng.integers(0, 8))
                        self.stats.corrupted += 1
                    out += raw
                    self.stats.replies += 1
        return bytes(out)

    def handle(self, frame: p.Frame) -> list[p.Frame]:
        """One frame, already parsed (the arena's own link to its robots): the replies."""
        with self._lock:
            return self._handle(frame)

    def _handle(self, frame: p.Frame, wire: bool = False) -> list[p.Frame]:
        self.stats.frames_in += 1
        targets = self.followers if frame.address == p.BROADCAST else (
            [frame.address] if frame.address in self.followers else [])
        replies = []
        for a in targets:
            auth = self.auth if wire and a not in self.older else None
            self.followers[a], reply = handle_frame(self.followers[a], self.hw, frame, auth)
            if reply is not None:
                replies.append(reply)
        return replies

    def step(self, dt: float) -> None:
        with self._lock:
            for a, s in self.followers.items():
                self.followers[a] = step_follower(s, self.hw, dt)

    def snapshot(self) -> dict[int, FollowerState]:
        with self._lock:
            return dict(self.followers)


class PtyEndpoint:
    """The master end of a fresh pseudo-terminal; ``path`` is the end a service opens."""

    def __init__(self) -> None:
        self.master, self._slave = os.openpty()
        tty.setraw(self._slave)
        self.path = os.ttyname(self._slave)
        os.set_blocking(self.master, False)

    def read(self, timeout: float) -> bytes:
        ready, _, _ = select.select([self.master], [], [], timeout)
        if not ready:
            return b""
        try:
            return os.read(self.master, 4096)
        except BlockingIOError:
            return b""
        except OSError as exc:  # EIO: no peer has the port open
            if exc.errno == errno.EIO:
                return b""
            raise

    def write(self, data: bytes) -> None:
        view = memoryview(data)
        while view:
            try:
                k = os.write(self.master, view)
            except BlockingIOError:
                select.select([], [self.master], [], 0.05)
                continue
            view = view[k:]

    def offer(self, data: bytes) -> bool:
        """Write ``data`` if the pty takes all of it now, without waiting: whether it did. A
        reader that does not read (a leader killed, its port still open here) misses frames, as
        a radio receiver that is off does; nobody else waits for it."""
        try:
            k = os.write(self.master, data)
        except OSError:  # full (EAGAIN), or no peer
            return False
        return k == len(data)

    def close(self) -> None:
        for fd in (self.master, self._slave):
            try:
                os.close(fd)
            except OSError:
                pass


class SerialEndpoint:
    """A real serial device through pyserial."""

    def __init__(self, path: str, baud: int) -> None:
        import serial

        self.path = path
        self._port = serial.Serial(path, baud, timeout=0)

    def read(self, timeout: float) -> bytes:
        ready, _, _ = select.select([self._port.fileno()], [], [], timeout)
        return bytes(self._port.read(4096)) if ready else b""

    def write(self, data: bytes) -> None:
        self._port.write(data)

    def close(self) -> None:
        self._port.close()


def serve(emulator: FollowerEmulator, endpoint: PtyEndpoint | SerialEndpoint, stop: threading.Event,
          clock: Callable[[], float] = time.monotonic) -> None:
    """Answer frames and step the followers in real time until ``stop``."""
    last = clock()
    while not stop.is_set():
        data = endpoint.read(STEP_S)
        if data:
            reply = emulator.receive(data)
            if reply:
                endpoint.write(reply)
        now = clock()
        while now - last >= STEP_S:
            emulator.step(STEP_S)
            last += STEP_S


def _ours(path: Path) -> bool:
    """A link an earlier emulator left (a symlink to a pseudo-terminal), which may be replaced."""
    return path.is_symlink() and os.readlink(path).startswith("/dev/pts/")


def _link(path: Path, target: str) -> None:
    """``path`` -> ``target``, never over a file of anybody else's (one-line UserError)."""
    from app.files import UserError

    if (path.exists() or path.is_symlink()) and not _ours(path):
        raise UserError(f"--link-path {path}: exists and is not a link to a pseudo-terminal; give a new name"
                        " (nothing was changed)")
    tmp = path.with_name(f".{path.name}.{os.getpid()}.new")
    if tmp.exists() or tmp.is_symlink():
        raise UserError(f"--link-path {path}: {tmp} is in the way; remove it or give another name")
    tmp.symlink_to(target)
    tmp.replace(path)  # atomic: a service reopening the name sees the old or the new port


def robot_auth(path: Path | None, protocol: int = 3) -> RadioAuth | None:
    """What ``--radio-key ROBOTS.json`` / ``--protocol`` give the robots (one-line UserError)."""
    from app.backends.radio_keys import load_robot_auth

    if protocol == 2:
        if path is not None:
            from app.files import UserError

            raise UserError("--protocol 2 robots know no key: leave --radio-key out")
        return None
    return RadioAuth() if path is None else load_robot_auth(path)


def run_emulator(args: argparse.Namespace) -> int:
    """`omniformation emulate-follower` (arguments: app.cli.emulator)."""
    from app.files import UserError

    addresses = [p.LEADER_ADDRESS] if args.leader else list(range(1, args.followers + 1))
    auth = robot_auth(args.radio_key, args.protocol)
    emulator = FollowerEmulator(addresses, drop=args.drop, corrupt=args.corrupt, seed=args.seed, auth=auth)
    endpoint: PtyEndpoint | SerialEndpoint
    if args.port:
        try:
            endpoint = SerialEndpoint(args.port, args.baud)
        except Exception as exc:  # noqa: BLE001 - pyserial raises SerialException / OSError / ValueError
            raise UserError(f"cannot open serial port {args.port}: {exc}") from None
    else:
        endpoint = PtyEndpoint()
    if args.link_path is not None:
        if not args.link_path.parent.is_dir():
            endpoint.close()
            raise UserError(f"{args.link_path}: folder {args.link_path.parent} does not exist")
        try:
            _link(args.link_path, endpoint.path)
        except BaseException:
            endpoint.close()
            raise
    stop = threading.Event()
    for sig in (signal.SIGINT, signal.SIGTERM):
        signal.signal(sig, lambda *_: stop.set())
    shown = f"{endpoint.path}" + (f" (also {args.link_path})" if args.link_path else "")
    what = "the leader base (address 0)" if args.leader else f"followers {addresses[0]}..{addresses[-1]}"
    print(f"omniformation: emulating {what} on {shown}", flush=True)
    flag = "--leader" if args.leader else "--link"
    print(f"omniformation: drive them with: omniformation run {flag} serial:{args.link_path or endpoint.path}",
          flush=True)
    try:
        serve(emulator, endpoint, stop)
    except KeyboardInterrupt:
        pass
    finally:
        endpoint.close()
        if args.link_path is not None and args.link_path.is_symlink() and os.readlink(args.link_path) == endpoint.path:
            args.link_path.unlink(missing_ok=True)  # ours, still: a later emulator's link is left alone
        s = emulator.stats
        print(f"omniformation: emulator stopped ({s.frames_in} frames in, {s.replies} replies,"
              f" {emulator.parser.rejected_total} rejected)", file=sys.stderr, flush=True)
    return 0
