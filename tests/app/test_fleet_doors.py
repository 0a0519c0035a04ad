"""Every door of the fleet bus closed (docs/fleet-protocol.md), each tried by a hostile party
written from the document: a name that only looks like loopback, payloads built to break a
parser, key folders that hold more than their identity's keys, a page certificate used
beyond the page's role."""

from __future__ import annotations

import json
import os
import shutil
import subprocess
import sys
import time
import uuid
from collections.abc import Iterator
from pathlib import Path

import pytest

from tests.helpers import ROOT

FLEET = "three_teams"
BASE = f"omniformation/{FLEET}"


# -- H: a name is judged by the addresses it resolves to -------------------------------------------
@pytest.fixture
def netns() -> Iterator[tuple[str, str]]:
    """A network namespace of this test's own, joined to this one by a veth pair: its address
    (10.231.x.2) is on this machine and is not loopback. ``ip netns exec`` gives a process in it
    the namespace's own hosts file (/etc/netns/NAME/hosts) in place of /etc/hosts: the names
    below resolve through the real resolver, for that process only."""
    if shutil.which("ip") is None or os.geteuid() != 0:
        pytest.skip("network namespaces need `ip` and root")
    tag = uuid.uuid4().hex[:6]
    name, here, there = f"omf{tag}", f"vo{tag}", f"vi{tag}"
    subnet = f"10.231.{int(tag[:2], 16)}"
    made = subprocess.run(["ip", "netns", "add", name], capture_output=True, text=True)
    if made.returncode != 0:
        pytest.skip(f"network namespaces unavailable: {made.stderr.strip()}")
    etc = Path("/etc/netns") / name
    try:
        for cmd in (["ip", "link", "add", here, "type", "veth", "peer", "name", there],
                    ["ip", "link", "set", there, "netns", name],
                    ["ip", "addr", "add", f"{subnet}.1/24", "dev", here], ["ip", "link", "set", here, "up"],
                    ["ip", "-n", name, "addr", "add", f"{subnet}.2/24", "dev", there],
                    ["ip", "-n", name, "link", "set", there, "up"], ["ip", "-n", name, "link", "set", "lo", "up"]):
            subprocess.run(cmd, check=True, capture_output=True)
        etc.mkdir(parents=True)
        (etc / "hosts").write_text(f"127.0.0.1 localhost home.lan both.lan\n{subnet}.2 127.lan 127.0.0.1.evil both.lan\n")
        yield name, f"{subnet}.2"
    finally:
        subprocess.run(["ip", "link", "del", here], capture_output=True)
        subprocess.run(["ip", "netns", "del", name], capture_output=True)
        shutil.rmtree(etc, ignore_errors=True)


RUN_IN_NETNS = """
import json, sys
from tests.helpers import main_cli
out = []
for args in json.loads(sys.argv[1]):
    r = main_cli(*args)
    out.append([r.returncode, r.stderr])
print(json.dumps(out))
"""


def test_an_open_endpoint_is_loopback_by_every_address_its_name_resolves_to(netns):
    """docs/fleet-protocol.md, "Joining": a name is resolved and every address must be loopback."""
    name, address = netns
    cases = [
        (["arena", FLEET, "--zenoh-listen", "tcp/127.lan:17447", "--minutes", "0.005"], 2, f"127.lan is {address}"),
        (["fleet", "--fleet", FLEET, "--zenoh-connect", "tcp/127.0.0.1.evil:17447", "--port", "0"], 2,
         f"127.0.0.1.evil is {address}"),
        (["arena", FLEET, "--zenoh-listen", "udp/both.lan:17447", "--minutes", "0.005"], 2, f"both.lan is {address}"),
        (["arena", FLEET, "--zenoh-listen", "tcp/nowhere.invalid:17447", "--minutes", "0.005"], 2,
         "nowhere.invalid' does not resolve"),
        # a name that is 127.0.0.1 only passes: the line is about what comes after it
        (["run", "--fleet", FLEET, "--leader-id", "L1", "--zenoh-connect", "tcp/home.lan:17447", "--scenario",
          "no_such_scenario"], 2, "scenario 'no_such_scenario' not found"),
    ]
    r = subprocess.run(["ip", "netns", "exec", name, sys.executable, "-c", RUN_IN_NETNS,
                        json.dumps([c[0] for c in cases])], cwd=ROOT, capture_output=True, text=True, timeout=60)
    assert r.returncode == 0, r.stderr
    for (args, code, words), (rc, err) in zip(cases, json.loads(r.stdout.strip().splitlines()[-1]), strict=True):
        lines = err.strip().splitlines()
        assert rc == code and len(lines) == 1 and words in lines[0], (args, rc, err)
        refused_endpoint = "not loopback" in lines[0] or "does not resolve" in lines[0]
        assert refused_endpoint == ("no_such_scenario" not in args), (args, err)


# -- I: payloads built to break a parser ------------------------------------------------------------
DEEP = b"[" * 5000 + b"]" * 5000
HUGE = b"1" + b"0" * 400


def _replies(session, key: str, payload: bytes) -> list[dict]:
    out = []
    for reply in session.get(key, payload=payload, timeout=5.0):
        assert reply.ok is not None, "an error instead of an answer"
        out.append(json.loads(reply.ok.payload.to_bytes()))
    return out


def test_payloads_built_to_break_a_parser_are_refused_counted_and_answered():
    """docs/fleet-protocol.md, "Payloads": limits, exact types, every refusal counted and every
    question answered; and a leader takes no truth whose tick the arena's clock cannot have reached."""
    import threading

    from app.backends.arena import ArenaTeam
    from app.fleet.arena import Arena
    from app.fleet.bridge import FleetBridge, loopback_endpoint, open_session
    from app.params import ParamsStore
    from core.fleet import parse_fleet
    from tests.helpers import fleet_session, wait_for

    scenario = parse_fleet((ROOT / "static_config" / "fleets" / f"{FLEET}.toml").read_text(), FLEET)
    ep = loopback_endpoint()
    session = open_session([ep], [])
    arena = Arena(scenario, session)
    stop = threading.Event()
    stepper = threading.Thread(target=arena.run, args=(stop,), daemon=True)
    stepper.start()
    team = ArenaTeam(session, FLEET, "L1", 0.0, 0.0, 0, wait_s=5.0, hues_deg=scenario.hues_deg,
                     rate_hz=scenario.rate_hz)
    store = ParamsStore(fixed_followers=len(team.owned))
    bridge = FleetBridge(store, FLEET, "L1", session=session, allow_control=True)
    hostile = fleet_session(None, None, ep)
    truths: list[dict] = []
    events: list[dict] = []
    subs = [hostile.declare_subscriber(f"{BASE}/arena/truth", lambda s: truths.append(json.loads(s.payload.to_bytes()))),
            hostile.declare_subscriber(f"{BASE}/leader/L1/events",
                                       lambda s: events.append(json.loads(s.payload.to_bytes())))]
    try:
        wait_for(lambda: truths and "L1" in truths[-1]["alive"], 10,
                 "the arena's truth, L1 alive")
        # drives: nested 5,000 deep, a 400-digit number, a string and booleans for numbers
        before = truths[-1]["refused"]["malformed"]
        drives = [b'{"twist":[0,0],"commands":{},"truth_tick":' + DEEP + b"}",
                  b'{"twist":[' + HUGE + b',0],"commands":{},"truth_tick":1}',
                  b'{"twist":"00","commands":{},"truth_tick":1}',
                  b'{"twist":[true,false],"commands":{},"truth_tick":1}',
                  b'{"twist":[0,0],"commands":{"R1":[true,false]},"truth_tick":1}']
        for d in drives:
            hostile.put(f"{BASE}/arena/drive/L1", d)
        wait_for(lambda: truths[-1]["refused"]["malformed"] >= before + len(drives), 10, "five malformed drives")
        # claims and a handover: each answered, refused, counted
        before = truths[-1]["refused"]["malformed"]
        asks = [("claim/L1", b"[]"), ("claim/L1", DEEP), ("claim/L1", b'{"robot":' + HUGE + b"}"),
                ("claim/L1", b'{"robot":true}'), ("handover", b'{"robot":"R1","to":["L2"]}')]
        for key, payload in asks:
            answers = _replies(hostile, f"{BASE}/arena/{key}", payload)
            assert len(answers) == 1 and answers[0]["granted"] is False and answers[0]["why"], (payload[:40], answers)
        wait_for(lambda: truths[-1]["refused"]["malformed"] >= before + len(asks), 10, "five malformed asks")
        assert truths[-1]["owners"][:3] == ["L1"] * 3
        # commands to a leader that takes everything: none of these is a value
        version = store.get().version
        n_refused = sum(e["kind"] == "refused" for e in events)
        cmds = [b'{"set":{"k_f1":"0.2"}}', b'{"set":{"k_f1":true}}', b'{"set":{"k_f1":' + DEEP + b"}}",
                b'{"set":{"leader_speed_mps":' + HUGE + b"}}", b'{"set":{"stop":1}}', b'{"set":{"stop":false},"x":1}']
        for c in cmds:
            hostile.put(f"{BASE}/leader/L1/cmd", c)
        wait_for(lambda: sum(e["kind"] == "refused" for e in events) >= n_refused + len(cmds), 10, "six refusals")
        assert store.get().version == version and bridge.commands_refused == len(cmds)
        # under the leader's own state key: counted, no twin
        for s in (DEEP, b'{"instance":"0badf00d","started":' + HUGE + b"}"):
            hostile.put(f"{BASE}/leader/L1/state", s)
        wait_for(lambda: bridge.states_refused == 2, 10, "two refused states")
        assert bridge.twin is None
        # truths: broken ones, and a forged one a million ticks ahead that gives every robot to L3
        real = truths[-1]
        forged = dict(real, tick=real["tick"] + 1_000_000, owners=["L3"] * len(real["owners"]))
        for t in (DEEP, b'{"tick":' + HUGE + b"}", json.dumps(dict(real, tick=str(real["tick"] + 1))).encode(),
                  json.dumps(forged).encode()):
            hostile.put(f"{BASE}/arena/truth", t)
        wait_for(lambda: team.truths_refused >= 4, 10, "four refused truths")
        time.sleep(0.2)
        taken = team.latest_truth()
        assert taken is not None and taken["owners"][:3] == ["L1"] * 3 and taken["tick"] < real["tick"] + 1000
    finally:
        for s in subs:
            s.undeclare()
        hostile.close()
        bridge.close()
        team.close()
        stop.set()
        stepper.join(5)
        arena.close()
        session.close()
