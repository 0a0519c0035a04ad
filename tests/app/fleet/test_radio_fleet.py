"""Orphans adopted on real robots' terms (docs/fleet-protocol.md, "Real robots"): three leaders
with vision, each on its own radio link (`arena --radio`: the arena is only the world; the
robots, running the followers' own rules, say who owns them). Leader L1's link goes through a
relay that delays, drops and cuts (this kernel has no netem).

Times are the arena's own (the ``t`` of its truth), so a loaded machine slows the world and the
clock together."""

from __future__ import annotations

import json
import math
import signal
import subprocess

import pytest

from app.fleet.bridge import loopback_endpoint

from tests.app.fleet.test_arena import Watcher, team_rms_m
from tests.helpers import LEADER_PROCESS, PtyRelay, interrupt, main_cli, spawn_cli, wait_for

zenoh = pytest.importorskip("zenoh")

FLEET = "three_teams"
LEASE_S = 1.0  # the lease a leader's radio link asks for (app.backends.serial_link.LEASE_MS)
WATCHDOG_BOUND_S = 0.5 + 1 / 30 + 1e-3  # the watchdog's 0.5 s, and the step in which a command ages past it


def _no_robot_moved_on_an_old_command(truths: list[dict]) -> None:
    for tr in truths:
        for r, age in enumerate(tr["command_age"]):
            assert tr["watchdog"][r] or age is None or age <= WATCHDOG_BOUND_S, (r, tr["t"], age)


def _cut_and_back(w: Watcher, relay: PtyRelay, seconds: float, owners: list[str]) -> None:
    """Cut L1's radio for ``seconds``: its robots stop by their own watchdog and their leases
    lapse, nobody takes them (L1 is alive on the bus), and L1 claims and drives them again when
    its radio is back; no robot moves on a command older than the watchdog allows."""
    mine = [r for r, o in enumerate(owners) if o == "L1"]
    with w.lock:
        k_cut = len(w.truths)
    relay.cut(seconds)
    wait_for(lambda: not relay.is_cut, seconds + 10, f"the {seconds:g} s cut healed")
    wait_for(lambda: all(w.last_truth()["leases"][r] > 0 and w.last_truth()["command_age"][r] < 0.2 for r in mine),
             30, "L1 driving its robots again")
    with w.lock:
        truths = w.truths[k_cut:]
    assert any(all(tr["leases"][r] == 0 and tr["watchdog"][r] for r in mine) for tr in truths), \
        "L1's robots stopped and their leases lapsed during the cut"
    assert all(tr["owners"] == owners for tr in truths), "nobody took L1's robots, nor any other"
    _no_robot_moved_on_an_old_command(truths)


def test_three_leaders_on_a_radio_adopt_a_killed_leaders_robots_and_ride_out_cuts(tmp_path):
    endpoint = loopback_endpoint()
    summary = tmp_path / "arena.json"
    keys = tmp_path / "keys"  # the fleet's radio key: the robots obey only L1..L3
    made = main_cli("fleet-keys", str(keys), "--fleet", "radio", "--leaders", "L1,L2,L3")
    assert made.returncode == 0, made.stderr
    arena = spawn_cli("arena", FLEET, "--radio", "--radio-drop", "0.02", "--radio-delay-ms", "5",  # a lossy, late medium
                   "--radio-key", str(keys / "radio" / "robots.json"),
                   "--zenoh-listen", endpoint, "--status-every", "0", "--summary", str(summary))
    procs: dict[str, subprocess.Popen] = {}
    relay = None
    watch = None
    try:
        assert arena.stdout is not None and "arena three_teams" in arena.stdout.readline()
        ptys = {}
        for _ in range(3):
            words = arena.stdout.readline().split()  # radio L1: /dev/pts/N (radio id 1)
            ptys[words[1].rstrip(":")] = words[2]
        relay = PtyRelay(ptys["L1"], delay_s=0.01, drop=0.02, seed=3)
        watch = Watcher(endpoint)
        for leader in ("L1", "L2", "L3"):
            port = relay.path if leader == "L1" else ptys[leader]
            procs[leader] = spawn_cli("run", LEADER_PROCESS, "--arena", FLEET, "--leader-id", leader, "--link", f"serial:{port}",
                                   "--radio-key", str(keys / "radio" / f"{leader}.radio"),
                                   "--zenoh-connect", endpoint, "--port", "0", "--no-record")
        w = watch
        wait_for(lambda: bool(w.truths) and w.last_truth()["alive"] == ["L1", "L2", "L3"], 60, "three leaders alive")
        # every team seen by its leader's camera, in formation while every leader moves
        wait_for(lambda: all(team_rms_m(w.recent(ld, 2.0)) <= 0.02 and w.recent(ld, 2.0)[-1]["leader_twist"][0] > 0.01
                             and w.recent(ld, 2.0)[-1]["phase"] == "tracking" for ld in ("L1", "L2", "L3")), 90,
                 "every team in formation, moving")
        rms = {ld: team_rms_m(w.recent(ld, 2.0)) for ld in ("L1", "L2", "L3")}
        truth = w.last_truth()
        assert truth["radio"] and truth["owners"] == ["L1"] * 3 + ["L2"] * 3 + ["L3"] * 3, truth["owners"]
        assert all(x > 0 for x in truth["leases"]), truth["leases"]  # every robot held by its leader's drives

        # 1. L1's radio cut for 3 s
        _cut_and_back(w, relay, 3.0, truth["owners"])

        # 2. SIGKILL L2: its robots' leases lapse; L1 and L3 claim them by the plan and seat them
        orphans = [3, 4, 5]
        procs["L2"].send_signal(signal.SIGKILL)
        procs["L2"].wait(10)
        t_kill = w.arena_t()
        wait_for(lambda: all(w.last_truth()["owners"][r] in ("L1", "L3") for r in orphans), 30, "every orphan claimed")
        with w.lock:
            truths = list(w.truths)
        after = [tr for tr in truths if tr["t"] >= t_kill]
        delays = []
        for r in orphans:
            lapsed = next(tr["t"] for tr in after if tr["leases"][r] == 0 or tr["owners"][r] != "L2")
            claimed = next(tr["t"] for tr in after if tr["owners"][r] != "L2")
            delays.append(claimed - lapsed)
            assert claimed - lapsed <= 2.0, (r, lapsed, claimed)
            assert lapsed - t_kill <= LEASE_S + 0.5, (r, t_kill, lapsed)  # the lease of its last DRIVE, no more
        owners = w.last_truth()["owners"]

        def seated() -> bool:
            return all(len(w.recent(ld, 1.0)[-1]["error_m"]) == owners.count(ld)
                       and max(w.recent(ld, 1.0)[-1]["error_m"]) <= 0.05 for ld in ("L1", "L3"))

        wait_for(seated, 120, "every orphan in a slot")
        t_seated = w.arena_t() - t_kill
        assert t_seated <= 15.0, t_seated

        # 3. L1's radio cut for 6 s, with the orphans it adopted (twice the first, six times the robots' 1 s
        # lease: L1 stays alive on the bus, and nobody may take them)
        _cut_and_back(w, relay, 6.0, owners)
        print(f"radio fleet: formation RMS when all were first in formation {', '.join(f'{k} {v * 100:.2f} cm' for k, v in rms.items())}; orphans"
              f" claimed {max(delays):.2f} s at most after their lease lapsed, all seated {t_seated:.1f} s after the"
              f" kill; owners {owners}; relay lost {relay.lost} chunks")
        assert w.last_truth()["two_owners"] == 0 and w.last_truth()["contacts"] == 0
    finally:
        interrupt(*procs.values())
        interrupt(arena)
        if relay is not None:
            relay.close()
        if watch is not None:
            watch.close()
    counts = json.loads(summary.read_text())
    # the robots' own count: never a DRIVE obeyed from two leaders within 100 ms
    assert counts["two_owners"] == 0 and counts["radio"]["two_owners"] == 0, counts
    assert counts["radio_commands"] == 0 and counts["conflicts"] == 0, counts  # nothing drove robots past the radio
    assert counts["radio"]["dropped"] > 0, counts["radio"]  # the medium did lose frames
    assert counts["contacts"] == 0 and counts["closest_m"] >= 0.25 and math.isfinite(counts["closest_m"]), counts
