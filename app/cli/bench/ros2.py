"""The bench's ROS 2 line: the live loop's rate and CPU per tick without and with ``--ros2``
(every topic published and received by a subscriber, the camera at 10 Hz, the leader's base
on an emulated ROS 2 base). The router, the subscriber and the base are another process, as
they would be: the CPU counted is the service's own. ``python -m app.cli.bench.ros2`` prints
the line alone."""

from __future__ import annotations

import json
import math
import threading
import time
from collections.abc import Callable
from typing import Any
from app.cli.bench.family import Family


def _loop_rate(loop: Any, seconds: float) -> tuple[float, float]:
    """(ticks per second, process CPU ms per tick) of ``loop`` run for ``seconds`` after a warm-up."""
    for _ in range(3):
        loop.tick()  # compiled code loads (the first tick of a process takes seconds)
    thread = threading.Thread(target=loop.run, daemon=True)
    thread.start()
    time.sleep(2.0)  # the base's odometry flows
    k0, c0, t0 = loop.tick_count, time.process_time(), time.monotonic()
    time.sleep(seconds)
    k1, c1, t1 = loop.tick_count, time.process_time(), time.monotonic()
    loop.stop()
    thread.join(30)
    ticks = max(k1 - k0, 1)
    return ticks / (t1 - t0), (c1 - c0) / ticks * 1e3


def _make_loop(ros2: Any | None) -> Any:
    from app.files import DEFAULT_CONFIG
    from app.live.config import load_service_config
    from app.live.loop import ServiceLoop
    from app.backends.world import Backends
    from app.params import MAX_FOLLOWERS, Params, ParamsStore, default_slots

    config = load_service_config(DEFAULT_CONFIG, MAX_FOLLOWERS)
    store = ParamsStore(Params(n_followers=3, slots=default_slots(3), leader_mode="straight"))
    return store, ServiceLoop(store, Backends(seed=1, dynamics=config.dynamics, camera=config.camera(), leader=ros2),
                              rate_hz=30.0)


def bench_ros2(print_fn: Callable[[str], None] = print, seconds: float = 5.0, rounds: int = 3) -> dict[str, float]:
    """The loop at 30 Hz (vision in the loop, 3 followers) alone and as a ROS 2 node, in turns
    (``rounds`` of each, ``seconds`` long): the medians, so that a busy moment of a shared machine
    falls on one run, not on one side."""
    import statistics
    import subprocess
    import sys

    from app.backends.ros2 import Ros2Base, Ros2Node
    from app.fleet.bridge import loopback_endpoint
    from app.ros2.bridge import Ros2Bridge
    from app.ros2.session import open_ros2_session

    endpoint = loopback_endpoint()
    ros_side = subprocess.Popen([sys.executable, "-m", "app.cli.bench.ros2", "--serve", endpoint],
                                stdout=subprocess.PIPE, text=True)
    node = None
    alone: list[tuple[float, float]] = []
    ros: list[tuple[float, float]] = []
    published = 0
    try:
        assert ros_side.stdout is not None and ros_side.stdout.readline().strip() == "ready"
        node = Ros2Node(open_ros2_session([endpoint]), "omniformation")
        leader = Ros2Base(node)
        for _ in range(rounds):
            alone.append(_loop_rate(_make_loop(None)[1], seconds))
            store, loop = _make_loop(leader)
            bridge = Ros2Bridge(node, store, frames_hz=10.0)
            loop.subscribe(bridge.on_tick)
            ros.append(_loop_rate(loop, seconds))
            bridge.close()
            published += bridge.published
    finally:
        if node is not None:
            node.close()
            node.session.close()
        ros_side.terminate()
        ros_side.wait(30)
    alone_hz, alone_ms = (statistics.median(x) for x in zip(*alone))
    ros_hz, ros_ms = (statistics.median(x) for x in zip(*ros))
    change = (ros_hz / alone_hz - 1) * 100 if alone_hz > 0 else math.nan
    print_fn(f"live loop at 30 Hz (vision in the loop) as a ROS 2 node (--ros2 on a loopback router, every topic"
             f" subscribed, camera 10 Hz, --leader ros2:/cmd_vel on emulate-base at 50 Hz), median of {rounds} x"
             f" {seconds:g} s: {ros_hz:.2f} Hz ({change:+.1f} % of {alone_hz:.2f} Hz without; target within 1 %);"
             f" CPU {ros_ms:.2f} ms per tick vs {alone_ms:.2f} ms (+{ros_ms - alone_ms:.2f} ms); {published} states"
             " published")
    return {"loop_hz_ros2": ros_hz, "loop_hz_before_ros2": alone_hz, "ros2_cpu_ms_per_tick": ros_ms - alone_ms}


def serve_ros_side(endpoint: str) -> None:
    """The other process: a router at ``endpoint``, a subscriber to every ROS key, the base."""
    import signal

    import zenoh

    from app.backends.ros2 import Ros2Node
    from app.ros2.base import EmulatedBase
    from app.ros2.session import open_ros2_session

    router = zenoh.open(zenoh.Config.from_json5(json.dumps({
        "mode": "router", "listen": {"endpoints": [endpoint]},
        "scouting": {"multicast": {"enabled": False}, "gossip": {"enabled": False}}})))
    sub = router.declare_subscriber("0/**", lambda _s: None)  # everything is really sent
    node = Ros2Node(open_ros2_session([endpoint]), "base")
    base = EmulatedBase(node)
    base.start()
    done = threading.Event()
    signal.signal(signal.SIGTERM, lambda *_: done.set())
    print("ready", flush=True)
    done.wait()
    base.close()
    node.close()
    node.session.close()
    sub.undeclare()
    router.close()


def run_family(print_fn: Callable[[str], None] = print) -> dict[str, float]:
    """The loop's rate and CPU per tick with --ros2 (docs/ros2.md)."""
    return bench_ros2(print_fn)


FAMILY = Family('ros2', run_family, "the loop's rate and CPU per tick as a ROS 2 node (docs/ros2.md)",
                default=True, order=80)


if __name__ == "__main__":
    import sys

    if sys.argv[1:2] == ["--serve"]:
        serve_ros_side(sys.argv[2])
    else:
        bench_ros2()
