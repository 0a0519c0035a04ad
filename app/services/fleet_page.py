"""`omniformation fleet`: one page for a whole fleet (paper §6).

Everything comes from the bus (docs/fleet-protocol.md): every leader's state, events and
liveliness, and the arena's truth when there is one. One 3D scene shows the arena's robots
(each in its marker's hue) and leaders, and each leader's own estimates (drawn in the world
through the leader's pose); a panel per leader shows its errors and takes its controls
(STOP, release, gains, leader motion), sent to that leader's command key; *STOP every leader*
goes to the fleet-wide key. A leader takes changes other than STOP only when its operator
started it with ``--fleet-control``; a refusal comes back as its event and is shown.

The page is refreshed ten times a second from the newest messages (the bus is never waited
on). With ``recorder`` every message also goes into one MCAP, a channel per leader.
"""

from __future__ import annotations

import colorsys
import json
import math
import threading
import time
from collections import deque
from collections.abc import Callable
from typing import Any, Protocol

import numpy as np
import viser

from core.bounds import number_default
from core.geometry import leader_to_world

from app.dashboard.controls import add_slider
from app.dashboard.scene import yaw_wxyz
from app.dashboard.widgets import assign, on_page_thread
from app import wire
from app.backends.arena import read_truth
from app.keys import root
from app.fleet.bridge import read_state

REFRESH_S = 0.1
# a state arriving while the page redraws waited up to the GIL's 5 ms switch interval for its callback
# (the bench's p99 was 4.4-5.0 ms): `omniformation fleet` sets app.realtime's SWITCH_INTERVAL_S
GONE_AFTER_S = 2.0  # a leader whose state is older than this is shown as silent
RESYNC_S = 2.0  # after a person moves a control, the leader's own value is shown again after this


def hue_rgb(hue_deg: float) -> tuple[int, int, int]:
    r, g, b = colorsys.hsv_to_rgb((hue_deg % 360.0) / 360.0, 0.85, 0.95)
    return int(r * 255), int(g * 255), int(b * 255)


def refused_text(counts: dict[str, Any]) -> str:
    """``{"conflicts": 2, "claims": 1}`` for people: what was turned away, by kind (nonzero only)."""
    return ", ".join(f"{int(n)} {kind}" for kind, n in counts.items() if isinstance(n, int) and n) or "nothing"


def team_errors_cm(state: dict[str, Any]) -> tuple[float, float]:
    errs = [e for e, ok in zip(state.get("error_m", []), state.get("tracked", [])) if e is not None and ok]
    if not errs:
        return math.nan, math.nan
    return math.sqrt(float(np.mean(np.square(errs)))) * 100, max(errs) * 100


class LeaderPanel:
    """One leader's folder: its status and its controls (each sends a command on the bus)."""

    def __init__(self, view: "FleetView", leader_id: str, order: float) -> None:
        gui = view.server.gui
        self.view = view
        self.leader_id = leader_id
        self.folder = gui.add_folder(f"Leader {leader_id}", order=order)
        with self.folder:
            self.status = gui.add_markdown(f"**{leader_id}**: waiting for its state")
            self.stop = gui.add_button(f"STOP {leader_id}", color="red")
            self.release = gui.add_button(f"Release STOP {leader_id}", color="gray")
            # ranges from the parameter table (core.bounds), as the leader's own page and the bus take them
            self.k_f1 = add_slider(gui, "k_f1", f"{leader_id} k_f1", initial_value=number_default("k_f1"))
            self.k_w2 = add_slider(gui, "k_w2", f"{leader_id} k_w2", initial_value=number_default("k_w2"))
            self.mode = gui.add_dropdown(f"{leader_id} leader mode", options=("stop", "straight", "circle"),
                                         initial_value="straight")
            self.speed = add_slider(gui, "leader_speed_mps", f"{leader_id} leader speed (m/s)", initial_value=0.03)
        self.stop.on_click(lambda _: view.send(leader_id, {"stop": True}))
        self.release.on_click(lambda _: view.send(leader_id, {"stop": False}))
        self.word = "not on the bus"  # for the page's bar: running, STOPPED, not on the bus
        self._synced = False  # the controls show the leader's values once its first state came
        self._moved_at = -math.inf  # when a person last moved one of them
        self.controls = (self.k_f1, self.k_w2, self.mode, self.speed)
        for handle, key in ((self.k_f1, "k_f1"), (self.k_w2, "k_w2"), (self.mode, "leader_mode"),
                            (self.speed, "leader_speed_mps")):
            def changed(event: Any, key: str = key, handle: Any = handle) -> None:
                if event.client is not None:  # a person moved it (not the page following the leader)
                    self._moved_at = time.monotonic()
                    view.send(leader_id, {key: handle.value})
            handle.on_update(changed)

    def update(self, state: dict[str, Any] | None, age_s: float, alive: bool) -> None:
        self.word = ("not on the bus" if not alive else "no state yet" if state is None
                     else "STOPPED" if state.get("stopped") else "running")
        if state is None or not alive:  # a leader not on the bus takes nothing: its controls say so
            self.stop.disabled = not alive
            for handle in (*self.controls, self.release):
                handle.disabled = True
        if state is None:
            self.status.content = f"**{self.leader_id}**: {'alive, no state yet' if alive else 'not on the bus'}"
            return
        if state.get("phase") == "waiting":  # alive, empty-handed (its robots were adopted while it was gone)
            self.status.content = (f"**{self.leader_id}** {'alive' if alive else '**gone** (token lost)'}: owns no"
                                   " robot, waiting for one (Hand over a robot)")
            for handle in self.controls:
                handle.disabled = True
            self.release.disabled = True
            return
        rms, worst = team_errors_cm(state)
        n = len(state.get("p_est", []))
        tracked = sum(bool(t) for t in state.get("tracked", []))
        v, w = (state.get("leader_twist") or [0.0, 0.0])[:2]
        where = "alive" if alive else "**gone** (token lost)"
        if age_s > GONE_AFTER_S:
            where += f", silent for {age_s:.0f} s"
        stop = " · **STOPPED**" if state.get("stopped") else ""
        self.status.content = (
            f"**{self.leader_id}** {where}{stop}  \n{tracked}/{n} followers tracked, phase {state.get('phase', '?')}  \n"
            f"error RMS {rms:.1f} cm, worst {worst:.1f} cm  \nleader v {v or 0.0:.2f} m/s, ω {w or 0.0:.2f} rad/s,"
            f" loop {state.get('rate_hz') or 0.0:.1f} Hz")
        # what the leader obeys from here: a STOP-only leader (no --fleet-control) refuses the rest,
        # releasing its STOP included; Release is offered only to a stopped team
        all_of_it = state.get("takes") == "all"
        for handle in self.controls:
            handle.disabled = not all_of_it
        self.release.disabled = not (all_of_it and bool(state.get("stopped"))) or not alive
        self.stop.disabled = bool(state.get("stopped")) or not alive  # nothing to stop: the button says so
        if not alive:
            for handle in self.controls:
                handle.disabled = True
        if not all_of_it:
            self.status.content += "  \ntakes only STOP from here (started without --fleet-control)"
        refused = state.get("refused")
        if isinstance(refused, dict) and any(refused.values()):
            self.status.content += "  \nrefused: " + refused_text(refused)
        # the controls show what the leader runs with: a refused or clamped value does not stay on
        # the slider (a person's own move is left alone for a moment, while the leader answers)
        if not self._synced or time.monotonic() - self._moved_at > RESYNC_S:
            gains = state.get("gains", {})
            assign(self.k_f1, float(gains.get("k_f1", self.k_f1.value)))
            assign(self.k_w2, float(gains.get("k_w2", self.k_w2.value)))
            self._synced = True


class FleetSink(Protocol):
    """Where the page also hands every bus message: the fleet recording (FleetRecorder),
    Foxglove live, or both."""

    def write(self, topic: str, msg: dict[str, Any]) -> None: ...

    def status(self) -> str: ...


class FleetView:
    """The fleet page on one viser server, fed from the bus."""

    def __init__(self, server: viser.ViserServer, session: Any, fleet: str,
                 recorder: FleetSink | None = None, allow_viewer: Callable[..., None] | None = None) -> None:
        """``allow_viewer``: marks the controls a view-only client may press (the STOPs; the gate's)."""
        import zenoh

        self.server = server
        self.session = session
        self.fleet = fleet
        self.recorder = recorder
        self._zenoh = zenoh
        self._lock = threading.Lock()
        self.truth: dict[str, Any] | None = None
        # the page's own token (with the fleet's keys the page writes this, commands and handovers only)
        self._token = session.liveliness().declare_token(f"{root(fleet)}/page/alive")
        self.states: dict[str, tuple[float, dict[str, Any]]] = {}  # id -> (monotonic time received, state)
        self.alive: set[str] = set()
        self.events: deque[str] = deque(maxlen=12)
        self.received = 0
        self.malformed = 0
        self.latencies: deque[float] = deque(maxlen=2000)  # s from a state's "sent" (when given) to here
        server.gui.configure_theme(control_width="large", dark_mode=False)
        gui = server.gui
        self.stop_all = gui.add_button("STOP every leader", color="red", order=0)
        self.status = gui.add_markdown("fleet: connecting ...", order=1)
        self.event_text = gui.add_markdown("", order=1000)
        self.stop_all.on_click(lambda _: self.send_all_stop())
        self._allow_viewer = allow_viewer or (lambda *_: None)
        self._allow_viewer(self.stop_all)
        with gui.add_folder("Hand over a robot", order=900, expand_by_default=False):
            self.hand_robot = gui.add_dropdown("robot", options=("-",), initial_value="-")
            self.hand_to = gui.add_dropdown("to leader", options=("-",), initial_value="-")
            self.hand_button = gui.add_button("Hand over")
        def hand(_: Any) -> None:
            self.hand_over(str(self.hand_robot.value), str(self.hand_to.value))

        self.hand_button.on_click(hand)
        self.panels: dict[str, LeaderPanel] = {}
        self._scene: dict[str, Any] = {}
        server.scene.add_grid("/grid", width=20, height=20, cell_size=0.5, plane="xy")
        self._subs = [
            session.declare_subscriber(f"{root(fleet)}/arena/truth", self._on_truth),
            session.declare_subscriber(f"{root(fleet)}/leader/*/state", self._on_state),
            session.declare_subscriber(f"{root(fleet)}/leader/*/events", self._on_event),
            session.declare_subscriber(f"{root(fleet)}/arena/events", self._on_event),
            session.liveliness().declare_subscriber(f"{root(fleet)}/alive/*", self._on_alive, history=True),
        ]
        self._stop = threading.Event()
        self._thread = threading.Thread(target=self._refresh_loop, name="omniformation-fleet-page", daemon=True)
        self._thread.start()

    # -- in ------------------------------------------------------------------------------------
    def _decode(self, sample: Any) -> dict[str, Any] | None:
        try:
            msg = wire.decode(sample.payload.to_bytes())
        except wire.BadMessage:
            msg = None
        if not isinstance(msg, dict):
            with self._lock:
                self.malformed += 1
            return None
        return msg

    def _on_truth(self, sample: Any) -> None:
        msg = self._decode(sample)
        try:
            msg = read_truth(msg) if msg is not None else None
        except wire.BadMessage:
            with self._lock:
                self.malformed += 1
            msg = None
        if msg is None:
            return
        with self._lock:
            self.truth = msg
        if self.recorder is not None:
            self.recorder.write("arena/truth", msg)

    def _on_state(self, sample: Any) -> None:
        now, arrived = time.monotonic(), time.time()
        msg = self._decode(sample)
        leader = str(sample.key_expr).split("/")[-2]
        try:
            msg = read_state(msg) if msg is not None else None
        except wire.BadMessage:
            with self._lock:
                self.malformed += 1
            msg = None
        if msg is None:
            return
        sent = msg.get("sent")
        with self._lock:
            self.states[leader] = (now, msg)
            self.received += 1
            if isinstance(sent, (int, float)):
                self.latencies.append(arrived - float(sent))
        if self.recorder is not None:
            self.recorder.write(f"{leader}/state", msg)

    def _on_event(self, sample: Any) -> None:
        msg = self._decode(sample)
        if msg is None:
            return
        parts = str(sample.key_expr).split("/")
        who = parts[-2] if parts[-3] == "leader" else "arena"
        with self._lock:
            self.events.append(f"{who}: {msg.get('kind', '?')} — {str(msg.get('detail', ''))[:160]}")
        if self.recorder is not None:
            self.recorder.write(f"{who}/events", msg)

    def _on_alive(self, sample: Any) -> None:
        leader = str(sample.key_expr).rsplit("/", 1)[-1]
        with self._lock:
            if sample.kind == self._zenoh.SampleKind.PUT:
                self.alive.add(leader)
            else:
                self.alive.discard(leader)
            self.events.append(f"{leader}: {'joined' if sample.kind == self._zenoh.SampleKind.PUT else 'token lost'}")

    # -- out -----------------------------------------------------------------------------------
    def send(self, leader_id: str, changes: dict[str, Any]) -> None:
        self.session.put(f"{root(self.fleet)}/leader/{leader_id}/cmd",
                         json.dumps({"set": changes, "from": "fleet-dashboard"}))

    def hand_over(self, robot: str, to: str) -> str:
        """Ask the arena to give ``robot`` to leader ``to`` (e.g. back to a leader that came back
        empty-handed); the answer goes to the events and is returned."""
        if robot == "-" or to == "-":
            answer = "hand over: pick a robot and a leader first"
        else:
            answer = f"hand over {robot} to {to}: no arena answered"
            payload = json.dumps({"robot": robot, "to": to, "from": "fleet-dashboard"})
            for reply in self.session.get(f"{root(self.fleet)}/arena/handover", payload=payload, timeout=3.0):
                try:
                    got = json.loads(reply.ok.payload.to_bytes())
                except (AttributeError, ValueError, TypeError):
                    continue
                answer = (f"hand over {robot} to {to}: " + ("done" if got.get("granted") else
                                                             f"refused ({got.get('why', '?')})"))
        with self._lock:
            self.events.append(answer)
        return answer

    def send_all_stop(self) -> None:
        self.session.put(f"{root(self.fleet)}/all/cmd", json.dumps({"set": {"stop": True}, "from": "fleet-dashboard"}))

    # -- the page ------------------------------------------------------------------------------
    def _refresh_loop(self) -> None:
        while not self._stop.wait(REFRESH_S):
            try:
                on_page_thread(self.server, self.refresh)  # viser's thread: widgets.on_page_thread says why
            except Exception:
                import logging

                logging.getLogger(__name__).exception("fleet page refresh failed")

    def refresh(self) -> None:
        now = time.monotonic()
        with self._lock:
            truth = self.truth
            states = dict(self.states)
            alive = set(self.alive)
            events = list(self.events)
        ids = sorted(set(states) | alive | (set(truth["leaders"]) if truth else set()))
        for lid in ids:
            if lid not in self.panels:
                self.panels[lid] = LeaderPanel(self, lid, order=10 + len(self.panels))
                self._allow_viewer(self.panels[lid].stop)
        with self.server.atomic():
            for lid in ids:
                at, st = states.get(lid, (now, None))
                self.panels[lid].update(st, now - at, lid in alive)
            arena = "no arena" if truth is None else (f"arena t {truth.get('t', 0):.0f} s, {len(truth['robots'])} robots,"
                                                      f" conflicts {truth.get('conflicts', 0)}")
            dog = truth.get("watchdog") if truth is not None else None
            if isinstance(dog, list) and any(dog):  # in words: which robots their own watchdog holds, and why
                arena += ("; stopped by their watchdog (their leader went quiet): "
                          + ", ".join(f"R{r + 1}" for r, on in enumerate(dog) if on is True))
            refused = truth.get("refused") if truth is not None else None
            if isinstance(refused, dict):
                arena += f"; arena refused: {refused_text(refused) if any(refused.values()) else 'nothing'}"
            rec = "" if self.recorder is None else f"  \n{self.recorder.status()}"
            each = " · ".join(f"{lid} {self.panels[lid].word}" for lid in
                              sorted(ids, key=lambda lid: (self.panels[lid].word != "STOPPED", lid)))
            self.status.content = (f"**leaders** {each or 'none yet'}  \n**fleet {self.fleet}**: leaders alive {', '.join(sorted(alive)) or 'none'};"
                                   f" {arena}{rec}")
            self.event_text.content = "**events**  \n" + "  \n".join(reversed(events)) if events else ""
            robots = tuple(f"R{r + 1}" for r in range(len(truth["robots"]))) if truth else ("-",)
            if tuple(self.hand_robot.options) != robots:
                self.hand_robot.options = robots
            leaders = tuple(sorted(alive)) or ("-",)
            if tuple(self.hand_to.options) != leaders:
                self.hand_to.options = leaders
            self._draw(truth, states)

    def _draw(self, truth: dict[str, Any] | None, states: dict[str, tuple[float, dict[str, Any]]]) -> None:
        s = self.server.scene
        if truth is not None:
            hues = truth.get("hues_deg", [])
            for r, pose in enumerate(truth["robots"]):
                key = f"/arena/robots/{r}"
                if key not in self._scene:
                    rgb = hue_rgb(hues[r]) if r < len(hues) else (120, 120, 120)
                    self._scene[key] = s.add_box(key, color=rgb, dimensions=(0.25, 0.15, 0.10))
                    s.add_label(f"{key}/label", f"R{r + 1}", position=(0, 0, 0.25))
                h = self._scene[key]
                h.position = (float(pose[0]), float(pose[1]), 0.05)
                h.wxyz = yaw_wxyz(float(pose[2]))
            for lid, pose in truth["leaders"].items():
                key = f"/arena/leaders/{lid}"
                if key not in self._scene:
                    self._scene[key] = s.add_cylinder(key, radius=0.17, height=0.3, color=(40, 40, 40))
                    s.add_label(f"{key}/label", lid, position=(0, 0, 0.45))
                self._scene[key].position = (float(pose[0]), float(pose[1]), 0.15)
        for lid, (_, st) in states.items():  # each leader's own view, through its pose
            pose = st.get("leader") or [0.0, 0.0, math.pi / 2]
            p_est = np.array([[math.nan if v is None else v for v in p] for p in st.get("p_est", [])], dtype=float)
            p_d = np.array([[math.nan if v is None else v for v in p] for p in st.get("p_d", [])], dtype=float)
            if p_est.size == 0:
                continue
            est = leader_to_world(p_est.reshape(-1, 2), np.asarray(pose[:2], dtype=float), float(pose[2]))
            goal = leader_to_world(p_d.reshape(-1, 2), np.asarray(pose[:2], dtype=float), float(pose[2]))
            for kind, pts, colour, size in (("estimates", est, (30, 90, 220), 0.05), ("slots", goal, (220, 40, 40), 0.04)):
                key = f"/teams/{lid}/{kind}"
                pts3 = np.column_stack([np.nan_to_num(pts), np.full(len(pts), 0.12)]).astype(np.float32)
                if key not in self._scene or self._scene[key].points.shape != pts3.shape:
                    if key in self._scene:
                        self._scene[key].remove()
                    self._scene[key] = s.add_point_cloud(key, points=pts3, colors=colour, point_size=size)
                else:
                    self._scene[key].points = pts3

    def close(self) -> None:
        self._stop.set()
        self._thread.join(5.0)
        for sub in self._subs:
            sub.undeclare()
        self._token.undeclare()
