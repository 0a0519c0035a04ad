"""What Foxglove live costs the loop (a `make bench` line; alone:
``python -m app.cli.bench.foxglove``): the live loop's rate (vision in the loop, 3 followers,
30 Hz) with no Foxglove server, then with one and a client subscribed to every channel, and the
process CPU each tick costs more with it (the adapter's thread and the SDK's server threads).

The client runs in a process of its own (a viewer is on another machine in practice), written
from Foxglove's WebSocket protocol spec: subscribe to every advertised channel, count frames."""

from __future__ import annotations

import subprocess
import sys
import threading
import time
from collections.abc import Callable

import numpy as np

from app.cli.bench.family import Family

ROUNDS = 3

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


def bench_foxglove(print_fn: Callable[[str], None] = print, seconds: float = 4.0) -> dict[str, float]:
    """Loop rate alone and served to a subscribed Foxglove client, and the CPU added per tick (medians)."""
    from app.live.config import DEFAULT_CONFIG, load_service_config
    from app.live.loop import ServiceLoop
    from app.backends.world import Backends
    from app.params import MAX_FOLLOWERS, Params, ParamsStore, default_slots
    from app.services.foxglove_live import FoxgloveLive

    config = load_service_config(DEFAULT_CONFIG, MAX_FOLLOWERS)  # what `make run` serves: vision in the loop
    store = ParamsStore(Params(n_followers=3, slots=default_slots(3), leader_mode="circle"))
    loop = ServiceLoop(store, Backends(camera=config.camera(), dynamics=config.dynamics), rate_hz=30.0)
    thread = threading.Thread(target=loop.run, name="bench-loop", daemon=True)
    thread.start()

    def measure() -> tuple[float, float]:
        t0, c0, k0 = time.monotonic(), time.process_time(), loop.tick_count
        time.sleep(seconds)
        ticks = max(1, loop.tick_count - k0)
        return ticks / (time.monotonic() - t0), (time.process_time() - c0) / ticks

    live = FoxgloveLive("127.0.0.1", 0, params=store.get())
    feeding = [False]  # A/B rounds: the loop's states handed to Foxglove, or not (the client stays subscribed)
    loop.subscribe(lambda s: live.on_tick(s) if feeding[0] else None)
    client = None
    rounds: dict[bool, list[tuple[float, float]]] = {False: [], True: []}
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
        feeding[0] = False
        served_ticks = live.ticks
        if client.stdin:
            client.stdin.close()
        frames = int((client.stdout.readline() if client.stdout else "0").strip() or 0)
        client.wait(30)
    finally:
        loop.stop()
        thread.join(30.0)
        if client is not None and client.poll() is None:
            client.kill()
        live.close()
    alone_hz, alone_cpu = (float(np.median([r[i] for r in rounds[False]])) for i in (0, 1))
    served_hz, served_cpu = (float(np.median([r[i] for r in rounds[True]])) for i in (0, 1))
    added_ms = (served_cpu - alone_cpu) * 1e3
    print_fn(f"Foxglove live (run --foxglove), a client subscribed to every channel: loop {served_hz:.2f} Hz, {alone_hz:.2f}"
             f" Hz without ({(served_hz / alone_hz - 1) * 100:+.1f} %, target within 1 %); CPU added {added_ms:.2f} ms per"
             f" tick ({alone_cpu * 1e3:.2f} -> {served_cpu * 1e3:.2f} ms); {served_ticks} ticks served, the client got"
             f" {frames} messages, {live.dropped} states dropped; median of {ROUNDS} rounds of {seconds:g} s each, alternating")
    return {"foxglove_loop_hz": served_hz, "foxglove_loop_hz_without": alone_hz, "foxglove_cpu_ms_per_tick": added_ms}


def run_family(print_fn: Callable[[str], None] = print) -> dict[str, float]:
    """Foxglove live's cost (docs/foxglove.md)."""
    return bench_foxglove(print_fn)


FAMILY = Family('foxglove', run_family, 'what Foxglove live costs the loop (docs/foxglove.md)',
                default=True, order=40)


if __name__ == "__main__":
    bench_foxglove()
