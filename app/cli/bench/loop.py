"""`omniformation bench`'s loop figures: what the page and its clients cost the robots' loop.

A live service as `make run` serves it (vision in the loop, 30 Hz) is measured alone, during a
flood of refused updates from one raw websocket client and while 200 websockets stay open (each
party a process of its own, speaking viser's protocol as docs/page-access.md describes it). During
the flood a second client, from another loopback address, presses STOP and times the click until
its page says STOPPED. The loop's own CPU time per tick is read from its thread's counters
(/proc), so the page's work is not counted. These are the figures the loop's own process is to
improve; the frame-to-command latency with one browser attached is `bench --latency`'s.

`bench` measures two sides by turns, since the machine is shared and its load moves: before (the
page in the loop's process: `run --one-process`, what `run` was) and `run` now (the loop in a
process of its own). Each figure is given per side (the median of its turns) and as the ratio of
now to before. The browser renders on this machine's idle CPU, as if on the operator's own
machine (app.cli.bench.browsers.VIEWER); the latency is also given as `run --reserve-cpu` serves,
with the browser kept off the loop's CPU (app.realtime.CpuReservation says why), and with the
browser's session an equal of the service's, as a browser beside the service on one desktop is.
The flood and the 200 websockets last FLOOD_S in every turn, as the 1 % target is stated
(`python -m app.cli.bench.loop`: one side alone).
"""

from __future__ import annotations

import socket
import subprocess
import sys
import time
from collections.abc import Callable
from typing import Any

from app.cli.bench.floods import FLOODER  # one hostile party for both benches
from app.cli.bench.family import Family

FLOOD_S = 20.0
TURNS = 2
STOP_WITHIN_S = 0.5  # the target: STOP seen as STOPPED this soon after the click, during a flood
FLOODER_ADDRESS = "127.0.0.50"  # the flooder's own loopback address (its refusal is its own)



def _thread_cpu_s(native_id: int) -> float:
    """CPU seconds (user + system) one thread of this process has used."""
    from app.processes import read_stat

    return read_stat(f"/proc/self/task/{native_id}/stat")[1]


def _frames(ws: Any, until: float) -> Any:
    """The messages viser sends a client, decoded, until ``until`` (monotonic seconds)."""
    import msgspec
    import zstandard

    while time.monotonic() < until:
        frame = ws.recv(timeout=max(0.05, until - time.monotonic()))
        if isinstance(frame, bytes) and len(frame) >= 16:
            inner, packed = int.from_bytes(frame[:8], "little"), int.from_bytes(frame[8:16], "little")
            body = msgspec.msgpack.decode(zstandard.ZstdDecompressor().decompress(frame[16:16 + packed],
                                                                                   max_output_size=inner))
            yield from body.get("messages", [])


def _connect(port: int, source: str, timeout: float) -> Any:
    import viser
    import websockets.sync.client as wsc
    from websockets.typing import Subprotocol

    sock = socket.create_connection(("127.0.0.1", port), timeout=timeout, source_address=(source, 0))
    return wsc.connect(f"ws://127.0.0.1:{port}/", sock=sock, subprotocols=[Subprotocol(f"viser-v{viser.__version__}")],
                       additional_headers={"Origin": f"http://127.0.0.1:{port}"}, open_timeout=timeout, max_queue=None)


def control_ids(port: int, labels: tuple[str, ...], timeout: float = 30.0) -> dict[str, str]:
    """The ids of the page's controls with these labels, as a client learns them (the page may be
    served by another process)."""
    found: dict[str, str] = {}
    with _connect(port, "127.0.0.62", timeout) as ws:
        for msg in _frames(ws, time.monotonic() + timeout):
            label = (msg.get("props") or {}).get("label") if isinstance(msg.get("props"), dict) else None
            if label in labels and "uuid" in msg:
                found[label] = msg["uuid"]
                if len(found) == len(labels):
                    break
    return found


def press_stop(port: int, stop_id: str, timeout: float = 10.0) -> float | None:
    """A second client (its own loopback address) opens the page, presses STOP and waits for the
    status to say STOPPED; seconds from the click (None: not within ``timeout``)."""
    import msgspec

    try:
        with _connect(port, "127.0.0.61", timeout) as ws:
            for msg in _frames(ws, time.monotonic() + timeout):  # the page is loaded once STOP is among its controls
                if msg.get("uuid") == stop_id:
                    break
            camera = {"type": "ViewerCameraMessage", "wxyz": [1.0, 0.0, 0.0, 0.0], "position": [0.0, -3.0, 2.0],
                      "fov": 1.0, "near": 0.01, "far": 100.0, "image_height": 720, "image_width": 1280,
                      "look_at": [0.0, 0.0, 0.0], "up_direction": [0.0, 0.0, 1.0]}
            ws.send(msgspec.msgpack.encode(camera))  # viser takes a page's clicks once it has its camera
            click = time.monotonic()
            ws.send(msgspec.msgpack.encode({"type": "GuiUpdateMessage", "uuid": stop_id, "updates": {"value": True}}))
            for msg in _frames(ws, click + timeout):
                if "STOPPED" in str(msg):
                    return time.monotonic() - click
    except Exception:  # noqa: BLE001 - refused, timed out, closed: it did not see STOPPED
        return None
    return None


def bench_loop(print_fn: Callable[[str], None] = print, seconds: float = FLOOD_S,
               page_process: bool = False) -> dict[str, float]:
    """The loop's rate and CPU per tick alone, during a flood (and a second client's STOP), and with
    200 open websockets. ``page_process``: as `run` serves now, the page in a process of its own;
    False: in the loop's process (`run --one-process`, before)."""
    results: dict[str, float] = {}
    from app.live.config import DEFAULT_CONFIG, load_service_config
    from app.params import MAX_FOLLOWERS
    from app.services.live import Service

    config = load_service_config(DEFAULT_CONFIG, MAX_FOLLOWERS)  # what `make run` serves: vision in the loop
    svc = Service(host="127.0.0.1", port=0, n_followers=3, rate_hz=30.0, camera=config.camera(),
                  dynamics=config.dynamics, page_process=page_process)
    svc.start()
    port = svc.page.port if svc.page is not None else svc.gate.port
    ids = control_ids(port, ("STOP", "Speed (m/s)"))
    stop_id, speed_id = ids["STOP"], ids["Speed (m/s)"]  # a slider: the flood's values are out of its bounds
    where = "the page in its own process" if page_process else "the page in the loop's process"
    try:
        while svc.loop.tick_count < 60 and not svc.loop.stopping:  # past the warm-up and the first ticks
            time.sleep(0.2)
        thread = svc._thread  # the service's own loop thread, read for its CPU counters
        assert thread is not None and thread.native_id is not None
        tid = thread.native_id

        def window(span: float, during: Callable[[], None] | None = None) -> tuple[float, float, float]:
            tick0, cpu0, proc0, t0 = svc.loop.tick_count, _thread_cpu_s(tid), time.process_time(), time.monotonic()
            if during is not None:
                during()
            time.sleep(max(0.0, span - (time.monotonic() - t0)))
            ticks, cpu = svc.loop.tick_count - tick0, _thread_cpu_s(tid) - cpu0
            per_tick = max(ticks, 1) / 1e3
            return ticks / (time.monotonic() - t0), cpu / per_tick, (time.process_time() - proc0) / per_tick

        alone_hz, alone_ms, alone_proc = window(5.0)
        results["loop_hz_alone"], results["loop_cpu_ms_per_tick"] = alone_hz, alone_ms
        results["loop_process_cpu_ms_per_tick"] = alone_proc
        print_fn(f"loop alone ({where}; vision in the loop, 30 Hz, no client): {alone_hz:.2f} Hz, loop thread"
                 f" {alone_ms:.2f} ms CPU per tick, its process {alone_proc:.2f} ms")
        for mode in ("refused", "sockets"):
            flooder = subprocess.Popen([sys.executable, "-c", FLOODER, str(port), mode, str(seconds), FLOODER_ADDRESS, speed_id],
                                       stdout=subprocess.PIPE, stderr=subprocess.DEVNULL, text=True)
            assert flooder.stdout is not None
            flooder.stdout.readline()  # "ready"
            seen: list[float | None] = []

            def stop_during(seen: list[float | None] = seen) -> None:
                time.sleep(seconds / 2)
                seen.append(press_stop(port, stop_id))

            hz, ms, proc_ms = window(seconds, stop_during if mode == "refused" else None)
            flooder.wait(timeout=60)
            svc.store.update("bench", stop=False)  # released for the next window
            what = "a flood of refused updates from one client" if mode == "refused" else "200 open websockets"
            results[f"loop_hz_{mode}"], results[f"loop_cpu_ms_per_tick_{mode}"] = hz, ms
            results[f"loop_hz_{mode}_pct"] = (hz / alone_hz - 1) * 100 if alone_hz else float("nan")
            extra = ""
            if mode == "refused":
                took = seen[0] if seen else None
                results["stop_seen_s_during_flood"] = took if took is not None else float("inf")
                extra = (f"; a second client's STOP seen as STOPPED {took:.2f} s after the click" if took is not None
                         else "; a second client's STOP NOT seen as STOPPED within 10 s") \
                    + f" (target <= {STOP_WITHIN_S} s)"
            print_fn(f"loop during {seconds:g} s of {what}: {hz:.2f} Hz ({(hz / alone_hz - 1) * 100:+.1f} % of"
                     f" {alone_hz:.2f} alone; target within 1 %), loop thread {ms:.2f} ms CPU per tick, its process"
                     f" {proc_ms:.2f} ms{extra}")
    finally:
        svc.close()
    return results


# before: the page in the loop's process (`run --one-process`, what `run` was); now: `run`'s default
SIDES = (("before (one process)", False), ("run now (the loop's own process)", True))
# (figure, what it is, better when higher): the lines `bench` prints per side and as a ratio
SUMMARY = (("frame_to_command_p50_ms", "frame-to-command p50 (ms, one browser)", False),
           ("frame_to_command_p99_ms", "frame-to-command p99 (ms, one browser; target <= 5)", False),
           ("frame_to_command_p99_kept_ms", "  the same, run --reserve-cpu and the browser off the loop's CPU", False),
           ("frame_to_command_p99_equal_ms", "  the same, the browser's session an equal of the service's (one desktop)",
            False),
           ("loop_hz_alone", "loop rate alone (Hz)", True),
           ("loop_hz_refused_pct", "loop rate during a flood (% of alone; target within 1 %)", True),
           ("loop_hz_sockets_pct", "loop rate with 200 open websockets (% of alone; target within 1 %)", True),
           ("stop_seen_s_during_flood", "a second client's STOP seen as STOPPED during the flood (s; target <= 0.5)",
            False),
           ("loop_process_cpu_ms_per_tick", "the loop's process CPU per tick (ms, no client)", False))


def bench_loops(print_fn: Callable[[str], None] = print,
                latency: Callable[..., dict[str, float]] | None = None, turns: int = TURNS,
                seconds: float = FLOOD_S) -> dict[str, float]:
    """The figures before (the page in the loop's process) and as `run` serves now (the loop in a
    process of its own), measured by turns (each side ``turns`` times, alternately); given ``latency`` (`bench
    --latency`'s), first frame-to-command latency for 10 s with one browser attached, by turns too.
    Each side's figure is the median of its turns; the ratio is now over before."""
    import statistics

    runs: dict[bool, list[dict[str, float]]] = {False: [], True: []}
    for turn in range(turns):
        for name, page_process in SIDES:
            print_fn(f"loop, turn {turn + 1} of {turns}: {name}")
            figures: dict[str, float] = {}
            if latency is not None:
                lat = latency(10.0, print_fn, browsers=1, page_process=page_process)
                figures["frame_to_command_p50_ms"], figures["frame_to_command_p99_ms"] = lat["p50_ms"], lat["p99_ms"]
                lat = latency(10.0, print_fn, browsers=1, page_process=page_process, reserve_cpu=True)
                figures["frame_to_command_p99_kept_ms"] = lat["p99_ms"]
                lat = latency(10.0, print_fn, browsers=1, page_process=page_process, idle_browser=False)
                figures["frame_to_command_p99_equal_ms"] = lat["p99_ms"]
            figures.update(bench_loop(print_fn, seconds=seconds, page_process=page_process))
            runs[page_process].append(figures)
    results: dict[str, float] = {}
    print_fn(f"loop by turns ({turns} a side, alternately; floods of {seconds:g} s): before | run now |"
             " ratio")
    for key, what, _higher in SUMMARY:
        one = [r[key] for r in runs[False] if key in r]
        own = [r[key] for r in runs[True] if key in r]
        if not one or not own:
            continue
        a, b = statistics.median(one), statistics.median(own)
        results[key], results[f"page_process_{key}"] = a, b
        ratio = f"x{b / a:.2f}" if a and abs(a) != float("inf") and not key.endswith("_pct") else "-"
        print_fn(f"  {what}: {a:.2f} | {b:.2f} | {ratio}")
    return results


def run_family(print_fn: Callable[[str], None] = print) -> dict[str, float]:
    """The page's clients against the loop, the page in and out of its process, latency included."""
    from app.cli.bench.latency import bench_latency

    return bench_loops(print_fn, latency=bench_latency)


FAMILY = Family('loop', run_family, "the page's clients against the loop, the page in and out of its process, by turns",
                default=False, order=60)


if __name__ == "__main__":  # `python -m app.cli.bench.loop [--one-process]`: these figures alone
    bench_loop(page_process="--one-process" not in sys.argv)
