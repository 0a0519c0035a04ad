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
        wait_for(lambda: bridge.commands_refused == len(cmds), 10, "six refusals")
        assert store.get().version == version
        # said on the bus at most as the refusal rule allows (app.refusals): one sender, one kind
        wait_for(lambda: sum(e["kind"] == "refused" for e in events) > n_refused, 10, "the first refusal said")
        assert sum(e["kind"] == "refused" for e in events) - n_refused <= 2
        for _ in range(200):  # a flood of them: counted, never an event each
            hostile.put(f"{BASE}/leader/L1/cmd", b"{not json")
        wait_for(lambda: bridge.commands_refused == len(cmds) + 200, 10, "the flood refused")
        assert sum(e["kind"] == "refused" for e in events) - n_refused <= 3
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
        # the arena stopped, so that only the hostile party speaks: truths with the next tick that
        # name no L1, or fewer robots than the arena has (a tick on either would not know where this
        # leader or its robots are), are refused one by one; the next tick as the arena gives it is taken
        stop.set()
        stepper.join(5)
        last = team.latest_truth()
        for _ in range(50):  # until the truths already on their way are in: none for 0.3 s
            time.sleep(0.3)
            if team.latest_truth() is last:
                break
            last = team.latest_truth()
        assert last is not None
        n0, nxt = team.truths_refused, last["tick"] + 1
        others = {lid: pose for lid, pose in last["leaders"].items() if lid != "L1"}
        short = {k: (v[:-1] if isinstance(v, list) and len(v) == len(last["robots"]) else v) for k, v in last.items()}
        for k, t in enumerate((dict(last, tick=nxt, leaders=others), dict(short, tick=nxt))):
            hostile.put(f"{BASE}/arena/truth", json.dumps(t).encode())
            wait_for(lambda k=k: team.truths_refused == n0 + k + 1, 10, f"hostile truth {k + 1} refused")
            assert team.latest_truth() is last
        hostile.put(f"{BASE}/arena/truth", json.dumps(dict(last, tick=nxt)).encode())
        wait_for(lambda: team.latest_truth()["tick"] == nxt, 10, "the next tick taken")
        assert team.truths_refused == n0 + 2
        assert team.scene().shape == (len(last["robots"]) + len(last["leaders"]) - 1, 3)
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


# -- J: a process reads its own bundle, and nothing more ---------------------------------------------
def test_keys_are_one_bundle_per_identity_and_a_folder_holding_more_is_refused(tmp_path):
    """docs/fleet-protocol.md, "Making keys": the CA's key apart, one bundle per identity; --keys
    refuses a folder that holds the CA key or another identity's private key or that others can write."""
    from tests.helpers import main_cli

    keys = tmp_path / "keys"
    assert main_cli("fleet-keys", str(keys), "--fleet", FLEET, "--leaders", "L1,L2,L3").returncode == 0
    for ident in ("arena", "L1"):  # the CA's key is in no bundle, nor another identity's
        assert not list((keys / ident).glob("ca.key")) and [p.name for p in (keys / ident).glob("*.key")] == [f"{ident}.key"]

    def bundle(name: str, change=lambda d: None, mode: int = 0o700) -> Path:
        d = tmp_path / name
        shutil.copytree(keys / "L1", d)
        change(d)
        os.chmod(d, mode)
        return d

    cases = [
        (keys, "fleet-keys' whole folder"),
        (bundle("with_ca", lambda d: shutil.copy(keys / "ca" / "ca.key", d)), "ca.key: the fleet CA's private key"),
        (bundle("with_l2", lambda d: shutil.copy(keys / "L2" / "L2.key", d)), "L2.key: another private key"),
        (bundle("renamed", lambda d: shutil.copy(keys / "arena" / "arena.key", d / "spare.pem")),
         "spare.pem: another private key"),
        (bundle("open", mode=0o777), "others may write it (mode 0777)"),
        (bundle("open_ca", lambda d: os.chmod(d / "ca.pem", 0o666)), "ca.pem: others may write it"),
    ]
    for d, words in cases:
        r = main_cli("run", "--arena", FLEET, "--leader-id", "L1", "--keys", str(d), "--zenoh-connect",
                     "tls/127.0.0.1:9", "--port", "0", "--no-record")
        lines = r.stderr.strip().splitlines()
        assert r.returncode == 2 and len(lines) == 1 and words in lines[0], (d.name, r.stderr)


# -- G: the page's certificate is the operator's commands, nothing more ------------------------------
def test_the_page_certificate_sends_commands_and_handovers_and_speaks_for_no_one(tmp_path):
    """docs/fleet-protocol.md, "Who may do what": with the page's certificate a program may send
    commands and handovers and hold the page's token; it cannot drive a robot, publish a truth,
    or speak as a leader (a state, an alive/<id> token). Heard by a holder of L1's certificate,
    as a leader would hear it, through the arena (the hub)."""
    import threading
    import time

    import zenoh

    from app.fleet.bridge import loopback_endpoint
    from tests.helpers import fleet_session, interrupt, main_cli, wait_for

    keys = tmp_path / "keys"
    assert main_cli("fleet-keys", str(keys), "--fleet", FLEET, "--leaders", "L1,L2,L3").returncode == 0
    ep = "tls/" + loopback_endpoint().split("/", 1)[1]
    arena = subprocess.Popen([sys.executable, "-m", "app.cli", "arena", FLEET, "--keys", str(keys / "arena"),
                              "--zenoh-listen", ep, "--status-every", "0"], cwd=ROOT, stdout=subprocess.PIPE,
                             stderr=subprocess.PIPE, text=True)
    sessions = []
    lock = threading.Lock()
    heard: dict[str, list] = {"truth": [], "state": [], "cmd": [], "alive": []}

    def on_sample(s) -> None:
        key = str(s.key_expr)
        kind = "truth" if key.endswith("arena/truth") else "state" if key.endswith("/state") else \
            "cmd" if key.endswith("/cmd") else None
        if kind is not None:
            with lock:
                heard[kind].append(json.loads(s.payload.to_bytes()) if kind != "state" else s.payload.to_bytes())

    def on_alive(s) -> None:
        with lock:
            heard["alive"].append((str(s.key_expr).split(f"{BASE}/", 1)[1], s.kind == zenoh.SampleKind.PUT))

    try:
        assert arena.stdout is not None and "arena three_teams" in arena.stdout.readline()
        l1 = fleet_session(keys / "L1", "L1", ep)  # what a leader L1 hears
        page = fleet_session(keys / "page", "page", ep)  # the hostile holder of the page's certificate
        sessions += [l1, page]
        subs = [l1.declare_subscriber(f"{BASE}/**", on_sample),
                l1.liveliness().declare_subscriber(f"{BASE}/**", on_alive, history=True)]
        wait_for(lambda: len(heard["truth"]) > 3, 20, "the arena's truth at L1")
        real = heard["truth"][-1]
        r1 = real["owners"].index("L1")
        # the attack: L1's token and a twin's state, a truth a million ticks ahead giving every robot to
        # L3, and 2 s of drives reversing L1's robot, each naming the newest truth
        tokens = [page.liveliness().declare_token(f"{BASE}/alive/L1"), page.liveliness().declare_token(f"{BASE}/page/alive")]
        twin = {"leader_id": "L1", "tick": 1, "t": 0.0, "instance": "00000000", "started": 0.0, "p_est": []}
        forged = dict(real, tick=real["tick"] + 1_000_000, owners=["L3"] * len(real["owners"]))
        end = time.monotonic() + 2.0
        while time.monotonic() < end:
            newest = heard["truth"][-1]["tick"]
            page.put(f"{BASE}/arena/drive/L1", json.dumps({"tick": 1, "truth_tick": newest, "twist": [0.0, 0.0],
                                                           "commands": {f"R{r1 + 1}": [-0.25, 0.0]}}))
            page.put(f"{BASE}/leader/L1/state", json.dumps(twin))
            page.put(f"{BASE}/arena/truth", json.dumps(forged))
            time.sleep(1 / 30)
        # what the page may do reaches: a command to L1, a handover (answered by the arena), its token
        page.put(f"{BASE}/leader/L1/cmd", json.dumps({"set": {"stop": True}, "from": "test"}))
        answers = [json.loads(r.ok.payload.to_bytes()) for r in page.get(
            f"{BASE}/arena/handover", payload=json.dumps({"robot": "R4", "to": "L1", "from": "test"}), timeout=5.0)
            if r.ok is not None]
        wait_for(lambda: heard["cmd"] and ("page/alive", True) in heard["alive"], 10, "the page's command and token")
        time.sleep(0.5)
        with lock:
            truths, states, alive = list(heard["truth"]), list(heard["state"]), list(heard["alive"])
        found = {  # each what the page's certificate got through (all but the handover: none)
            "handover answered": len(answers) == 1,
            "handover granted": bool(answers and answers[0]["granted"]),
            "forged truths heard": sum(t["tick"] >= real["tick"] + 10_000 or t["owners"] != real["owners"]
                                       for t in truths),
            "twin states heard": len(states),
            "alive/L1 tokens heard": sum(key == "alive/L1" for key, _ in alive),
            "truths with L1 alive": sum("L1" in t["alive"] for t in truths),
            "steps with L1's robot moving": sum(abs(t["velocities"][r1][0]) > 0.01 for t in truths
                                                if t["tick"] < real["tick"] + 10_000),
        }
        assert found == {"handover answered": True, "handover granted": False, "forged truths heard": 0,
                         "twin states heard": 0, "alive/L1 tokens heard": 0, "truths with L1 alive": 0,
                         "steps with L1's robot moving": 0}, (sorted(found.items()), len(truths))
        assert "L1 is not alive" in answers[0]["why"], answers
        for tok in tokens:
            tok.undeclare()
        for s in subs:
            s.undeclare()
    finally:
        for s in sessions:
            s.close()
        interrupt(arena)


def test_a_state_s_robots_are_robot_names_or_the_state_is_refused():
    """docs/fleet-protocol.md, "state": ``robots`` (an arena leader's) is a list of robot names
    R1, R2, ... in the followers' order; anything else is refused like any broken state."""
    from app import wire
    from app.fleet.bridge import read_state

    base = {"p_est": [[0.1, 0.2], [0.3, 0.4]], "tracked": [True, True]}
    assert read_state(dict(base, robots=["R3", "R7"]))["robots"] == ["R3", "R7"]
    assert "robots" not in read_state(dict(base))  # a leader of no arena says nothing of it
    for bad in ("R3", [3, 7], ["R3", "X7"], ["R0"], ["R-1"], [["R3"]], ["r3"], [None], ["R3 "], {"R3": 0}):
        with pytest.raises(wire.BadMessage, match="robots must be a list of robot names"):
            read_state(dict(base, robots=bad))


def test_the_bus_reader_refuses_deep_nesting_and_numbers_that_are_not_finite_wherever_they_sit():
    """docs/fleet-protocol.md, "Payloads": at most MAX_DEPTH levels of nesting and only finite
    numbers, in a list or an object at any level (a float too large for a double reads as
    infinity); everything else JSON holds comes back as json.loads reads it. And a truth's poses
    are numbers of their exact type, three each, or the truth is refused."""
    from app import wire
    from app.backends.arena import read_truth

    deep = b"[" * wire.MAX_DEPTH + b"1" + b"]" * wire.MAX_DEPTH
    assert wire.decode(deep) == json.loads(deep)
    for bad in (b"[" + deep + b"]", b'{"a":' + deep + b"}", b'{"a":[{"b":' + b"[" * (wire.MAX_DEPTH - 2) + b"]" * (wire.MAX_DEPTH - 2) + b"}]}"):
        with pytest.raises(wire.BadMessage, match=f"nested deeper than {wire.MAX_DEPTH}"):
            wire.decode(bad)
    for bad in (b"1e999", b"[1.5, -1e999]", b'{"a":{"b":[0, 2e308]}}', b'{"t":1e400,"x":"y"}', b"[[1, [2.0, 1E+999]]]"):
        with pytest.raises(wire.BadMessage, match="is not a finite number"):
            wire.decode(bad)
    for bad in (b"[NaN]", b'{"a":Infinity}', b"-Infinity"):
        with pytest.raises(wire.BadMessage, match="is not a number JSON allows"):
            wire.decode(bad)
    fine = b'{"a":{"b":[1.5,2,"x",null,true,-0.0,1e308]},"c":[],"d":{}}'
    assert wire.decode(fine) == json.loads(fine)
    truth = {"tick": 3, "t": 0.1, "leaders": {"L1": [0.0, 1, 2.5]}, "robots": [[0.5, 0.0, 1.0], [1, 2, 3]],
             "velocities": [[0.0, 0.1], [0, 0]], "leases": [0.5, 1], "owners": ["L1", None]}
    assert read_truth(truth) is truth
    for key, bad, what in (("robots", [[0.5, 0.0, True], [1, 2, 3]], "robots must be a number"),
                           ("robots", [[0.5, 0.0], [1, 2, 3]], "robots must be a list of 3 numbers"),
                           ("leaders", {"L1": [0.0, "1", 2.5]}, "leaders.L1 must be a number"),
                           ("velocities", [[0.0, 0.1], [0, None]], "velocities must be a number"),
                           ("leases", [0.5, False], "leases must be a number")):
        with pytest.raises(wire.BadMessage, match=what):
            read_truth(dict(truth, **{key: bad}))


def test_a_robot_has_one_name_the_fleet_s_with_its_leader_s_slot():
    """docs/page-access.md, "One name per robot": R3 (F1) on its leader's page, R3 · L1 F1 on the
    fleet page, F1 for a team of no arena."""
    from app.keys import follower_name, held_name

    assert [follower_name(i, (2, 6)) for i in range(2)] == ["R3 (F1)", "R7 (F2)"]
    assert follower_name(0) == "F1" and follower_name(2, (2, 6)) == "F3"
    assert held_name(2, "L1", 0) == "R3 · L1 F1"
