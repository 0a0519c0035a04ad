"""A leader's link to the arena cut and healed (docs/fleet-protocol.md, "drive" and
"Orphans"): through a TCP relay that holds every byte while cut and delivers it late, as a
partition that heals does (this kernel has no netem). No command computed from an old truth
moves a robot; a leader back after its robots were adopted drops them at once."""

from __future__ import annotations

import json
import subprocess

import pytest

from app.fleet.bridge import loopback_endpoint

from tests.app.fleet.test_arena import Watcher
from tests.helpers import LEADER_PROCESS, TcpRelay, interrupt, spawn_cli, wait_for

zenoh = pytest.importorskip("zenoh")

FLEET = "three_teams"
BASE = f"omniformation/{FLEET}"
WATCHDOG_BOUND_S = 0.5 + 1 / 30 + 1e-3  # the watchdog's 0.5 s, and the step in which a command ages past it


def test_a_cut_leader_moves_nothing_on_old_truths_and_drops_what_was_adopted_while_it_was_gone(tmp_path):
    endpoint = loopback_endpoint()
    port = int(endpoint.rsplit(":", 1)[1])
    summary = tmp_path / "arena.json"
    arena = spawn_cli("arena", FLEET, "--zenoh-listen", endpoint, "--status-every", "0", "--summary", str(summary))
    relay = TcpRelay(port)
    procs: dict[str, subprocess.Popen] = {}
    watch = None
    try:
        assert arena.stdout is not None and "arena three_teams" in arena.stdout.readline()
        watch = Watcher(endpoint)
        procs["L1"] = spawn_cli("run", LEADER_PROCESS, "--arena", FLEET, "--leader-id", "L1", "--zenoh-connect",
                             f"tcp/127.0.0.1:{relay.port}", "--port", "0", "--no-record", "--feedback", "truth")
        procs["L2"] = spawn_cli("run", LEADER_PROCESS, "--arena", FLEET, "--leader-id", "L2", "--zenoh-connect", endpoint, "--port", "0",
                             "--no-record", "--feedback", "truth")
        w = watch
        wait_for(lambda: bool(w.truths) and w.last_truth()["alive"] == ["L1", "L2"], 60, "L1 and L2 alive")
        mine = [r for r, o in enumerate(w.last_truth()["owners"]) if o == "L1"]
        wait_for(lambda: all(w.last_truth()["command_age"][r] is not None for r in mine), 30, "L1 driving")

        # a short cut (3 s): L1's drives wait in the relay and arrive late, each naming a truth 0.5-3 s old
        stale_before = w.last_truth()["stale"]
        with w.lock:
            k_cut = len(w.truths)
        relay.cut(3.0)
        wait_for(lambda: not relay.is_cut, 10, "the relay healed")
        wait_for(lambda: w.last_truth()["stale"] > stale_before, 30, "the held drives refused as stale")
        wait_for(lambda: all(w.last_truth()["command_age"][r] is not None and w.last_truth()["command_age"][r] < 0.2
                             for r in mine), 30, "L1 driving again on fresh truths")
        with w.lock:
            after_cut = w.truths[k_cut:]
        for tr in after_cut:  # not one step moved an L1 robot on a command older than the watchdog allows
            for r in mine:
                age = tr["command_age"][r]
                assert tr["watchdog"][r] or age is None or age <= WATCHDOG_BOUND_S, (r, tr["t"], age)
        assert any(tr["watchdog"][r] for tr in after_cut for r in mine)  # they did stop while it was cut
        assert w.last_truth()["conflicts"] == 0

        # a long cut (12 s, past Zenoh's 10 s lease): L1 is lost, L2 adopts its robots; back, L1 drops them
        relay.cut(12.0)
        wait_for(lambda: "L1" in w.last_truth()["lost"], 30, "L1 lost")
        wait_for(lambda: all(w.last_truth()["owners"][r] == "L2" for r in mine), 30, "L2 adopting L1's robots")
        wait_for(lambda: not relay.is_cut, 30, "the relay healed")
        with w.lock:
            k_heal = len(w.truths)
            seen = len(w.states.get("L1", []))  # (arena t when heard, state) rows
        wait_for(lambda: "L1" in w.last_truth()["alive"], 60, "L1 back on the bus")

        def l1_after() -> list[dict]:
            with w.lock:
                return [m for _, m in w.states.get("L1", [])[seen:]]

        wait_for(lambda: len(l1_after()) > 30, 30, "a second of L1's states after it came back")
        back = l1_after()
        # within a second of its first state back, none of the robots it lost is tracked or commanded, and
        # from then on never again
        first_clean = next(i for i, s in enumerate(back) if not any(s["tracked"]))
        assert first_clean <= 30, [s["tracked"] for s in back[:first_clean + 1]]
        late = [s for s in back[first_clean:] if any(s["tracked"]) or any(v or ww for v, ww in s["commands"])]
        assert not late, late[:1]
        # every robot it had is L2's: its state is an empty team, waiting for the operator
        wait_for(lambda: w.recent("L1", 1.0)[-1]["phase"] == "waiting" and w.recent("L1", 1.0)[-1]["p_est"] == [], 30,
                 "L1 letting go of every robot")
        with w.lock:
            after_heal = w.truths[k_heal:]
        for tr in after_heal:
            for r in mine:
                age = tr["command_age"][r]
                assert tr["watchdog"][r] or age is None or age <= WATCHDOG_BOUND_S, (r, tr["t"], age)
        assert w.last_truth()["conflicts"] == 0 and all(w.last_truth()["owners"][r] == "L2" for r in mine)
        # the operator hands one back: L1's team is that robot, in a slot on its side
        replies = [json.loads(r.ok.payload.to_bytes()) for r in w.session.get(
            f"{BASE}/arena/handover", payload=json.dumps({"robot": f"R{mine[0] + 1}", "to": "L1", "from": "test"}),
            timeout=5.0)]
        assert replies and replies[0]["granted"], replies

        def l1_has_it() -> bool:
            last = w.recent("L1", 1.0)
            return bool(last) and last[-1]["phase"] != "waiting" and last[-1]["tracked"] == [True] \
                and last[-1]["error_m"][0] <= 0.05

        try:
            wait_for(l1_has_it, 60, f"R{mine[0] + 1} in L1's slot")
        except AssertionError:
            last = w.recent("L1", 1.0)[-1]
            print({k: last[k] for k in ("phase", "tracked", "error_m", "p_est", "p_d", "link_state", "stopped")},
                  w.last_truth()["owners"])
            raise
    finally:
        interrupt(*procs.values())
        interrupt(arena)
        relay.close()
        if watch is not None:
            watch.close()
    counts = json.loads(summary.read_text())
    assert counts["conflicts"] == 0 and counts["stale"] > 0, counts
