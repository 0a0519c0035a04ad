"""`omniformation bench`'s floods: what one hostile client costs the live loop (docs/page-access.md).

A live service as `make run` serves it (vision in the loop) is flooded by a client in a process of
its own (so the flooder's work is not counted as the service's): refused updates, valid slider
updates, scene messages that mean nothing, and 200 open websockets. During each flood it prints the
loop's rate, the service's resident memory and threads, and the time a new client (another
address) takes to load the page and receive its STOP control. The flooder speaks viser's protocol
from the docs alone and reconnects whenever it is closed or refused, as a hostile one would.
"""

from __future__ import annotations

import http.client
import socket
import subprocess
import sys
import threading
import time
from collections.abc import Callable
from typing import Any

from app.cli.bench.family import Family

FLOOD_S = 10.0  # how long each flood lasts (the rate is measured over it)
SEE_STOP_S = 30.0  # a new client that has not seen STOP by then is reported as "> 30 s"
NEWCOMER_ADDRESS = "127.0.0.60"  # loopback: each party an address of its own (a flooder's refusal is its own)
MODES = ("none", "refused", "valid", "scene", "sockets")

# The hostile party: argv = port, mode, seconds, source address, the speed slider's id.
FLOODER = r"""
import os, socket, sys, time
os.sched_setaffinity(0, range(os.cpu_count() or 1))  # every CPU, as a client elsewhere has (not the bench's)
import msgspec, viser
import websockets.exceptions
import websockets.sync.client as wsc

port, mode, seconds, source, speed = int(sys.argv[1]), sys.argv[2], float(sys.argv[3]), sys.argv[4], sys.argv[5]
sub = [f"viser-v{viser.__version__}"]

def connect():
    sock = socket.create_connection(("127.0.0.1", port), timeout=10, source_address=(source, 0))
    return wsc.connect(f"ws://127.0.0.1:{port}/", sock=sock, subprotocols=sub, open_timeout=10, max_queue=None,
                       additional_headers={"Origin": f"http://127.0.0.1:{port}"})

camera = {"type": "ViewerCameraMessage", "wxyz": [1.0, 0.0, 0.0, 0.0], "position": [0.0, -3.0, 2.0], "fov": 1.0,
          "near": 0.01, "far": 100.0, "image_height": 720, "image_width": 1280, "look_at": [0.0, 0.0, 0.0],
          "up_direction": [0.0, 0.0, 1.0]}
if mode == "refused":
    payloads = [msgspec.msgpack.encode({"type": "GuiUpdateMessage", "uuid": speed, "updates": {"value": 1e9}})]
elif mode == "valid":
    payloads = [msgspec.msgpack.encode({"type": "GuiUpdateMessage", "uuid": speed, "updates": {"value": v}})
                for v in (0.05, 0.06)]
else:  # scene: a camera whose "up" is zero
    payloads = [msgspec.msgpack.encode(dict(camera, up_direction=[0.0, 0.0, 0.0]))]
end = time.monotonic() + seconds
sent = refused = held = 0
conns = []
print("ready", flush=True)
while time.monotonic() < end:
    try:
        if mode == "sockets":
            if len(conns) < 200:
                conns.append(connect())  # and never read: the server's frames pile up
                held = len(conns)
            else:
                time.sleep(0.1)
            continue
        conn = connect()
        conn.send(msgspec.msgpack.encode(camera))
        k = 0
        while time.monotonic() < end:
            conn.send(payloads[k % len(payloads)])
            k += 1
            sent += 1
    except (websockets.exceptions.InvalidHandshake, websockets.exceptions.ConnectionClosed, OSError, TimeoutError):
        refused += 1
        time.sleep(0.01)
print(f"sent {sent} refused {refused} held {held}", flush=True)
for c in conns:
    c.close()
"""


def _rss_mb() -> float:
    with open("/proc/self/status") as f:
        for line in f:
            if line.startswith("VmRSS:"):
                return int(line.split()[1]) / 1024.0
    return float("nan")


def _threads() -> int:
    with open("/proc/self/status") as f:
        for line in f:
            if line.startswith("Threads:"):
                return int(line.split()[1])
    return threading.active_count()


def time_to_see_stop(port: int, stop_id: str, source: str = NEWCOMER_ADDRESS,
                     timeout: float = SEE_STOP_S) -> float | None:
    """Seconds a new client takes to load the page and receive the STOP control (None: not within ``timeout``)."""
    import viser
    import websockets.sync.client as wsc
    import zstandard
    from websockets.typing import Subprotocol

    start = time.monotonic()
    try:
        http_conn = http.client.HTTPConnection("127.0.0.1", port, timeout=timeout, source_address=(source, 0))
        try:
            http_conn.request("GET", "/", headers={"Host": f"127.0.0.1:{port}"})
            page = http_conn.getresponse()
            page.read()
            if page.status != 200:
                return None
        finally:
            http_conn.close()
        sock = socket.create_connection(("127.0.0.1", port), timeout=timeout, source_address=(source, 0))
        with wsc.connect(f"ws://127.0.0.1:{port}/", sock=sock, subprotocols=[Subprotocol(f"viser-v{viser.__version__}")],
                         additional_headers={"Origin": f"http://127.0.0.1:{port}"}, open_timeout=timeout,
                         max_queue=None) as ws:
            want = stop_id.encode()
            while time.monotonic() - start < timeout:
                frame = ws.recv(timeout=max(0.1, timeout - (time.monotonic() - start)))
                if not isinstance(frame, bytes) or len(frame) < 16:
                    continue
                inner, packed = int.from_bytes(frame[:8], "little"), int.from_bytes(frame[8:16], "little")
                body = zstandard.ZstdDecompressor().decompress(frame[16:16 + packed], max_output_size=inner)
                if want in body:
                    return time.monotonic() - start
    except Exception:  # noqa: BLE001 - refused, timed out, closed: it did not see STOP
        return None
    return None


def _see_stop_into(seen: list[float | None], port: int, stop_id: str) -> None:
    seen.append(time_to_see_stop(port, stop_id))


def bench_floods(print_fn: Callable[[str], None] = print, seconds: float = FLOOD_S) -> dict[str, float]:
    """The loop's rate, memory, threads and a newcomer's time to see STOP, alone and during each flood."""
    from app.live.config import DEFAULT_CONFIG, load_service_config
    from app.params import MAX_FOLLOWERS
    from app.services.live import Service

    config = load_service_config(DEFAULT_CONFIG, MAX_FOLLOWERS)  # what `make run` serves: vision in the loop
    svc = Service(host="127.0.0.1", port=0, n_followers=3, rate_hz=30.0, camera=config.camera(),
                  dynamics=config.dynamics)
    svc.start()
    results: dict[str, float] = {}
    from app.dashboard import viser_private

    port = svc.gate.port
    stop_id = viser_private.uuid_of(svc.dashboard.controls.stop_button)
    speed_id = viser_private.uuid_of(svc.dashboard.controls.speed)
    print_fn(f"floods on the live page (vision in the loop, 30 Hz; each flood {seconds:g} s from one client"
             " in a process of its own; a new client from another address loads the page meanwhile):")
    try:
        start = time.monotonic()  # past the start-up (compiled code loads, the team is found): the loop's own pace
        while (svc.loop.last is None or svc.loop.last.phase != "tracking") and time.monotonic() - start < 300:
            time.sleep(0.2)
        time.sleep(2.0)
        for k, mode in enumerate(MODES):
            flooder: subprocess.Popen[str] | None = None
            if mode != "none":
                flooder = subprocess.Popen([sys.executable, "-c", FLOODER, str(port), mode, str(seconds + 2.0),
                                            f"127.0.0.{61 + k}", speed_id], stdout=subprocess.PIPE, text=True)
                assert flooder.stdout is not None
                flooder.stdout.readline()  # "ready"
                time.sleep(1.0)  # the flood is on
            rss0, threads0 = _rss_mb(), _threads()
            seen: list[float | None] = []
            newcomer = threading.Thread(target=_see_stop_into, args=(seen, port, stop_id), daemon=True)
            tick0, t0 = svc.loop.tick_count, time.monotonic()
            newcomer.start()
            time.sleep(seconds - 1.0 if mode != "none" else 4.0)
            hz = (svc.loop.tick_count - tick0) / (time.monotonic() - t0)
            rss, threads = _rss_mb(), _threads()
            newcomer.join(SEE_STOP_S)
            said = ""
            if flooder is not None:
                out, _ = flooder.communicate(timeout=60)
                said = out.strip().splitlines()[-1] if out.strip() else ""
            stop_s = seen[0] if seen else None
            results[f"flood_{mode}_loop_hz"] = hz
            results[f"flood_{mode}_see_stop_s"] = stop_s if stop_s is not None else float("inf")
            shown = f"{stop_s:.2f} s" if stop_s is not None else f"> {SEE_STOP_S:g} s"
            print_fn(f"  {mode:>7}: loop {hz:5.2f} Hz; RSS {rss:.0f} MB ({rss - rss0:+.0f}), threads {threads}"
                     f" ({threads - threads0:+d}); a new client sees STOP in {shown}"
                     + (f"; flooder: {said}" if said else "") + _counts(svc))
            time.sleep(2.0)  # the service settles before the next flood
    finally:
        svc.close()
    return results


def _counts(svc: Any) -> str:
    """What the gate counted (where it counts it)."""
    refused = svc.gate.refused
    names = ("messages", "flood", "cut", "banned", "full")
    return "; gate: " + ", ".join(f"{n} {getattr(refused, n)}" for n in names if hasattr(refused, n))


def run_family(print_fn: Callable[[str], None] = print) -> dict[str, float]:
    """The page under floods (docs/page-access.md)."""
    return bench_floods(print_fn)


FAMILY = Family('floods', run_family, 'what one hostile page client costs the loop (docs/page-access.md)',
                default=True, order=50)


if __name__ == "__main__":
    bench_floods()
