"""A stranger on the fleet's radio, written from docs/follower-protocol.md alone: radio id 99 on the
third pty of `omniformation radio --radio-key`, two `run --radio-id N --radio-key` leaders of the
fleet on the first two. It knows the frame layout, the open key and every frame it hears on the
medium; it does not know the fleet's key. It tries what issue 42 found working: DRIVEs as leader 1,
a captured DRIVE replayed, a forged HANDOVER, the claim race after leader 1's death, keeping a
dead leader's lease alive, and STOP. Every frame is refused and counted by the robots (their own
counts, in the radio's summary), none is answered; STOP is obeyed as the documented policy says
(fail-safe), and never answered; the standby leader, refused while leader 1 lives, takes the
robots once leader 1's lease lapses, and no robot ever obeys two owners."""

from __future__ import annotations

import json
import signal
import subprocess
import sys
import threading
import time
from pathlib import Path

import serial

from core.link import protocol as p
from tests.helpers import ROOT, interrupt, main_cli, wait_for

ME = 99
ROBOTS = (1, 2, 3)


class Stranger:
    """Radio id 99's end of the medium: it hears every frame and writes its own."""

    def __init__(self, path: str) -> None:
        self.port = serial.Serial(path, 115200, timeout=0.01)
        self.parser = p.FrameParser()
        self.heard: list[tuple[float, p.Frame]] = []
        self.lock = threading.Lock()
        self.seq = 0
        self.counter = 1
        self.sent: dict[str, int] = {}  # per row
        self.expect = {"bad_mac": 0, "unknown_sender": 0, "replayed": 0, "unauthenticated": 0}
        self._stop = threading.Event()
        self._thread = threading.Thread(target=self._read, daemon=True)
        self._thread.start()

    def _read(self) -> None:
        while not self._stop.is_set():
            data = self.port.read(512)
            if data:
                now = time.monotonic()
                with self.lock:
                    self.heard += [(now, f) for f in self.parser.feed(data)]

    def frames(self) -> list[tuple[float, p.Frame]]:
        with self.lock:
            return list(self.heard)

    def write(self, row: str, frame: p.Frame | bytes, refused_as: str | None) -> None:
        self.port.write(frame if isinstance(frame, bytes) else p.encode_frame(frame))
        self.sent[row] = self.sent.get(row, 0) + 1
        if refused_as is not None:
            self.expect[refused_as] += 1
        time.sleep(0.005)

    def as_someone(self, row: str, make, sender: int) -> None:
        """One attempt, twice: plain (protocol 2) and authenticated with the open key (the only
        key the document gives; the fleet's robots hold another)."""
        self.seq = (self.seq + 1) & 0xFF
        self.write(row, make(self.seq), "unauthenticated")
        self.counter += 1
        self.write(row, p.seal(make(self.seq), p.OPEN_KEY, sender, self.counter), "bad_mac")

    def answered(self) -> int:
        """Replies that answer the stranger: plain replies (a robot of the fleet sends none) and
        authenticated ones naming radio id 99."""
        return sum(1 for _, f in self.frames() if f.msg_type >= 0x80 and (
            not p.is_sealed(f) or p.trailer(f)[0] == ME))

    def driven_by(self, leader: int, since: float = 0.0) -> set[int]:
        """Robots heard answering a DRIVE of ``leader`` (an authenticated DRIVEN naming it)."""
        return {f.address for t, f in self.frames() if t >= since and f.msg_type == p.MSG_DRIVEN | p.AUTH
                and p.trailer(f)[0] == leader}

    def close(self) -> None:
        self._stop.set()
        self._thread.join(2)
        self.port.close()


def _leader(path: str, radio_id: int, keys: Path) -> subprocess.Popen:
    return subprocess.Popen([sys.executable, "-m", "app.cli", "run", "--link", f"serial:{path}", "--radio-id",
                             str(radio_id), "--radio-key", str(keys / f"L{radio_id}.radio"), "--followers", "3",
                             "--feedback", "truth", "--port", "0", "--no-record"],
                            cwd=ROOT, stdout=subprocess.DEVNULL, stderr=subprocess.PIPE, text=True)


def test_a_stranger_on_the_radio_is_refused_everything_and_counted(tmp_path):
    keys = tmp_path / "keys"
    made = main_cli("fleet-keys", str(keys), "--fleet", "lab", "--leaders", "L1,L2,L3")
    assert made.returncode == 0, made.stderr
    summary = tmp_path / "radio.json"
    radio = subprocess.Popen([sys.executable, "-m", "app.cli", "radio", "--leaders", "3", "--followers", "3",
                              "--radio-key", str(keys / "radio" / "robots.json"), "--summary", str(summary)],
                             cwd=ROOT, stdout=subprocess.PIPE, stderr=subprocess.PIPE, text=True)
    procs: list[subprocess.Popen] = []
    stranger = None
    try:
        assert radio.stdout is not None
        header = radio.stdout.readline()
        assert "the fleet's key, leaders [1, 2, 3]" in header, header + radio.stderr.read()
        ptys = [radio.stdout.readline().split(": ", 1)[1].strip() for _ in range(3)]
        stranger = Stranger(ptys[2])
        procs.append(_leader(ptys[0], 1, keys / "radio"))
        wait_for(lambda: stranger.driven_by(1) == set(ROBOTS), 90, "leader 1 driving R1..R3")
        procs.append(_leader(ptys[1], 2, keys / "radio"))

        def captured() -> list[bytes]:  # leader 1's DRIVEs to R1, as heard on the air
            return [p.encode_frame(f) for _, f in stranger.frames()
                    if f.msg_type == p.MSG_DRIVE | p.AUTH and f.address == 1 and p.trailer(f)[0] == 1]

        wait_for(lambda: len(captured()) >= 10, 10, "leader 1's DRIVEs heard")
        wait_for(lambda: {f.address for _, f in stranger.frames() if f.msg_type == p.MSG_NACK | p.AUTH
                          and p.trailer(f)[0] == 2} == set(ROBOTS), 90, "the standby, leader 2, refused R1..R3")
        old = captured()[0]

        # 1. DRIVEs as leader 1: R1 backwards at 0.24 m/s
        for _ in range(30):
            stranger.as_someone("DRIVE as leader 1", lambda seq: p.drive(1, seq, 1, 0, -0.24, 0.0), 1)
        # 2. a DRIVE captured earlier, replayed 30 times
        for _ in range(30):
            stranger.write("captured DRIVE replayed", old, "replayed")
        # 3. a HANDOVER "from 1" of R3 to 99 for 10 s
        for _ in range(10):
            stranger.as_someone("forged HANDOVER", lambda seq: p.handover(3, seq, 1, ME, 10_000), 1)
        # 4. STOP to R2 (the document: every STOP heard stops the robot, and none is answered)
        for _ in range(20):
            stranger.write("STOP", p.stop(2, 0), None)
        assert stranger.driven_by(1, since=time.monotonic() - 0.1) or wait_for(
            lambda: stranger.driven_by(1, since=time.monotonic() - 0.3) == set(ROBOTS), 5, "leader 1 driving on")

        # leader 1 dies: the stranger races for its robots and keeps their leases alive "as leader 1"
        procs[0].send_signal(signal.SIGKILL)
        procs[0].wait(10)
        killed = time.monotonic()
        replays = captured()[-20:]
        k = 0
        while stranger.driven_by(2, since=killed) != set(ROBOTS) and time.monotonic() - killed < 20:
            for r in ROBOTS:
                stranger.as_someone("claim race after leader 1's death", lambda seq, r=r: p.claim(r, seq, ME, 10_000),
                                    ME)
                stranger.as_someone("lease keep-alive as leader 1", lambda seq, r=r: p.drive(r, seq, 1, 0, 0.0, 0.0),
                                    1)
            stranger.write("lease keep-alive as leader 1", replays[k % len(replays)], "replayed")
            k += 1
            time.sleep(0.03)
        took = {r: min(t for t, f in stranger.frames() if t >= killed and f.address == r
                       and f.msg_type == p.MSG_DRIVEN | p.AUTH and p.trailer(f)[0] == 2) - killed for r in ROBOTS}
        # the dead leader's lease (1 s) held against the stranger's keep-alives, then the standby's next
        # claim (every 0.5 s) was granted
        assert 0.9 <= min(took.values()) and max(took.values()) < 5.0, took
        answered = stranger.answered()
    finally:
        for proc in procs:
            interrupt(proc)
        if stranger is not None:
            stranger.close()
        radio.send_signal(signal.SIGINT)
        radio.wait(30)
    s = json.loads(summary.read_text())
    refused = {kind: sum(r["refused"][kind] for r in s["robots"].values()) for kind in stranger.expect}
    print(f"\nthe stranger, radio id {ME} (sent / obeyed):")
    for row, n in stranger.sent.items():
        print(f"  {row}: {n} / {'0 (all counted as refused)' if row != 'STOP' else 'stopped per policy, 0 answered'}")
    print(f"  robots' refusals {refused}; standby drove each robot {max(took.values()):.2f} s after the kill")
    assert answered == 0  # no robot answered the stranger, ever
    assert refused == stranger.expect  # every frame it sent (STOP aside) refused by the robots, by kind
    assert {r["owner"] for r in s["robots"].values()} == {2} and s["two_owners"] == 0
