"""The fleet page in real Chromium: an arena and two leaders on a loopback Zenoh bus, one page
for both; its fleet-wide STOP reaches every leader, a team's own controls reach that leader
(or come back refused when its operator did not allow the bus to command it), and the whole
fleet is recorded into one MCAP with a channel per leader."""

from __future__ import annotations

import json
import threading

import pytest

from app.dashboard.gate import quietly, serve_gated
from app.files import load_fleet
from app.fleet.arena import Arena
from app.backends.arena import ArenaTeam
from app.fleet.adopter import Adopter
from app.fleet.bridge import FleetBridge, loopback_endpoint, open_session
from app.services.fleet_page import FleetView
from app.recording.fleet import FleetRecorder
from app.dashboard import Dashboard
from app.live.loop import ServiceLoop
from app.backends.world import Backends
from app.params import Params, ParamsStore, default_slots
from app.tick import LatestStatePublisher

from tests.helpers import ARTIFACTS, chromium_browser, control_id, new_page, settle, wait_for

pytest.importorskip("playwright.sync_api")
pytest.importorskip("zenoh")


# every light of the page's three.js scene, [type, casts a shadow], found from a node viser named
SCENE_LIGHTS = """() => { let o = window.__viserMutable.nodeRefFromName['/grid']; while (o.parent) o = o.parent;
    const out = []; o.traverse(x => { if (x.isLight) out.push([x.type, x.castShadow]); }); return out; }"""


class Leader:
    """A leader as `run --arena` makes one, without its own page: loop, arena team, bridge."""

    def __init__(self, endpoint: str, fleet: str, leader_id: str, allow_control: bool, page: bool = False) -> None:
        """``page``: with its own page too (the operator's dashboard, drawn from its loop)."""
        self.session = open_session([], [endpoint])
        self.team = ArenaTeam(self.session, fleet, leader_id, 0.003, 0.01, seed=1)
        n = len(self.team.owned)
        self.store = ParamsStore(Params(n_followers=n, slots=default_slots(n), leader_mode="straight",
                                        leader_speed_mps=0.02), fixed_followers=n)
        self.loop = ServiceLoop(self.store, Backends(arena=self.team), rate_hz=30.0)
        self.bridge = FleetBridge(self.store, fleet, leader_id, allow_control=allow_control, session=self.session)
        self.loop.subscribe(self.bridge.on_tick)
        self.adopter = Adopter(self.session, fleet, leader_id, self.team, self.store, event=self.bridge.event)
        self.server = self.gate = self.publisher = None
        if page:
            self.server, self.gate = serve_gated("127.0.0.1", 0)
            self.publisher = LatestStatePublisher(Dashboard(self.server, self.store).publish)
            self.loop.subscribe(self.publisher)
        self.thread = threading.Thread(target=self.loop.run, daemon=True)
        self.thread.start()

    def close(self) -> None:
        self.loop.stop()
        self.thread.join(10)
        if self.publisher is not None:
            self.publisher.close()
            self.gate.close()
            quietly(self.server.stop)
        self.adopter.close()
        self.bridge.close()
        self.session.close()


def test_one_page_for_the_fleet_stops_every_leader_and_commands_each_team(tmp_path):
    endpoint = loopback_endpoint()
    scenario = load_fleet("three_teams")
    arena_session = open_session([endpoint], [])
    arena = Arena(scenario, arena_session)
    stop_arena = threading.Event()
    stepper = threading.Thread(target=arena.run, args=(stop_arena,), daemon=True)
    stepper.start()
    leaders: list[Leader] = []
    page_session = server = gate = view = recorder = None
    try:
        leaders = [Leader(endpoint, "three_teams", "L1", True, page=True), Leader(endpoint, "three_teams", "L2", False)]
        page_session = open_session([], [endpoint])
        server, gate = serve_gated("127.0.0.1", 0)
        gate.page_kind = "fleet"
        recorder = FleetRecorder(tmp_path / "fleet.mcap")
        view = FleetView(server, page_session, "three_teams", recorder)
        l1, l2 = leaders
        with chromium_browser() as browser:
            page = new_page(browser, 1500, 1200, scene=False)  # the fleet's panels, not the 3D view
            page.goto(gate.url)
            page.get_by_text("Leader L1", exact=True).first.wait_for(timeout=60_000)
            page.get_by_text("Leader L2", exact=True).first.wait_for(timeout=60_000)
            settle(page)
            # the status names both leaders and the arena (L3 never joined: its robots stand still)
            page.get_by_text("leaders alive L1, L2", exact=False).first.wait_for(timeout=30_000)
            page.get_by_text("9 robots", exact=False).first.wait_for(timeout=30_000)
            page.get_by_text("3/3 followers tracked", exact=False).first.wait_for(timeout=90_000)  # a vision start-up, loaded machine
            # no light of the page's 3D view casts a shadow (a browser without a GPU drew this page at
            # 0.5-2 frames a second with them once the robots moved, and every click waited for a frame)
            lights = page.evaluate(SCENE_LIGHTS)
            assert lights and not any(casts for _, casts in lights), lights

            page.get_by_role("button", name="STOP every leader").click()
            wait_for(lambda: l1.store.get().stop and l2.store.get().stop, 30, "every leader stopped")
            wait_for(lambda: all(v == [0.0, 0.0] for v in l1.loop.last.commands.tolist()), 30, "L1 at zero")
            wait_for(lambda: l2.loop.last.leader_twist == (0.0, 0.0), 30, "L2's own base stopped too")
            # the bar names each leader; a stopped leader's STOP is disabled; L3 (never on the bus) has
            # every control disabled
            bar = page.locator("#omni-stopstate")
            wait_for(lambda: "L1 STOPPED" in bar.inner_text() and "L2 STOPPED" in bar.inner_text(), 30, "the bar's leaders")
            wait_for(lambda: page.get_by_role("button", name="STOP L1", exact=True).is_disabled(), 30, "STOP L1 disabled")
            assert "L3" in view.panels  # the arena's truth names it: it has a panel, every control disabled
            assert "L3 not on the bus" in bar.inner_text(), bar.inner_text()
            assert page.get_by_role("button", name="STOP L3", exact=True).is_disabled()
            assert all(h.disabled for h in (*view.panels["L3"].controls, view.panels["L3"].release))
            assert page.locator(f'[id="{control_id(page, "L3 leader mode")}"]').first.is_disabled()  # in the browser too
            assert page.get_by_role("button", name="Release STOP L3", exact=True).is_disabled()

            # L1 takes the page's commands; L2's operator did not allow it (STOP only): its controls and
            # Release are disabled, and say why; a release sent on the bus anyway is refused, and said so
            page.get_by_text("takes only STOP from here", exact=False).first.wait_for(timeout=30_000)
            assert page.get_by_role("button", name="Release STOP L2").is_disabled()
            assert page.get_by_role("button", name="Release STOP L1").is_enabled()  # stopped, and it takes all
            page.get_by_role("button", name="Release STOP L1").click()
            wait_for(lambda: not l1.store.get().stop, 30, "L1 released")
            wait_for(lambda: page.get_by_role("button", name="Release STOP L1").is_disabled(), 30,
                     "Release L1 disabled once it runs")
            wait_for(lambda: "L1 running" in bar.inner_text() and "L2 STOPPED" in bar.inner_text(), 30,
                     "the bar: L2 STOPPED while L1 runs")
            assert page.get_by_role("button", name="STOP L1", exact=True).is_enabled()
            page_session.put("omniformation/three_teams/leader/L2/cmd", json.dumps({"set": {"stop": False}, "from": "test"}))
            page.get_by_text("L2: refused", exact=False).first.wait_for(timeout=30_000)
            assert l2.store.get().stop
            page.get_by_role("button", name="STOP L1", exact=True).click()
            wait_for(lambda: l1.store.get().stop, 30, "L1 stopped again")
            # bad messages on the arena's keys are counted and dropped; a robot is moved by its owner only
            base = "omniformation/three_teams/arena"
            malformed, conflicts = arena.counts.malformed, arena.counts.conflicts
            page_session.put(f"{base}/drive/L1", b"{not json")
            page_session.put(f"{base}/drive/L1", json.dumps({"twist": [0, 0], "commands": {"R99": [1, 0]}}))
            page_session.put(f"{base}/drive/L9", json.dumps({"twist": [0, 0], "commands": {}}))
            page_session.put(f"{base}/drive/L2", json.dumps({"twist": [0, 0], "commands": {"R1": [0.3, 0.0]}}))
            wait_for(lambda: arena.counts.malformed == malformed + 3 and arena.counts.conflicts == conflicts + 1, 30,
                     "three malformed drives and one conflict")
            replies = [json.loads(r.ok.payload.to_bytes()) for r in page_session.get(
                f"{base}/claim/L2", payload=json.dumps({"leader": "L2", "robot": "R1"}), timeout=5.0)]
            assert replies and not replies[0]["granted"] and "R1 is L1's, its lease lives" in replies[0]["why"], replies
            replies = [json.loads(r.ok.payload.to_bytes()) for r in page_session.get(  # one id asking for another
                f"{base}/claim/L2", payload=json.dumps({"leader": "L1", "robot": "R7"}), timeout=5.0)]
            assert replies and not replies[0]["granted"] and "is L2's, not 'L1'" in replies[0]["why"], replies
            replies = [json.loads(r.ok.payload.to_bytes()) for r in page_session.get(
                f"{base}/claim/L1", payload=b"nonsense", timeout=5.0)]
            assert replies and not replies[0]["granted"], replies
            assert arena.owners[0] == "L1"
            # a token under a name that leads no team is counted and can be given nothing
            squatter = page_session.liveliness().declare_token("omniformation/three_teams/alive/X9")
            wait_for(lambda: arena.counts.strangers == 1, 10, "the stranger's token counted")
            replies = [json.loads(r.ok.payload.to_bytes()) for r in page_session.get(
                f"{base}/handover", payload=json.dumps({"robot": "R7", "to": "X9", "from": "test"}), timeout=5.0)]
            assert replies and not replies[0]["granted"] and "X9 is not alive" in replies[0]["why"], replies
            squatter.undeclare()
            # what the arena refused is on the page, by kind
            from app.dashboard.fleet_view import refused_text

            said = refused_text(arena.refused())
            assert "1 conflicts" in said and "2 claims" in said and "malformed" in said, said
            page.get_by_text(f"arena refused: {said}", exact=False).first.wait_for(timeout=30_000)

            # the operator hands a robot of the leader that never came (L3's R7) to L1: it joins L1's team
            page.get_by_text("Hand over a robot", exact=True).first.click()
            for label, option in (("robot", "R7"), ("to leader", "L1")):
                page.locator(f'[id="{control_id(page, label)}"]').first.click()
                page.get_by_role("option", name=option, exact=True).click()
            wait_for(lambda: view.hand_robot.value == "R7" and view.hand_to.value == "L1", 30, "the two choices")
            page.get_by_role("button", name="Hand over", exact=True).click()
            page.get_by_text("hand over R7 to L1: done", exact=False).first.wait_for(timeout=30_000)
            assert arena.owners[6] == "L1"
            wait_for(lambda: l1.team.owned == [0, 1, 2, 6] and l1.store.get().n_followers == 4, 30, "R7 in L1's team")
            wait_for(lambda: l1.loop.last is not None and l1.loop.last.n == 4, 30, "L1's loop driving four")
            # one name per robot, the fleet's: R7 is L1's fourth follower, "R7 (F4)" on L1's own page and in
            # L1's panel here, and its label in the fleet page's 3D view says who holds it, "R7 · L1 F4"
            page.get_by_text("robots R1 (F1), R2 (F2), R3 (F3), R7 (F4)", exact=False).first.wait_for(timeout=30_000)
            wait_for(lambda: view.page.labels.get(6, (None, ""))[1] == "R7 · L1 F4", 30, "R7's label in 3D")
            assert view.page.labels[0][1] == "R1 · L1 F1" and view.page.labels[3][1] == "R4 · L2 F1"
            assert view.page.labels[8][1] == "R9"  # L3's, never driven: held by no leader here
            own = new_page(browser, 1500, 1000, scene=False)
            own.goto(l1.gate.url)
            own.get_by_text("R7 (F4)", exact=False).first.wait_for(timeout=60_000)  # the status's errors
            own.close()
            # a leader that goes quiet (its loop ends, its token stays): its robots' own watchdogs stop them,
            # and the page says so in words, with the count of stops it saw
            l2.loop.stop()
            l2.thread.join(10)
            wait_for(lambda: view.watchdog_stops >= 3, 30, "L2's three robots stopped by their watchdogs")
            page.get_by_text("stopped by their watchdog now (their leader went quiet): R4, R5, R6",
                             exact=False).first.wait_for(timeout=30_000)
            seen = view.watchdog_stops
            assert seen <= arena.counts.watchdog_stops, (seen, arena.counts.watchdog_stops)
            page.get_by_text(f"{seen} watchdog stops since this page started", exact=False).first.wait_for(timeout=30_000)
            ARTIFACTS.mkdir(parents=True, exist_ok=True)
            page.screenshot(path=str(ARTIFACTS / "fleet_page.png"))
    finally:
        if view is not None:
            view.close()
        if recorder is not None:
            recorder.close()
        if gate is not None:
            gate.close()
        if server is not None:
            quietly(server.stop)
        for ld in leaders:
            ld.close()
        if page_session is not None:
            page_session.close()
        stop_arena.set()
        stepper.join(10)
        arena.close()
        arena_session.close()
    # the whole fleet in one file: a channel per leader, the arena's truth, the events
    from mcap.reader import make_reader

    with open(tmp_path / "fleet.mcap", "rb") as f:
        counts: dict[str, int] = {}
        stops = 0
        for _, channel, message in make_reader(f).iter_messages():
            counts[channel.topic] = counts.get(channel.topic, 0) + 1
            if channel.topic == "/fleet/L2/events" and json.loads(message.data)["kind"] == "refused":
                stops += 1
    assert counts.get("/fleet/L1/state", 0) > 30 and counts.get("/fleet/L2/state", 0) > 30, counts
    assert counts.get("/fleet/arena/truth", 0) > 30 and counts.get("/fleet/L1/events", 0) >= 2, counts
    assert stops >= 1, counts
    assert arena.counts.conflicts == 1  # the one sent on purpose above: the leaders themselves never conflict
