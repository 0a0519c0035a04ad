"""The fleet page's widgets (paper §6): a folder per leader, the fleet's status and events, the
hand-over folder and the 3D arena. They show what they are handed and call back what a person
pressed; the bus (subscriptions, decoding, sending) is app.services.fleet_page's."""

from __future__ import annotations

import math
import time
from collections.abc import Callable, Sequence
from dataclasses import dataclass, field
from typing import Any, Protocol

import numpy as np
import viser

from core.bounds import number_default
from core.camera.render.looks import hue_rgb
from core.geometry import leader_to_world

from app.dashboard.controls import add_slider
from app.dashboard.scene import yaw_wxyz
from app.dashboard.widgets import assign
from app.keys import held_name, robot_index, robot_name

GONE_AFTER_S = 2.0  # a leader whose state is older than this is shown as silent
RESYNC_S = 2.0  # after a person moves a control, the leader's own value is shown again after this


def refused_text(counts: dict[str, Any]) -> str:
    """``{"conflicts": 2, "claims": 1}`` for people: what was turned away, by kind (nonzero only)."""
    return ", ".join(f"{int(n)} {kind}" for kind, n in counts.items() if isinstance(n, int) and n) or "nothing"


def team_errors_cm(state: dict[str, Any]) -> tuple[float, float]:
    errs = [e for e, ok in zip(state.get("error_m", []), state.get("tracked", [])) if e is not None and ok]
    if not errs:
        return math.nan, math.nan
    return math.sqrt(float(np.mean(np.square(errs)))) * 100, max(errs) * 100


def watchdog_text(held: Sequence[Any], stops: int) -> str:
    """The robots' watchdogs in words: how many stops so far, and which robots one holds now."""
    words = f"{stops} watchdog stop{'' if stops == 1 else 's'} since this page started"
    now = [robot_name(r) for r, on in enumerate(held) if on is True]
    if now:  # which robots their own watchdog holds, and why
        words += f"; stopped by their watchdog now (their leader went quiet): {', '.join(now)}"
    return words


def slots_of(states: dict[str, tuple[float, dict[str, Any]]], count: int) -> dict[int, tuple[str, int]]:
    """robot index -> (leader id, its follower slot) from the leaders' states (their ``robots``)."""
    held: dict[int, tuple[str, int]] = {}
    for lid, (_, st) in states.items():
        for k, name in enumerate(st.get("robots") or []):
            r = robot_index(name, count)
            if r is not None:
                held[r] = (lid, k)
    return held


class Sender(Protocol):
    """What a leader's panel sends its changes through (the fleet page's bus)."""

    server: viser.ViserServer

    def send(self, leader_id: str, changes: dict[str, Any]) -> None: ...


class LeaderPanel:
    """One leader's folder: its status and its controls (each sends a command on the bus)."""

    def __init__(self, view: Sender, leader_id: str, order: float) -> None:
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
        robots = [f"{name} (F{k + 1})" for k, name in enumerate(state.get("robots") or [])]
        self.status.content = (
            f"**{self.leader_id}** {where}{stop}  \n{tracked}/{n} followers tracked, phase {state.get('phase', '?')}  \n"
            + (f"robots {', '.join(robots)}  \n" if robots else "")
            + f"error RMS {rms:.1f} cm, worst {worst:.1f} cm  \nleader v {v or 0.0:.2f} m/s, ω {w or 0.0:.2f} rad/s,"
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


@dataclass
class FleetSnapshot:
    """What the fleet page shows at one refresh, as the bus gave it."""

    fleet: str
    truth: dict[str, Any] | None
    states: dict[str, tuple[float, dict[str, Any]]]  # id -> (monotonic time received, state)
    alive: set[str]
    events: list[str]
    watchdog_stops: int = 0  # the robots' transitions into their watchdog's hold, counted by the page
    extra: str = ""  # what else is said under the status (the recording's and Foxglove's state)
    now: float = field(default_factory=time.monotonic)


class FleetPage:
    """The fleet page's widgets on one viser server: STOP every leader, the status, a panel per
    leader, the hand-over folder, the events and the 3D arena. ``send``, ``send_all_stop`` and
    ``hand_over`` are the bus's; ``allow_viewer`` marks the controls a view-only client may press."""

    def __init__(self, server: viser.ViserServer, send: Callable[[str, dict[str, Any]], None],
                 send_all_stop: Callable[[], None], hand_over: Callable[[str, str], Any],
                 allow_viewer: Callable[..., None] | None = None) -> None:
        self.server = server
        self._send = send
        server.gui.configure_theme(control_width="large", dark_mode=False)
        gui = server.gui
        self.stop_all = gui.add_button("STOP every leader", color="red", order=0)
        self.status = gui.add_markdown("fleet: connecting ...", order=1)
        self.event_text = gui.add_markdown("", order=1000)
        self.stop_all.on_click(lambda _: send_all_stop())
        self._allow_viewer = allow_viewer or (lambda *_: None)
        self._allow_viewer(self.stop_all)
        with gui.add_folder("Hand over a robot", order=900, expand_by_default=False):
            self.hand_robot = gui.add_dropdown("robot", options=("-",), initial_value="-")
            self.hand_to = gui.add_dropdown("to leader", options=("-",), initial_value="-")
            self.hand_button = gui.add_button("Hand over")

        def hand(_: Any) -> None:
            hand_over(str(self.hand_robot.value), str(self.hand_to.value))

        self.hand_button.on_click(hand)
        self.panels: dict[str, LeaderPanel] = {}
        self._scene: dict[str, Any] = {}
        self.labels: dict[int, tuple[Any, str]] = {}  # robot -> (its 3D label, the text it shows)
        server.scene.add_grid("/grid", width=20, height=20, cell_size=0.5, plane="xy")
        # No shadows: an overview of where the robots are needs none, and a browser without a GPU
        # redraws every shadow map each time a robot moves. With them, such a browser drew this page
        # at 0.5-2 frames a second once the leaders drove, and a click waited 8-12 s for it
        # (docs/page-access.md).
        server.scene.configure_default_lights(enabled=True, cast_shadow=False)

    def send(self, leader_id: str, changes: dict[str, Any]) -> None:
        self._send(leader_id, changes)

    def show(self, snap: FleetSnapshot) -> None:
        """Every widget from one snapshot of the bus (on viser's thread: widgets.on_page_thread)."""
        truth, states, alive = snap.truth, snap.states, snap.alive
        ids = sorted(set(states) | alive | (set(truth["leaders"]) if truth else set()))
        for lid in ids:
            if lid not in self.panels:
                self.panels[lid] = LeaderPanel(self, lid, order=10 + len(self.panels))
                self._allow_viewer(self.panels[lid].stop)
        with self.server.atomic():
            for lid in ids:
                at, st = states.get(lid, (snap.now, None))
                self.panels[lid].update(st, snap.now - at, lid in alive)
            arena = "no arena" if truth is None else (f"arena t {truth.get('t', 0):.0f} s, {len(truth['robots'])} robots,"
                                                      f" conflicts {truth.get('conflicts', 0)}")
            dog = truth.get("watchdog") if truth is not None else None
            if isinstance(dog, list):
                arena += "; " + watchdog_text(dog, snap.watchdog_stops)
            refused = truth.get("refused") if truth is not None else None
            if isinstance(refused, dict):
                arena += f"; arena refused: {refused_text(refused) if any(refused.values()) else 'nothing'}"
            extra = f"  \n{snap.extra}" if snap.extra else ""
            each = " · ".join(f"{lid} {self.panels[lid].word}" for lid in
                              sorted(ids, key=lambda lid: (self.panels[lid].word != "STOPPED", lid)))
            self.status.content = (f"**leaders** {each or 'none yet'}  \n**fleet {snap.fleet}**: leaders alive"
                                   f" {', '.join(sorted(alive)) or 'none'}; {arena}{extra}")
            self.event_text.content = "**events**  \n" + "  \n".join(reversed(snap.events)) if snap.events else ""
            robots = tuple(robot_name(r) for r in range(len(truth["robots"]))) if truth else ("-",)
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
            held = slots_of(states, len(truth["robots"]))
            for r, pose in enumerate(truth["robots"]):
                key = f"/arena/robots/{r}"
                if key not in self._scene:
                    rgb = hue_rgb(hues[r]) if r < len(hues) else (120, 120, 120)
                    self._scene[key] = s.add_box(key, color=rgb, dimensions=(0.25, 0.15, 0.10))
                # the robot's one name (the fleet's R id) and, while a leader drives it, whose slot it is
                text = held_name(r, *held[r]) if r in held else robot_name(r)
                label = self.labels.get(r)
                if label is None or label[1] != text:
                    if label is not None:
                        label[0].remove()
                    self.labels[r] = (s.add_label(f"{key}/label", text, position=(0, 0, 0.25)), text)
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
