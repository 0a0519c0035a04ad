"""A fleet in one arena (paper §6): the arena and three leader processes on loopback, watched
by a plain Zenoh session as a third program would (docs/fleet-protocol.md).

Times are the arena's own (the ``t`` of its truth), so a loaded machine slows the world and
the clock together."""

from __future__ import annotations

import bisect
import contextlib
import json
import math
import signal
import subprocess
import threading
import time
from collections.abc import Iterator
from pathlib import Path
from typing import Any

import numpy as np
import pytest

from app.fleet.bridge import loopback_endpoint
from core.config import ConfigError
from core.fleet import FleetScenario, adoption_plan, initial_arena, parse_fleet, step_arena
from core.sim.team import FollowerDynamics

from tests.helpers import LEADER_PROCESS, ROOT, fleet_session, interrupt, main_cli, spawn_cli, wait_for

zenoh = pytest.importorskip("zenoh")

FLEET = "three_teams"


class Watcher:
    """Subscribes to the arena's truth and every leader's state."""

    def __init__(self, endpoint: str, keys: Path | None = None) -> None:
        # with the fleet's keys, the operator's identity (it may hand over); else a plain session
        self.session = fleet_session(keys / "page" if keys is not None else None, "page" if keys is not None else None,
                                     endpoint)
        self.lock = threading.Lock()
        self.truths: list[dict] = []
        self.states: dict[str, list[tuple[float, dict]]] = {}  # leader -> (arena t when received, state)
        self.subs = [self.session.declare_subscriber(f"omniformation/{FLEET}/arena/truth", self._truth),
                     self.session.declare_subscriber(f"omniformation/{FLEET}/leader/*/state", self._state)]

    def _truth(self, s) -> None:
        with self.lock:
            self.truths.append(json.loads(s.payload.to_bytes()))

    def _state(self, s) -> None:
        msg = json.loads(s.payload.to_bytes())
        with self.lock:
            t = self.truths[-1]["t"] if self.truths else 0.0
            self.states.setdefault(msg["leader_id"], []).append((t, msg))

    def arena_t(self) -> float:
        with self.lock:
            return self.truths[-1]["t"] if self.truths else 0.0

    def last_truth(self) -> dict:
        with self.lock:
            return self.truths[-1]

    def recent(self, leader: str, seconds: float) -> list[dict]:
        with self.lock:
            rows = self.states.get(leader, [])
            if not rows:
                return []
            # rows come in arena-time order: find the window's start, not scan every state so far
            # (polled every 10 ms for minutes, the scan took a core from the leaders it watches)
            start = bisect.bisect_left(rows, rows[-1][0] - seconds, key=lambda row: row[0])
            return [m for _, m in rows[start:]]

    def close(self) -> None:
        self.session.close()


def team_rms_m(states: list[dict]) -> float:
    """RMS over these states of each follower's true distance from its slot (the arena's truth,
    which the leader publishes as p_true; its camera's estimates are what it steers by)."""
    errs = [math.dist(p, d) for s in states for p, d in zip(s["p_true"], s["p_d"]) if p is not None and d is not None]
    return math.sqrt(float(np.mean(np.square(errs)))) if errs else math.inf


def test_three_teams_hold_formation_and_adopt_a_killed_leaders_robots(tmp_path):
    """With the fleet's keys (mutual TLS, access control by identity), as a fleet on a lab network
    runs; tests/app/fleet/test_fleet.py and the fleet page's test run the open loopback bus."""
    keys = tmp_path / "keys"
    assert main_cli("fleet-keys", str(keys), "--fleet", FLEET, "--leaders", "L1,L2,L3").returncode == 0
    endpoint = "tls/" + loopback_endpoint().split("/", 1)[1]
    summary = tmp_path / "arena.json"
    arena = spawn_cli("arena", FLEET, "--keys", str(keys / "arena"), "--zenoh-listen", endpoint, "--status-every", "0",
                   "--summary", str(summary))
    procs: dict[str, subprocess.Popen] = {}
    watcher = None
    try:
        assert arena.stdout is not None
        assert "arena three_teams: 3 leaders, 9 robots" in arena.stdout.readline()
        watcher = Watcher(endpoint, keys)
        for leader in ("L1", "L2", "L3"):
            procs[leader] = spawn_cli("run", LEADER_PROCESS, "--arena", FLEET, "--leader-id", leader, "--keys", str(keys / leader), "--zenoh-connect", endpoint,
                                   "--port", "0", "--no-record")
        w = watcher
        wait_for(lambda: sorted(w.last_truth()["alive"]) == ["L1", "L2", "L3"] if w.truths else False, 60,
                 "three leaders alive")
        # every team, seen by its leader's camera (rendered from the arena, the other teams in view), in
        # formation while every leader moves: steady true RMS over the last 2 s of its own state
        wait_for(lambda: all(team_rms_m(w.recent(ld, 2.0)) <= 0.02 and w.recent(ld, 2.0)[-1]["leader_twist"][0] > 0.01
                             and w.recent(ld, 2.0)[-1]["phase"] == "tracking" for ld in ("L1", "L2", "L3")), 90,
                 "every team in formation, moving")
        t_in = w.arena_t()  # steady: the next 2 s of every team, all moving
        wait_for(lambda: w.arena_t() >= t_in + 2.0, 60, "2 s more in the arena")
        rms = {ld: team_rms_m(w.recent(ld, 2.0)) for ld in ("L1", "L2", "L3")}
        assert all(v <= 0.02 for v in rms.values()), rms
        # a second leader with an id on the bus already refuses to start, saying so
        twin = main_cli("run", "--arena", FLEET, "--leader-id", "L1", "--keys", str(keys / "L1"), "--zenoh-connect", endpoint, "--port", "0",
                        "--no-record")
        assert twin.returncode == 2 and "a leader with this id is alive on fleet three_teams" in twin.stderr, twin.stderr
        assert len(twin.stderr.strip().splitlines()) == 1
        truth = w.last_truth()
        assert truth["conflicts"] == 0
        orphans = [r for r, o in enumerate(truth["owners"]) if o == "L2"]
        assert orphans == [3, 4, 5]

        # SIGKILL one leader: its robots stop by their own watchdog; the others adopt them
        procs["L2"].send_signal(signal.SIGKILL)
        procs["L2"].wait(10)
        t_kill = w.arena_t()
        # each orphan stops by its own watchdog, unless a survivor adopted and drove it first (with the
        # fleet's keys the token's loss can travel faster than the watchdog's 0.5 s)
        wait_for(lambda: all(w.last_truth()["watchdog"][r] or w.last_truth()["owners"][r] in ("L1", "L3")
                             for r in orphans), 30, "the orphans stopped by their watchdogs or adopted")
        with w.lock:
            truths = list(w.truths)
        # what must hold: no robot ever moves on a command older than the watchdog's 0.5 s (plus the step
        # during which it ages: the arena zeroes a command for the whole step in which it would pass 0.5 s)
        k_kill = next(k for k, tr in enumerate(truths) if tr["t"] >= t_kill)
        for tr in truths[k_kill:]:
            for r in orphans:
                age = tr["command_age"][r]
                assert tr["watchdog"][r] or age is None or age <= 0.5 + 1 / 30 + 1e-3, (r, tr["t"], age)

        # the robot's own watchdog: zero within 0.5 s of its last command. The first truth saying so is
        # published after the step that zeroed it: that step began one step (1/30 s) before its age
        def first_stop(r: int) -> float | None:  # the truth after its last one still driven
            last_driven = max(k for k, tr in enumerate(truths) if not tr["watchdog"][r])
            age = truths[last_driven + 1]["command_age"][r]
            return None if age is None else age - 1 / 30

        stopped = [r for r in orphans if any(tr["watchdog"][r] for tr in truths[k_kill:])]
        stop_after = [first_stop(r) for r in stopped]
        assert all(a is not None and a <= 0.5 + 1e-3 for a in stop_after), stop_after
        wait_for(lambda: "L2" in w.last_truth()["lost"], 30, "L2 lost")
        wait_for(lambda: all(w.last_truth()["owners"][r] in ("L1", "L3") for r in orphans), 30, "every orphan claimed")
        t_claimed = w.arena_t() - t_kill
        adopters = w.last_truth()["owners"]
        # the plan: nearest living leader with room, ties by id -- both survivors agree, the arena granted each once
        assert sum(o == "L1" for o in adopters) + sum(o == "L3" for o in adopters) == 9

        def seated() -> bool:  # every team, adopted robots included, in its slots
            return all(len(w.recent(ld, 1.0)[-1]["error_m"]) == adopters.count(ld)
                       and max(w.recent(ld, 1.0)[-1]["error_m"]) <= 0.05 for ld in ("L1", "L3"))

        wait_for(seated, 120, "every orphan in a slot")
        t_seated = w.arena_t() - t_kill
        print(f"arena: formation RMS {', '.join(f'{k} {v * 100:.2f} cm' for k, v in rms.items())}; orphans stopped"
              f" by their watchdog {len(stop_after)} of {len(orphans)}, at most"
              f" {max(stop_after, default=float('nan')):.2f} s after their last command; claimed {t_claimed:.1f} s, all seated {t_seated:.1f} s (arena time) after the"
              f" kill; owners {adopters}; closest two bodies so far {min(tr['closest_m'] for tr in w.truths) * 100:.1f} cm apart")
        assert t_seated <= 15.0, t_seated
        assert w.last_truth()["conflicts"] == 0 and w.last_truth()["contacts"] == 0

        # L2 comes back empty-handed and waits; the operator hands it R5 back; its adopter lets go
        procs["L2"] = spawn_cli("run", LEADER_PROCESS, "--arena", FLEET, "--leader-id", "L2", "--keys", str(keys / "L2"), "--zenoh-connect", endpoint, "--port", "0",
                             "--no-record")
        assert procs["L2"].stdout is not None
        assert "L2 owns no robot in the arena now" in procs["L2"].stdout.readline()
        wait_for(lambda: "L2" in w.last_truth()["alive"], 30, "L2 alive again")
        # waiting, it still says how it is every tick: an empty team
        wait_for(lambda: sum(m["phase"] == "waiting" for m in w.recent("L2", 2.0)) > 10, 30, "L2's waiting states")
        waiting = w.recent("L2", 2.0)[-1]
        assert waiting["phase"] == "waiting" and waiting["p_est"] == [] and waiting["stopped"], waiting
        giver = adopters[4]
        replies = [json.loads(r.ok.payload.to_bytes()) for r in w.session.get(
            f"omniformation/{FLEET}/arena/handover", payload=json.dumps({"robot": "R5", "to": "L2", "from": "test"}),
            timeout=5.0)]
        assert replies and replies[0]["granted"], replies
        def l2_seated() -> bool:
            last = w.recent("L2", 1.0)
            return bool(last) and len(last[-1]["error_m"]) == 1 and last[-1]["error_m"][0] <= 0.05

        try:
            wait_for(l2_seated, 90, "R5 in L2's slot")
        except AssertionError:
            last = w.recent("L2", 1.0)
            print("L2 now:", {k: last[-1][k] for k in ("tick", "p_est", "p_d", "error_m", "stopped", "phase")} if last
                  else None, "owners", w.last_truth()["owners"])
            raise
        wait_for(lambda: len(w.recent(giver, 1.0)[-1]["error_m"]) == adopters.count(giver) - 1, 30,
                 f"{giver} let R5 go")
        # one process, one clock: its states' t went on from where its waiting ones were, one instance throughout
        with w.lock:
            l2_states = [m for _, m in w.states["L2"] if m["instance"] == waiting["instance"]]
        assert l2_states[-1]["phase"] != "waiting" and l2_states[-1]["t"] > waiting["t"]
        ts = [m["t"] for m in l2_states]
        assert ts == sorted(ts), ts[:5]
        assert w.last_truth()["conflicts"] == 0 and w.last_truth()["contacts"] == 0
    finally:
        interrupt(*procs.values())
        interrupt(arena)  # the leaders first: the arena sees them go
        if watcher is not None:
            watcher.close()
    counts = json.loads(summary.read_text())
    assert counts["conflicts"] == 0 and counts["claims_granted"] == 3 and counts["claims_repeated"] == 0, counts
    assert counts["malformed"] == 0, counts
    assert counts["ever_alive"] == ["L1", "L2", "L3"]
    # no two bodies (robots, leaders) ever closer than the safety filter's 0.25 m, centre to centre
    assert counts["contacts"] == 0 and counts["closest_m"] >= 0.25, counts


def _fleet(text: str) -> FleetScenario:
    return parse_fleet(text, "f.toml")


LEADER = '[[leaders]]\nid = "{id}"\nstart = [{x}, 0]\nfollowers = {n}\n'


def test_a_fleet_scenario_is_checked_and_its_hues_are_fleet_wide():
    sc = _fleet('name = "f"\n' + LEADER.format(id="A", x=0, n=3) + LEADER.format(id="B", x=3, n=2))
    assert sc.robots == 5 and list(sc.owners) == [0, 0, 0, 1, 1]
    assert sc.hues_deg == (0.0, 72.0, 144.0, 216.0, 288.0)
    bad = {
        'name = "f"\n' + LEADER.format(id="A", x=0, n=2) + LEADER.format(id="A", x=3, n=2): "every leader needs its own id",
        'name = "f"\n' + LEADER.format(id="A", x=0, n=2) + 'hues_deg = [0, 100]\n' + LEADER.format(id="B", x=3, n=2)
        + 'hues_deg = [200, 105]\n': "R2 (A) and R4 (B) have hues 100 and 105 deg, 5 deg apart",
        'name = "f"\n' + LEADER.format(id="A", x=0, n=8) + LEADER.format(id="B", x=3, n=8)
        + LEADER.format(id="C", x=6, n=8) + LEADER.format(id="D", x=9, n=8): "32 followers cannot carry hues",
        'name = "f"\n' + LEADER.format(id="A/B", x=0, n=2): "leaders[1].id = 'A/B'",
        'name = "f"\n' + LEADER.format(id="A", x=0, n=9): "leaders[1].followers = 9",
    }
    for text, words in bad.items():
        with pytest.raises(ConfigError) as exc:
            _fleet(text)
        assert words in str(exc.value) and "\n" not in str(exc.value), str(exc.value)


def test_the_adoption_rule_is_the_same_for_everyone_and_respects_room():
    xy = np.array([[0.0, 0.0], [1.0, 0.0], [5.0, 0.0], [2.5, 0.0]])
    leaders = {"B": (3.0, 0.0, 2), "A": (-1.0, 0.0, 7), "C": (2.0, 0.0, 8)}
    plan = adoption_plan([3, 0, 1, 2], xy, leaders, capacity=8)
    # robot 0: A nearest (1 m) and has room (7 -> 8); robot 1: A full now, B (2 m) beats C (full)
    assert plan == {0: "A", 1: "B", 2: "B", 3: "B"}
    assert adoption_plan([3, 0, 1, 2], xy, dict(reversed(list(leaders.items()))), capacity=8) == plan
    tie = adoption_plan([0], np.array([[0.0, 0.0]]), {"Y": (1.0, 0.0, 0), "X": (-1.0, 0.0, 0)})
    assert tie == {0: "X"}  # equally near: the lower id
    assert adoption_plan([0], xy, {"A": (0.0, 0.0, 8)}, capacity=8) == {}  # nobody has room: left alone


def test_the_arena_steps_every_robot_and_leader():
    sc = _fleet('name = "f"\n' + LEADER.format(id="A", x=0, n=2) + LEADER.format(id="B", x=3, n=1))
    s = initial_arena(sc)
    twists = np.array([[0.1, 0.0], [0.0, 0.0]])
    commands = np.array([[0.1, 0.0], [0.0, 0.0], [0.0, 1.0]])
    for _ in range(30):
        s = step_arena(s, twists, commands, 1 / 30, FollowerDynamics())
    assert s.leaders[0, 1] == pytest.approx(0.1, abs=1e-6) and s.leaders[1, 1] == pytest.approx(0.0)
    assert s.robots[0, 1] - initial_arena(sc).robots[0, 1] == pytest.approx(0.1, abs=1e-6)
    assert s.robots[2, 2] - initial_arena(sc).robots[2, 2] == pytest.approx(1.0, abs=1e-6)


@pytest.mark.parametrize("args, words", [
    (["run", "--arena", FLEET, "--leader-id", "L9"], "--leader-id must be one of its leaders: L1, L2, L3"),
    (["run", "--arena", FLEET, "--leader-id", "L1", "--scenario", "vee3"], "cannot be combined"),
    (["run", "--arena", "nofleet", "--leader-id", "L1"], "fleet scenario 'nofleet' not found"),
    (["arena", "nofleet"], "fleet scenario 'nofleet' not found"),
    (["arena", FLEET, "--zenoh-listen", "127.0.0.1:1"], "tcp/HOST:PORT"),
    (["arena", FLEET, "--radio-drop", "0.1"], "--radio-drop and --radio-delay-ms go with --radio"),
    (["arena", FLEET, "--radio", "--radio-drop", "2"], "--radio-drop"),
    (["arena", FLEET, "--radio", "--radio-delay-ms", "-1"], "--radio-delay-ms"),
    (["run", "--arena", FLEET, "--leader-id", "L2", "--link", "serial:/dev/null", "--radio-id", "1"],
     "on three_teams's radio L2 is radio id 2"),
    (["run", "--arena", FLEET, "--leader-id", "L1", "--link", "sim"], "the link is this leader's radio"),
    (["run", "--arena", FLEET, "--leader-id", "L1", "--link", "serial:/a,/b"], "the link is this leader's radio"),
    (["run", "--arena", FLEET, "--leader-id", "L1", "--radio-id", "1"], "--radio-id goes with --link serial:PATH"),
])
def test_bad_arena_arguments_are_one_line(args, words):
    r = main_cli(*args, *(["--port", "0", "--no-record"] if args[0] == "run" else []))
    assert r.returncode == 2 and words in r.stderr and len(r.stderr.strip().splitlines()) == 1, r.stderr


def test_a_leader_without_an_arena_says_so(tmp_path):
    r = main_cli("run", "--arena", FLEET, "--leader-id", "L1", "--zenoh-connect", loopback_endpoint(),
                 "--port", "0", "--no-record")
    assert r.returncode == 2 and "no arena is alive on fleet three_teams's bus" in r.stderr, r.stderr
    assert len(r.stderr.strip().splitlines()) == 1


def test_an_adopted_robot_joins_on_the_side_it_comes_from():
    from core.control.presets import MIN_SPACING_M, default_formation
    from core.fleet import slot_for_newcomer

    slots = default_formation(3)
    for newcomer in (np.array([3.0, 0.0]), np.array([-3.0, 0.2]), np.array([0.0, -2.0])):
        new = slot_for_newcomer(slots, newcomer)
        assert np.min(np.hypot(*(slots - new).T)) >= MIN_SPACING_M - 1e-9
        assert 0.5 <= math.hypot(*new) <= 1.5 + 1e-9
        assert np.sign(new[np.argmax(np.abs(newcomer))]) == np.sign(newcomer[np.argmax(np.abs(newcomer))]), new
    assert np.array_equal(slot_for_newcomer(slots, np.array([3.0, 0.0])), slot_for_newcomer(slots, np.array([3.0, 0.0])))


@contextlib.contextmanager
def _stepping_arena_and_l1(alive: tuple[str, ...] = ()) -> Iterator[tuple[Any, threading.Event, threading.Thread,
                                                                      Any, dict[str, Any]]]:
    """A real arena stepping on its own thread (until the event is set) and leader L1's team on it,
    both on one in-process Zenoh session, with liveliness tokens for the leaders ``alive`` declared
    before the arena's first step (the test's to undeclare early): (arena, stop, stepper, team,
    tokens). Everything closed after, the team first."""
    from app.backends.arena import ArenaTeam
    from app.fleet.arena import Arena
    from app.fleet.bridge import open_session

    scenario = parse_fleet((ROOT / "static_config" / "fleets" / f"{FLEET}.toml").read_text(), FLEET)
    session = open_session([], [])
    arena = Arena(scenario, session)
    tokens = {lid: session.liveliness().declare_token(f"omniformation/{FLEET}/alive/{lid}") for lid in alive}
    stop = threading.Event()
    stepper = threading.Thread(target=arena.run, args=(stop,), daemon=True)
    stepper.start()
    team = None
    try:
        team = ArenaTeam(session, FLEET, "L1", 0.0, 0.0, 0, wait_s=5.0, hues_deg=scenario.hues_deg)
        yield arena, stop, stepper, team, tokens
    finally:
        if team is not None:
            team.close()
        stop.set()
        stepper.join(5)
        for tok in tokens.values():
            tok.undeclare()
        arena.close()
        session.close()


@contextlib.contextmanager
def _l1_in_an_arena():
    """A real arena stepping in-process on a real Zenoh session, the three leaders' tokens (the
    test's to undeclare), and L1's team and adopter: (arena, tokens, team, store, adopter)."""
    from app.fleet.adopter import Adopter
    from app.params import ParamsStore

    with _stepping_arena_and_l1(("L1", "L2", "L3")) as (arena, _stop, _stepper, team, tokens):
        store = ParamsStore(fixed_followers=len(team.owned))
        adopter = Adopter(team.session, FLEET, "L1", team, store)
        try:
            wait_for(lambda: arena.alive == {"L1", "L2", "L3"} and adopter.alive >= {"L1", "L2", "L3"}, 10,
                     "three alive")
            yield arena, tokens, team, store, adopter
        finally:
            adopter.close()


def test_a_leader_that_read_no_truth_for_longer_than_its_queue_takes_the_newest_and_refuses_none():
    """docs/fleet-protocol.md, "truth": a leader reads the truths queued for it, in their order,
    whenever its loop looks at the world; the queue holds the last TRUTH_QUEUE. After a stall
    longer than that (nobody read the truths for three seconds) the first read takes the newest
    truth the arena has published, and refuses none of those read on the way; and a truth that
    waited in the queue is not taken for younger than it is: the arena stopped, the newest truth
    read STALE_TRUTH_S after it came is a lost link."""
    from app.backends.arena import STALE_TRUTH_S, TRUTH_QUEUE

    with _stepping_arena_and_l1() as (arena, stop, stepper, team, _tokens):
        first = team.latest_truth()
        assert first is not None and team.truths_refused == 0
        wait_for(lambda: arena.counts.steps > first["tick"] + TRUTH_QUEUE + arena.scenario.rate_hz, 30,
                 "a second more than the queue holds")  # the arena's count: the team is not read meanwhile
        stop.set()
        stepper.join(5)  # the arena's last truth is out
        newest = arena.counts.steps
        time.sleep(STALE_TRUTH_S + 0.1)
        taken = team.latest_truth()
        assert taken is not None and taken["tick"] == newest
        assert team.truths_refused == 0
        assert team.link_lost and "no truth for" in team.link_state


def test_a_leader_closed_while_another_thread_reads_its_truths_answers_from_the_last_one():
    """The adopter's thread reads the team's truths while the loop's thread closes the team at the
    end of a run: no read fails on the subscriber that close takes away (a traceback at every
    leader's shutdown), the last truth taken stands, and a closed team's link is lost once it is
    older than STALE_TRUTH_S."""
    from app.backends.arena import STALE_TRUTH_S

    failures: list[BaseException] = []
    reads = [0]
    with _stepping_arena_and_l1() as (_arena, stop, _stepper, team, _tokens):

        def reader() -> None:
            while not stop.is_set():
                try:
                    team.latest_truth(), team.link_state, team.truths_refused, team.link_lost
                    reads[0] += 1
                except BaseException as exc:  # noqa: BLE001 - what the test looks for
                    failures.append(exc)
                    return

        other = threading.Thread(target=reader, daemon=True)
        other.start()
        try:
            wait_for(lambda: reads[0] > 100, 30, "the reader reading")
            team.close()
            at_close = team.latest_truth()
            done = reads[0]
            wait_for(lambda: reads[0] > done + 100, 30, "the reader reading after close")
            assert not failures, failures
            assert at_close is not None and team.latest_truth() is at_close  # the last truth taken stands
            time.sleep(STALE_TRUTH_S + 0.1)
            assert team.link_lost and "no truth for" in team.link_state
            team.close()  # a second close is nothing
        finally:
            stop.set()
            other.join(5)


def test_a_leader_never_claims_twice_what_an_old_truth_still_shows_as_orphaned():
    """The adopter acts on the newest truth it holds, which may be older than its own grant: a
    robot it took already is no orphan (claimed again it would be granted -- it is the
    claimant's -- and seated in a second slot). A real arena, a real Zenoh session in-process."""
    with _l1_in_an_arena() as (arena, tokens, team, store, adopter):
        # nobody drives L2's robots: their power-up lease lapses, and the robots grant a claim
        wait_for(lambda: all(arena.leases[r] == 0 for r, o in enumerate(arena.owners) if o == "L2"), 10, "leases lapsed")
        tokens.pop("L2").undeclare()
        wait_for(lambda: "L2" not in arena.alive and "L2" not in adopter.alive, 10, "L2 gone")
        stale = arena.truth()  # L2's robots orphans in it; the newest truth the adopter sees, twice
        adopter._adopt_orphans(stale)
        taken = arena.counts.claims_granted
        assert taken >= 1 and sorted(team.owned) == sorted(set(team.owned))
        adopter._adopt_orphans(stale)
        assert arena.counts.claims_granted == taken and arena.counts.claims_repeated == 0, arena.counts
        assert sorted(team.owned) == sorted(set(team.owned)) and len(team.owned) == 3 + taken
        params = store.get()
        assert params.n_followers == len(team.owned) and len(params.slots) == params.n_followers
        # a robot the arena gives away is no longer one this leader may command, from the truth that says so
        team.resize(len(team.owned))
        wait_for(lambda: team.answering().all(), 10, "the truth showing every robot it took")
        given = team.active[0]
        with arena._lock:  # the operator's handover, as the robot takes it
            assert arena._hand_over(given, "L3") == ""
        wait_for(lambda: team.latest_truth()["owners"][given] == "L3", 10, "the truth of the handover")
        assert list(team.answering()) == [r != given for r in team.active]


def test_the_arena_is_the_worlds_physics_and_ignores_drives_from_old_truths():
    """A drive computed from a truth older than 0.5 s (or naming none) moves nothing and is
    counted; a fresh one is held to the bodies' limits: a leader's base to the page's speed and
    turn bounds, a robot to its dynamics' (a 50 m/s twist does not throw a leader across the
    arena). A real arena, a real Zenoh session in-process."""
    from app.fleet.arena import STALE_DRIVE_S, Arena
    from app.fleet.bridge import open_session
    from core.bounds import LEADER_SPEED, LEADER_TURN

    scenario = parse_fleet((ROOT / "static_config" / "fleets" / f"{FLEET}.toml").read_text(), FLEET)
    session = open_session([], [])
    arena = Arena(scenario, session)
    try:
        for _ in range(30):
            arena.step()
        r = arena.owners.index("L1")
        key = f"omniformation/{FLEET}/arena/drive/L1"
        old = arena.counts.steps - int(STALE_DRIVE_S * scenario.rate_hz) - 5
        future = arena.counts.steps + 10_000  # a truth not yet published: forged, not seen
        for tick in (old, None, future):
            session.put(key, json.dumps({"tick": 1, "truth_tick": tick, "twist": [50.0, 0.0],
                                         "commands": {f"R{r + 1}": [0.3, 0.0]}}))
        wait_for(lambda: arena.counts.stale == 3, 10, "three stale drives counted")
        assert np.all(arena.robot_commands()[r] == 0.0) and np.all(arena.twists[0] == 0.0)
        session.put(key, json.dumps({"tick": 2, "truth_tick": arena.counts.steps, "twist": [50.0, 9.0],
                                     "commands": {f"R{r + 1}": [5.0, 50.0]}}))
        wait_for(lambda: arena.counts.drives == 4, 10, "the fresh drive")
        assert tuple(arena.twists[0]) == pytest.approx((LEADER_SPEED.hi, math.radians(LEADER_TURN.hi)))
        dyn = scenario.dynamics
        # the body's limits, then the wheels' (both scaled together: the same curvature, slower)
        v, w = arena.robot_commands()[r]
        assert 0 < v <= dyn.speed_max_mps and 0 < w <= dyn.turn_max_rps
        assert w / v == pytest.approx(dyn.turn_max_rps / dyn.speed_max_mps, rel=1e-2)
        start = arena.state.leaders[0, :2].copy()
        for _ in range(30):
            arena.step()
        assert float(np.hypot(*(arena.state.leaders[0, :2] - start))) <= LEADER_SPEED.hi * 1.0 + 1e-6
        assert arena.truth()["stale"] == 3 and arena.counts.conflicts == 0
    finally:
        arena.close()
        session.close()


def test_a_leader_left_with_no_robot_waits_and_takes_an_orphan_the_plan_gives_it():
    """A leader whose robots all went to others lets every one go (its state an empty team);
    when the leader holding its last one dies, that robot is an orphan like any other, and the
    plan may give it back. A real arena, a real Zenoh session in-process."""
    with _l1_in_an_arena() as (arena, tokens, team, store, adopter):
        # the operator's handovers: R1, R2 to L3, R3 to L2, and L2's own to L3 (full: 8), so that R3 is L2's only
        moves = ((0, "L3"), (1, "L3"), (2, "L2"), (3, "L3"), (4, "L3"), (5, "L3"))
        with arena._lock:
            assert [arena._hand_over(r, to) for r, to in moves] == [""] * len(moves)
        wait_for(lambda: team.emptied and team.owned == [2], 10, "L1 letting go of every robot")
        team.resize(store.get().n_followers)  # as its loop does when the team changes
        assert team.active == [2] and team.answering().tolist() == [False]  # its last place: another's robot
        tokens.pop("L2").undeclare()  # L2 dies: R3 is an orphan once its lease lapses; L3 has no room
        truth = arena.truth()
        leaders = {lid: (pose[0], pose[1], truth["owners"].count(lid)) for lid, pose in truth["leaders"].items()
                   if lid != "L2"}
        assert adoption_plan([2], np.asarray(truth["robots"])[:, :2], leaders, 8) == {2: "L1"}
        wait_for(lambda: arena.owners[2] == "L1", 20, "R3 claimed by L1")
        wait_for(lambda: not team.emptied and team.owned == [2], 10, "L1's team: R3 again")
        team.resize(store.get().n_followers)
        assert store.get().n_followers == 1 and team.answering().tolist() == [True]


def test_an_arena_on_a_radio_takes_robot_commands_from_the_radio_alone_and_its_robots_judge_strangers():
    """``arena --radio``, in-process: robot commands and claims on the bus move and give nothing
    (counted, refused with the reason); on a leader's radio, garbage bytes are dropped, a
    stranger's DRIVE is refused and a stranger's CLAIM waits for the lease like anyone's (without
    --radio-key the robots hold the open key, so any sender is taken: the truth names it
    ``radio 7``, never a leader of the fleet; with the fleet's key see test_radio_stranger)."""
    import serial

    from app.fleet.arena import Arena
    from app.fleet.bridge import open_session
    from core.link import protocol as p

    scenario = parse_fleet((ROOT / "static_config" / "fleets" / f"{FLEET}.toml").read_text(), FLEET)
    session = open_session([], [])
    arena = Arena(scenario, session, radio=True)
    assert arena.radio is not None
    stop = threading.Event()
    threads = [threading.Thread(target=arena.run, args=(stop,), daemon=True),
               threading.Thread(target=arena.radio.run, args=(stop,), daemon=True)]
    for t in threads:
        t.start()
    token = session.liveliness().declare_token(f"omniformation/{FLEET}/alive/L1")
    port = serial.Serial(arena.radio.paths[0], 115200, timeout=0.05)
    parser = p.FrameParser()
    heard: list[p.Frame] = []

    counter = [0]

    def say(frame: p.Frame) -> p.Frame:  # one frame from radio id 7 on L1's radio; the robot's answer to 7
        counter[0] += 1  # without --radio-key the robots hold the open key: any sender, frames authenticated
        sealed = p.seal(frame, p.OPEN_KEY, 7, counter[0])
        port.write(p.encode_frame(sealed))

        def answer() -> p.Frame | None:
            for f in heard:
                o = p.open_sealed(f, (p.OPEN_KEY,), p.tag_of(sealed)) if f.msg_type >= 0x80 else None
                if o is not None and o.ident == 7 and o.counter == counter[0]:
                    return o.frame
            return None

        def answered() -> bool:
            heard.extend(parser.feed(port.read(256)))
            return answer() is not None

        wait_for(answered, 10, f"the answer to {frame.msg_type:#x}")
        got = answer()
        assert got is not None
        return got

    try:
        wait_for(lambda: "L1" in arena.alive, 10, "L1 alive")
        session.put(f"omniformation/{FLEET}/arena/drive/L1",
                    json.dumps({"tick": 1, "truth_tick": arena.counts.steps, "twist": [0.0, 0.0],
                                "commands": {"R1": [0.3, 0.0], "R2": [0.3, 0.0]}}))
        wait_for(lambda: arena.counts.radio_commands == 2, 10, "the bus's robot commands counted")
        replies = [json.loads(r.ok.payload.to_bytes()) for r in session.get(
            f"omniformation/{FLEET}/arena/claim/L1", payload=json.dumps({"robot": "R4"}), timeout=5.0)]
        assert replies and not replies[0]["granted"] and "over the radio" in replies[0]["why"], replies
        port.write(b"\xa5\x5a\xff\x00garbage\x00\xa5")  # dropped by every robot's parser
        refused = say(p.claim(1, 11, 7, 1000))  # R1's power-up lease still lives
        assert refused.msg_type == p.MSG_NACK and p.decode_ownership(refused).owner == 1
        assert say(p.drive(2, 12, 7, 10, 0.3, 0.0)).msg_type == p.MSG_NACK  # not its owner
        wait_for(lambda: arena.leases[0] == 0, 10, "R1's lease lapsed (nobody drives it)")
        assert say(p.claim(1, 13, 7, 1000)).msg_type == p.MSG_OWNER
        wait_for(lambda: arena.truth()["owners"][0] == "radio 7", 10, "the truth naming the stranger")
        assert np.all(arena.robot_commands()[:, 0] == 0.0) and arena.two_owners == 0  # nothing moved
    finally:
        port.close()
        token.undeclare()
        stop.set()
        for t in threads:
            t.join(5)
        arena.close()
        session.close()
