"""The radio's authentication on the host's side (protocol 3, docs/follower-protocol.md,
"Authenticated frames"): this leader's frame counter, and which reply heard on the port is an
answer to this leader under its key (an echo of a host's frame, another leader's reply, a
forged or unmatched one are told apart and counted). The serial link (app.backends.serial_link)
sends and counts; this says whose a reply is."""

from __future__ import annotations

import time
from collections.abc import Callable, Mapping
from typing import TYPE_CHECKING, Any

from core.link import protocol as p

if TYPE_CHECKING:
    from app.backends.link_stats import FollowerLinkStats

UNAUTHENTICATED = "speaks an unauthenticated protocol"
ALLOWED_NOTE = " · UNAUTHENTICATED RADIO ALLOWED"  # on every tick's link state while the flag is given
# frames a host sends, never a robot (what answers each: app.backends.serial_link.REPLIES)
HOST_KINDS = (p.MSG_SET_VELOCITY, p.MSG_STOP, p.MSG_PING, p.MSG_CLAIM, p.MSG_DRIVE, p.MSG_HANDOVER)


class FrameCounter:
    """This leader's frame counter: above every one it sent before, across restarts too, and not
    guessable by a device that does not read the frames. It starts at 256 × the milliseconds since
    2024-01-01 (UTC) plus a random 0..255, and goes up by one per frame: a leader sends far fewer
    than 256 frames a millisecond, so a restarted one always starts above where it stopped (the
    48 bits last until 2058). With a file it also starts above the high-water mark written there,
    reserved in blocks, so a wrong wall clock after a restart cannot bring back a used counter.
    The file is checked first (app.backends.radio_keys.check_counter_file): a corrupt, unreadable
    or unwritable one, or one at the end of the 48 bits or far ahead of the clock, is a one-line
    UserError, never rewritten or passed over."""

    BLOCK = 1 << 20
    EPOCH_S = 1_704_067_200.0  # 2024-01-01T00:00:00Z

    def __init__(self, wall: Callable[[], float] = time.time, path: Any = None) -> None:
        import secrets

        self._path = path
        clock = self.clock_counter(wall())
        self._last = clock + secrets.randbelow(256)
        self._reserved = -1
        if path is not None:
            from app.backends.radio_keys import check_counter_file

            self._last = max(self._last, check_counter_file(path, clock) + 1)

    @classmethod
    def clock_counter(cls, wall_s: float) -> int:
        """Where the clock alone starts the counter (before the random 0..255)."""
        return max(0, int((wall_s - cls.EPOCH_S) * 1000) * 256)

    def next(self) -> int:
        """The next frame's counter. Past 2^48 - 1 there is none: a RuntimeError, never a counter
        the robots took already (the start refuses a counter that close to its end)."""
        if self._last >= p.COUNTER_MAX:
            raise RuntimeError(f"this leader's frame counter reached {p.COUNTER_MAX}: it cannot sign another frame"
                               " (docs/follower-protocol.md, Counters that only grow)")
        self._last += 1
        if self._path is not None and self._last > self._reserved:
            from app.backends.radio_keys import write_counter_mark

            reserved = min(p.COUNTER_MAX, self._last + self.BLOCK)
            write_counter_mark(self._path, reserved)  # before the counters are used
            self._reserved = reserved
        return self._last


class ReplyAuth:
    """Whose a frame heard on the port is: ``open`` gives an answer to this leader as
    (frame, the request's counter or sequence, authenticated?), or None for anything else, and
    counts on the follower's stats what it was (an echo, unmatched, forged)."""

    def __init__(self, radio_id: int | None, sender_id: int, radio_key: bytes, tags: Mapping[int, bytes]) -> None:
        """``tags``: counter -> tag of each request sent with it (the link's, kept up to date)."""
        self.radio_id, self.sender_id, self.radio_key, self.tags = radio_id, sender_id, radio_key, tags

    def open(self, f: p.Frame, s: FollowerLinkStats) -> tuple[p.Frame, int, bool] | None:
        if f.msg_type & ~p.AUTH in HOST_KINDS and f.msg_type < 0x80:
            # on a shared radio another leader's frames are heard too: only ours coming back is an echo
            ident = p.trailer(f)[0] if p.is_sealed(f) else p.sender(f)
            s.echoes += (self.radio_id is None and not p.is_sealed(f)) or \
                ident == (self.sender_id if p.is_sealed(f) else self.radio_id)
            return None
        if p.is_sealed(f):
            if p.trailer(f)[0] != self.sender_id:
                return None  # a reply to another leader on the same radio: not ours (nor checkable)
            request_tag = self.tags.get(p.trailer(f)[1])
            if request_tag is None:
                s.unmatched += 1  # names a counter we never used: it answers nothing we sent
                return None
            opened = p.open_sealed(f, (self.radio_key,), request_tag)
            if opened is None:
                s.forged += 1  # not signed with our key: a stranger's, or a broken robot's
                return None
            return opened.frame, opened.counter, True
        asker = p.answers(f)
        if asker is not None and asker != self.radio_id:
            return None  # a protocol 2 reply to another leader on the same radio: not ours
        return f, f.seq, False
