"""What Foxglove live costs the loop (`make bench` lines; alone:
``python -m app.cli.bench.foxglove``): the live loop (vision in the loop, 3 followers, 30 Hz)
served as `run --foxglove` serves it (the server in a process of its own, FoxgloveProcess):

* its rate with the states handed to Foxglove and a client subscribed to every channel, against
  without, and the CPU the loop's process spends more per tick (the sender's pickling);
* its rate and skipped ticks with 300 clients that subscribe to everything and never read their
  sockets, against without them (the server running in both).

Both by turns (with, without, with, ...: a neighbour's load falls on both alike), medians. The
clients run in processes of their own (a viewer is on another machine in practice), written from
Foxglove's WebSocket protocol spec."""

from __future__ import annotations

import subprocess
import sys
import threading
import time
from collections.abc import Callable

import numpy as np

from app.cli.bench.family import Family

ROUNDS = 3
SILENT = 300

# A viewer from the protocol spec: advertise -> subscribe to every channel; prints "ready" once
# data flows, and on stdin's end the frames it received.
_CLIENT = """
import json, sys, threading
from websockets.sync.client import connect
ws = connect(sys.argv[1], subprotocols=["foxglove.sdk.v1", "foxglove.websocket.v1"])
count, ready = [0], [False]
def read():
  try:
    for m in ws:
        if isinstance(m, bytes):
            count[0] += 1
            if not ready[0]:
                ready[0] = True
                print("ready", flush=True)
            continue
        msg = json.loads(m)
        if msg.get("op") == "advertise":
            ws.send(json.dumps({"op": "subscribe", "subscriptions": [
                {"id": 1000 + c["id"], "channelId": c["id"]} for c in msg["channels"]]}))
  except Exception:
    pass
t = threading.Thread(target=read, daemon=True)
t.start()
sys.stdin.read()
n = count[0]
ws.close()
print(n, flush=True)
"""


# 300 clients that never read, on raw sockets (RFC 6455 handshake, subprotocol foxglove.sdk.v1):
# each reads up to the server's advertise, subscribes to every channel and never reads again. A
# line "open" on stdin opens them (answers "open N"), "close" closes them (answers "closed").
_SILENT = r"""
import base64, json, os, socket, struct, sys
host, port, n = sys.argv[1], int(sys.argv[2]), int(sys.argv[3])
def frame(p):
    key = os.urandom(4)
    head = struct.pack("!BB", 0x81, 0x80 | len(p)) if len(p) < 126 else struct.pack("!BBH", 0x81, 0x80 | 126, len(p))
    return head + key + bytes(b ^ key[i % 4] for i, b in enumerate(p))
def silent():
    s = socket.create_connection((host, port))
    s.setsockopt(socket.SOL_SOCKET, socket.SO_RCVBUF, 4096)
    key = base64.b64encode(os.urandom(16)).decode()
    s.sendall(("GET / HTTP/1.1\r\nHost: x\r\nUpgrade: websocket\r\nConnection: Upgrade\r\nSec-WebSocket-Key: " + key
               + "\r\nSec-WebSocket-Version: 13\r\nSec-WebSocket-Protocol: foxglove.sdk.v1\r\n\r\n").encode())
    buf = [b""]
    def take(k):
        while len(buf[0]) < k:
            buf[0] += s.recv(65536)
        out, buf[0] = buf[0][:k], buf[0][k:]
        return out
    head = b""
    while b"\r\n\r\n" not in head:
        head += s.recv(1)
    assert b" 101 " in head.split(b"\r\n")[0], head
    while True:
        n7 = take(2)[1] & 0x7F
        size = n7 if n7 < 126 else struct.unpack("!H", take(2))[0] if n7 == 126 else struct.unpack("!Q", take(8))[0]
        payload = take(size)
        msg = json.loads(payload) if payload[:1] == b"{" else {}
        if msg.get("op") == "advertise":
            subs = [{"id": 1 + k, "channelId": c["id"]} for k, c in enumerate(msg["channels"])]
            s.sendall(frame(json.dumps({"op": "subscribe", "subscriptions": subs}).encode()))
            return s
held = []
for line in sys.stdin:
    if line.strip() == "open":
        held = [silent() for _ in range(n)]
        print("open", len(held), flush=True)
    elif line.strip() == "close":
        for s in held:
            s.close()
        held = []
        print("closed", flush=True)
"""


def bench_foxglove(print_fn: Callable[[str], None] = print, seconds: float = 4.0) -> dict[str, float]:
    """Loop rate alone and served to a subscribed Foxglove client, the CPU added per tick, then
    the loop's rate and skipped ticks with 300 silent clients against without (medians of turns)."""
    from app.live.config import DEFAULT_CONFIG, load_service_config
    from app.live.loop import ServiceLoop
    from app.backends.world import Backends
    from app.params import MAX_FOLLOWERS, Params, ParamsStore, default_slots
    from app.services.foxglove_process import FoxgloveProcess

    config = load_service_config(DEFAULT_CONFIG, MAX_FOLLOWERS)  # what `make run` serves: vision in the loop
    store = ParamsStore(Params(n_followers=3, slots=default_slots(3), leader_mode="circle"))
    loop = ServiceLoop(store, Backends(camera=config.camera(), dynamics=config.dynamics), rate_hz=30.0)
    thread = threading.Thread(target=loop.run, name="bench-loop", daemon=True)
    thread.start()

    def measure() -> tuple[float, float, int]:
        t0, c0, k0, d0 = time.monotonic(), time.process_time(), loop.tick_count, loop.ticks_dropped
        time.sleep(seconds)
        ticks = max(1, loop.tick_count - k0)
        return ticks / (time.monotonic() - t0), (time.process_time() - c0) / ticks, loop.ticks_dropped - d0

    live = FoxgloveProcess("127.0.0.1", 0, params=store.get(), rate_hz=loop.rate_hz)
    feeding = [False]  # A/B rounds: the loop's states handed to Foxglove, or not (the client stays subscribed)
    loop.subscribe(lambda s: live.on_tick(s) if feeding[0] else None)
    client = silent = None
    rounds: dict[bool, list[tuple[float, float, int]]] = {False: [], True: []}
    quiet: dict[bool, list[tuple[float, float, int]]] = {False: [], True: []}
    try:
        deadline = time.monotonic() + 120.0
        while loop.tick_count < 60 and time.monotonic() < deadline:  # past the first ticks, which load compiled code
            time.sleep(0.1)
        client = subprocess.Popen([sys.executable, "-c", _CLIENT, live.url], stdin=subprocess.PIPE,
                                  stdout=subprocess.PIPE, text=True)
        feeding[0] = True
        ready = client.stdout.readline() if client.stdout else ""
        if "ready" not in ready:
            raise RuntimeError(f"the Foxglove client did not receive data: {ready.strip()!r}")
        for k in range(2 * ROUNDS):  # alternating, so a neighbour's load falls on both alike
            feeding[0] = k % 2 == 1
            time.sleep(0.3)
            rounds[feeding[0]].append(measure())
        if client.stdin:
            client.stdin.close()
        frames = int((client.stdout.readline() if client.stdout else "0").strip() or 0)
        client.wait(30)
        feeding[0] = True  # served from here on; the silent clients come and go by turns
        silent = subprocess.Popen([sys.executable, "-c", _SILENT, "127.0.0.1", str(live.port), str(SILENT)],
                                  stdin=subprocess.PIPE, stdout=subprocess.PIPE, text=True)
        assert silent.stdin is not None and silent.stdout is not None
        for k in range(2 * ROUNDS):
            with_them = k % 2 == 0
            silent.stdin.write("open\n" if with_them else "close\n")
            silent.stdin.flush()
            said = silent.stdout.readline()
            if with_them and said.strip() != f"open {SILENT}":
                raise RuntimeError(f"the silent clients did not connect: {said.strip()!r}")
            time.sleep(1.0)  # their sockets fill
            quiet[with_them].append(measure())
        silent.stdin.close()
        silent.wait(30)
    finally:
        loop.stop()
        thread.join(30.0)
        for proc in (client, silent):
            if proc is not None and proc.poll() is None:
                proc.kill()
        live.close()

    def med(rs: list[tuple[float, float, int]], i: int) -> float:
        return float(np.median([r[i] for r in rs]))

    alone_hz, alone_cpu, served_hz, served_cpu = med(rounds[False], 0), med(rounds[False], 1), med(rounds[True], 0), \
        med(rounds[True], 1)
    added_ms = (served_cpu - alone_cpu) * 1e3
    print_fn(f"Foxglove live (run --foxglove), a client subscribed to every channel: loop {served_hz:.2f} Hz, {alone_hz:.2f}"
             f" Hz without ({(served_hz / alone_hz - 1) * 100:+.1f} %, target within 1 %); CPU added {added_ms:.2f} ms per"
             f" tick in the loop's process ({alone_cpu * 1e3:.2f} -> {served_cpu * 1e3:.2f} ms); {live.sent} states sent"
             f" to the Foxglove process, {live.skipped} skipped there, the client got {frames} messages; median of"
             f" {ROUNDS} rounds of {seconds:g} s each, alternating")
    with_hz, without_hz = med(quiet[True], 0), med(quiet[False], 0)
    skipped_with = sum(r[2] for r in quiet[True])
    skipped_without = sum(r[2] for r in quiet[False])
    ratio = with_hz / without_hz
    print_fn(f"Foxglove live, {SILENT} clients that subscribe and never read: loop {with_hz:.2f} Hz, {without_hz:.2f} Hz"
             f" without them (ratio {ratio:.4f}, {(ratio - 1) * 100:+.2f} %, target within 1 %); ticks skipped"
             f" {skipped_with} with them, {skipped_without} without (target 0); {ROUNDS} turns of {seconds:g} s each way,"
             f" alternating, medians")
    return {"foxglove_loop_hz": served_hz, "foxglove_loop_hz_without": alone_hz, "foxglove_cpu_ms_per_tick": added_ms,
            "foxglove_silent_loop_hz": with_hz, "foxglove_silent_loop_hz_without": without_hz,
            "foxglove_silent_ratio": ratio, "foxglove_silent_ticks_skipped": float(skipped_with)}


def run_family(print_fn: Callable[[str], None] = print) -> dict[str, float]:
    """Foxglove live's cost (docs/foxglove.md)."""
    return bench_foxglove(print_fn)


FAMILY = Family('foxglove', run_family, 'what Foxglove live costs the loop (docs/foxglove.md)',
                default=True, order=40)


if __name__ == "__main__":
    bench_foxglove()
