"""The fleet: state latency on the bus, the arena's step, how many leader processes hold 30 Hz."""

from __future__ import annotations

import json
import math
from collections.abc import Callable
from typing import Any

import numpy as np

from app.processes import interrupt


def bench_fleet_latency(seconds: float = 15.0, feedback: str = "vision", keyed: bool = False) -> tuple[float, float, int]:
    """(median ms, p99 ms, states) from a leader process publishing its state (`run --fleet`, vision
    in the loop, 30 Hz) to the fleet page's subscriber (FleetView) in this process, on loopback;
    ``keyed``: both with the fleet's keys (mutual TLS and access control, fresh keys made here)."""
    import subprocess
    import sys
    import tempfile
    import time as _time
    from pathlib import Path

    from app.dashboard.gate import quietly, serve_gated
    from app.fleet.bridge import loopback_endpoint, open_session
    from app.fleet.security import load_fleet_keys, make_fleet_keys
    from app.realtime import SWITCH_INTERVAL_S
    from app.services.fleet_page import FleetView

    endpoint = loopback_endpoint()
    tmp = tempfile.TemporaryDirectory(prefix="omniformation-keys-") if keyed else None
    keys_args: list[str] = []
    page_keys = None
    if tmp is not None:
        make_fleet_keys(Path(tmp.name), "bench", ("L1",))
        endpoint = "tls/" + endpoint.split("/", 1)[1]
        keys_args = ["--keys", str(Path(tmp.name) / "L1")]  # each identity its own bundle
        page_keys = load_fleet_keys(Path(tmp.name) / "page", "page", "bench")
    page_session = open_session([endpoint], [], page_keys)
    server, gate = serve_gated("127.0.0.1", 0)
    switch = sys.getswitchinterval()
    sys.setswitchinterval(SWITCH_INTERVAL_S)  # as `omniformation fleet` runs the page
    view = FleetView(server, page_session, "bench")
    leader = subprocess.Popen([sys.executable, "-m", "app.cli", "run", "--port", "0", "--no-record", "--fleet", "bench",
                               "--leader-id", "L1", "--zenoh-connect", endpoint, "--feedback", feedback, *keys_args],
                              stdout=subprocess.DEVNULL, stderr=subprocess.DEVNULL)
    try:
        deadline = _time.monotonic() + 120
        while view.received < 60 and _time.monotonic() < deadline:  # past its start-up
            _time.sleep(0.2)
        view.latencies.clear()
        _time.sleep(seconds)
        lat = np.array(list(view.latencies)) * 1e3
    finally:
        interrupt(leader)
        view.close()
        gate.close()
        quietly(server.stop)
        page_session.close()
        sys.setswitchinterval(switch)
        if tmp is not None:
            tmp.cleanup()
    if lat.size == 0:
        return float("nan"), float("nan"), 0
    return float(np.median(lat)), float(np.percentile(lat, 99)), int(lat.size)


def bench_arena_tick(leaders: int, followers: int, ticks: int = 300) -> float:
    """Median ms of one arena step (every robot's dynamics, the truth built and published) for
    ``leaders`` x ``followers`` (built directly: more robots than one fleet's hues allow)."""
    import dataclasses
    import time as _time

    from app.fleet.arena import Arena
    from app.fleet.bridge import open_session
    from core.fleet import FleetLeader, FleetScenario
    from core.sim.team import FollowerDynamics

    sc = FleetScenario("bench", "", tuple(FleetLeader(f"L{i + 1}", (3.0 * i, 0.0, math.pi / 2), followers, "straight",
                                                      0.03, 0.0, tuple([0.0] * followers)) for i in range(leaders)),
                       30.0, FollowerDynamics(actuator_tau_s=0.3, speed_max_mps=0.35, turn_max_rps=2.5))
    session = open_session([], [])
    arena = Arena(sc, session, "bench")
    try:
        times = []
        for _ in range(ticks):
            for a, f in arena.robots.followers.items():  # every robot commanded this tick
                arena.robots.followers[a] = dataclasses.replace(f, target_l_mps=0.044, target_r_mps=0.056,
                                                                command_age_s=0.0)
            t0 = _time.perf_counter()
            arena.step()
            times.append(_time.perf_counter() - t0)
    finally:
        arena.close()
        session.close()
    return float(np.median(times[20:]) * 1e3)


# teams of 3 per fleet in the bench: every robot of a fleet wears its own hue, at least
# MIN_HUE_SEPARATION_DEG (core.camera.config) from the next, so a fleet holds 360 / that / 3 teams at most
# (tests/app/cli/test_bench_fleet.py parses bench_fleet_file(FLEET_TEAMS) as `arena` does)
FLEET_TEAMS = 8


def bench_fleet_file(teams: int, name: str = "bench") -> str:
    """The fleet file of the leader bench: ``teams`` leaders of 3 followers side by side, 2.2 m
    apart, driving straight on slowly (every robot's hue spread fleet-wide by core.fleet)."""
    leaders = "".join(f'[[leaders]]\nid = "L{k + 1}"\nstart = [{2.2 * k:.1f}, 0.0]\nheading_deg = 90\nfollowers = 3\n'
                      f'mode = "straight"\nspeed_mps = 0.03\n' for k in range(teams))
    return f'name = "{name}"\nrate_hz = 30\n' + leaders


def bench_leader_processes(max_processes: int = 24, seconds: float = 12.0,
                           extra: tuple[str, ...] = ()) -> tuple[int, list[float], list[tuple[float, float]]]:
    """Start arenas for ``max_processes`` teams of 3 (side by side, every robot in its fleet-wide
    hue; fleets of FLEET_TEAMS teams, each its own arena on its own loopback bus, as two fleets on
    one machine are), then leader processes one more at a time, the fleets in turn (`run --arena`,
    each rendering its camera from its arena with the other teams in view, the vision pipeline in
    the loop, its page served, no browser) and read every one's loop rate from the buses; how many
    run at once with every loop within 1 % of 30 Hz, and the slowest rate at each count. The arenas
    step every team, joined or not, all along. ``extra``: more `run` arguments (``--one-process``:
    each leader's page in its loop's process, as `run` was before its loop had a process of its own).
    And at each count, what the machine's CPU went to over the window (app.processes.cpu_seconds):
    (% of one CPU per leader, its process and its page's; % the arenas took together)."""
    import subprocess
    import sys
    import tempfile
    import threading
    import time as _time
    from pathlib import Path

    from app.fleet.bridge import loopback_endpoint, open_session
    from app.keys import root
    from app.processes import cpu_seconds

    n_fleets = -(-max_processes // FLEET_TEAMS)
    tmp = tempfile.TemporaryDirectory(prefix="omniformation-bench-")
    teams = -(-max_processes // n_fleets)  # per fleet: the leaders spread evenly
    fleets: list[tuple[Path, str]] = []  # (fleet file, its bus)
    for f in range(n_fleets):
        path = Path(tmp.name) / f"bench{f}.toml"
        path.write_text(bench_fleet_file(teams, f"bench{f}"))
        fleets.append((path, loopback_endpoint()))
    session = open_session([], [bus for _, bus in fleets])
    rates: dict[str, list[tuple[float, float]]] = {}
    lock = threading.Lock()

    def on_state(sample: Any) -> None:
        msg = json.loads(sample.payload.to_bytes())
        who = f"{str(sample.key_expr).split('/')[1]}/{msg['leader_id']}"  # its fleet's and its own name
        with lock:
            rates.setdefault(who, []).append((_time.monotonic(), float(msg.get("rate_hz") or 0.0)))

    sub = session.declare_subscriber(f"{root('*')}/leader/*/state", on_state)
    arenas = [subprocess.Popen([sys.executable, "-m", "app.cli", "arena", str(path), "--zenoh-listen", bus,
                                "--status-every", "0"], stdout=subprocess.DEVNULL, stderr=subprocess.DEVNULL)
              for path, bus in fleets]
    procs: list[subprocess.Popen[bytes]] = []
    slowest: list[float] = []
    cpu: list[tuple[float, float]] = []
    held = 0
    try:
        for k in range(1, max_processes + 1):
            path, bus = fleets[(k - 1) % n_fleets]
            procs.append(subprocess.Popen([sys.executable, "-m", "app.cli", "run", "--port", "0", "--no-record",
                                           "--arena", str(path), "--leader-id", f"L{(k - 1) // n_fleets + 1}",
                                           "--feedback", "vision", "--zenoh-connect", bus, *extra],
                                          stdout=subprocess.DEVNULL, stderr=subprocess.DEVNULL))
            deadline = _time.monotonic() + 120
            while _time.monotonic() < deadline:  # every leader past its start-up (compiling, first frames)
                with lock:
                    ready = len(rates) == k and all(len(v) > 150 for v in rates.values())
                if ready:
                    break
                _time.sleep(0.5)
            pids = [p.pid for p in procs + arenas]
            t0, used0 = _time.monotonic(), cpu_seconds(pids)
            _time.sleep(seconds)
            used1, elapsed = cpu_seconds(pids), _time.monotonic() - t0
            with lock:
                window = [min(r for t, r in v if t >= t0) for v in rates.values() if any(t >= t0 for t, _ in v)]
            low = min(window) if len(window) == k else 0.0
            slowest.append(low)
            share = {pid: max(0.0, used1[pid] - used0[pid]) / elapsed * 100 for pid in pids}  # 0: one that ended
            cpu.append((sum(share[p.pid] for p in procs) / k, sum(share[p.pid] for p in arenas)))
            if low < 29.7:
                break
            held = k
    finally:
        interrupt(*procs)
        interrupt(*arenas)
        sub.undeclare()
        session.close()
        tmp.cleanup()
    return held, slowest, cpu


def run_family(print_fn: Callable[[str], None] = print) -> dict[str, float]:
    """The fleet's figures (skipped without eclipse-zenoh)."""
    try:
        import zenoh  # noqa: F401
    except ImportError:
        print_fn("fleet: skipped (needs eclipse-zenoh: make test installs it)")
        return {}
    results: dict[str, float] = {}
    for keyed in (False, True):
        p50, p99, samples = bench_fleet_latency(keyed=keyed)
        results["fleet_state_latency_p99_ms" + ("_keys" if keyed else "")] = p99
        how = "with --keys (mutual TLS, access control)" if keyed else "open (tcp, no keys)"
        print_fn(f"fleet: a leader's state to the fleet page on loopback, {how}: median {p50:.2f} ms, p99 {p99:.2f} ms"
                 f" over {samples} states (target p99 <= 5 ms)")
    tick_ms = bench_arena_tick(10, 10)
    results["arena_tick_ms_10x10"] = tick_ms
    print_fn(f"fleet: arena step for 10 leaders x 10 followers (dynamics, truth, publish): {tick_ms:.2f} ms per tick"
             f" ({tick_ms / (1000 / 30) * 100:.0f} % of a 30 Hz tick)")
    for name, extra in (("before (run --one-process)", ("--one-process",)), ("run now (the loop's own process)", ())):
        held, slowest, cpu = bench_leader_processes(extra=extra)
        results["leader_processes_at_30hz" + ("_one_process" if extra else "")] = held
        at = max(held, 1)  # the CPU at the most it held (at one, where it held none)
        results["leader_cpu_percent" + ("_one_process" if extra else "")] = cpu[at - 1][0]
        print_fn(f"fleet: leader processes of 3 followers (vision in the loop, each camera rendered from its arena;"
                 f" fleets of {FLEET_TEAMS}, each its own arena and bus), {name}: this machine holds {held} at 30 Hz (within 1 %)"
                 f"{' (every one the bench starts: it may hold more)' if held == len(slowest) else ''}; slowest loop with"
                 f" 1..{len(slowest)} running: {', '.join(f'{r:.2f}' for r in slowest)} Hz; with {at} running, each"
                 f" leader (its process and its page) took {cpu[at - 1][0]:.1f} % of one CPU, the arenas"
                 f" {cpu[at - 1][1]:.1f} % together")
    return results
