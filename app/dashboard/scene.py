"""3D view: floor grid, leader with camera and working-area ring, followers with heading
arrows, the desired formation polygon with draggable slot handles, trails, truth ghosts."""

from __future__ import annotations

import logging
import math
import time
from collections import deque
from collections.abc import Callable
from typing import Any

import numpy as np
import viser

from core.geometry import leader_to_world
from core.obstacles import Obstacle

from core.camera.render.looks import follower_rgb
from app.dashboard.controls import CARD_HINT, Controls
from app.tick import TickState
from app.params import ParamsStore
from app.refusals import refuse
from core.camera.guide import WORKING_RING_M

log = logging.getLogger(__name__)

TRAIL_SECONDS = 20.0


SLOT_Z_M = 0.16  # slot dots above a follower's body (0.11 m high): a settled robot does not hide its slot
BEHIND_M, BEHIND_UP_M = 2.5, 2.0  # the "behind the leader" camera: this far behind, this high
ABOVE_M = 6.0  # the "above the leader" camera's height


def yaw_wxyz(yaw: float) -> tuple[float, float, float, float]:
    return (math.cos(yaw / 2), 0.0, 0.0, math.sin(yaw / 2))


def _circle(radius: float, segments: int = 72) -> np.ndarray:
    ang = np.linspace(0, 2 * np.pi, segments + 1)
    pts = np.column_stack([radius * np.cos(ang), radius * np.sin(ang), np.full(ang.shape, 0.01)])
    return np.stack([pts[:-1], pts[1:]], axis=1)


class Scene:
    def __init__(self, server: viser.ViserServer, store: ParamsStore, controls: Controls,
                 obstacles: tuple[Obstacle, ...] = ()) -> None:
        """``obstacles``: the simulated world's boxes (its truth), drawn where they stand."""
        self.server = server
        self.store = store
        self.controls = controls
        s = server.scene
        s.set_up_direction("+z")
        s.add_grid("/grid", width=30.0, height=30.0, plane="xy", cell_size=0.25, section_size=1.0)
        self.leader = s.add_frame("/leader", show_axes=False)
        s.add_box("/leader/body", color=(40, 70, 140), dimensions=(0.40, 0.45, 0.22), position=(0, 0, 0.11))
        s.add_cylinder("/leader/camera", radius=0.05, height=0.25, color=(30, 30, 30),
                       wxyz=yaw_wxyz(0.0), position=(0, 0, 0.35))
        s.add_arrows("/leader/heading", points=np.array([[[0, 0.1, 0.25], [0, 0.45, 0.25]]]),
                     colors=(40, 70, 140), shaft_radius=0.015, head_radius=0.04, head_length=0.08)
        self.rings = [s.add_line_segments(f"/leader/ring_{r}", _circle(r), colors=(120, 160, 220), thickness=0.01)
                      for r in WORKING_RING_M]
        self.slot_handles: list[viser.TransformControlsHandle] = []
        self.followers: list[viser.FrameHandle] = []
        self.ghosts: list[viser.FrameHandle] = []
        self.trails: list[deque[tuple[float, float]]] = []
        self.trail_handles: list[viser.LineSegmentsHandle] = []
        self._n = 0
        self._names: tuple[str, ...] = ()  # the followers' labels in 3D
        self._slots_key = b""
        self._trail_at = -1.0
        self._dragging = False
        self._known_on = self._safety_on = True
        self.formation_line: viser.LineSegmentsHandle | None = None
        self._reset_asked = False
        self.selected: int | None = None  # the follower clicked in the 3D view
        self.asked = False  # the operator asked for something the view shows: draw it on the next tick
        controls.reset_view.on_click(lambda _: self._ask_reset())
        boxes: list[Any] = [controls.show_truth, controls.camera_view, *controls.layers.values()]
        for box in boxes:
            box.on_update(lambda _: self._ask())

        @controls.robots.on_click
        def _(event: viser.GuiEvent[Any]) -> None:
            name = str(controls.robots.value)
            if name[1:].isdigit():
                self.select(int(name[1:]) - 1)
        for k, o in enumerate(obstacles):
            s.add_box(f"/obstacles/{k}", color=(160, 110, 60), dimensions=(o.length, o.width, o.height),
                      position=(o.x, o.y, o.height / 2), wxyz=yaw_wxyz(o.heading), opacity=0.85)
        self.known = s.add_point_cloud("/known", points=np.zeros((1, 3)), colors=(240, 140, 0), point_size=0.03,
                                       visible=False)
        self.goal = s.add_frame("/goal", show_axes=False, visible=False)
        s.add_cylinder("/goal/pole", radius=0.015, height=0.5, color=(20, 150, 60), position=(0, 0, 0.25))
        s.add_icosphere("/goal/ball", radius=0.06, color=(20, 150, 60), position=(0, 0, 0.5))
        self.plan = s.add_arrows("/leader/plan", points=np.array([[[0, 0, 0.3], [0, 0.7, 0.3]]]), colors=(20, 150, 60),
                                 shaft_radius=0.012, head_radius=0.035, head_length=0.07, visible=False)
        self.active: list[viser.LineSegmentsHandle] = []
        self.picked: list[viser.LineSegmentsHandle] = []  # a ring round the follower whose card is open

        @s.on_click(modifier="shift")
        def _(event: viser.SceneClickEvent) -> None:
            (ox, oy, oz), (dx, dy, dz) = event.ray_origin, event.ray_direction
            if dz >= -1e-6:
                return  # the ray never meets the floor
            t = -oz / dz
            self.controls.drive_to(event, (ox + t * dx, oy + t * dy), what="goal clicked")
    def _selector(self, i: int) -> Callable[[Any], None]:
        def chosen(_: Any) -> None:
            self.select(i)
        return chosen

    def select(self, i: int | None) -> None:
        """Follower ``i`` (0-based; None: nobody) ringed in 3D and described on its card from the next tick on."""
        self.selected = i
        self._ask()

    def _ask(self) -> None:
        self.asked = True  # read by the dashboard (light mode draws the view at once, not at its next turn)

    def _describe(self, state: TickState) -> None:
        i = self.selected
        if i is None or i >= state.n:
            self.controls.selected.content = CARD_HINT
            return
        p, a, pd = state.p_est[i], float(state.a_est[i]), state.p_d[i]
        err = float(np.hypot(*(pd - p))) * 100 if np.all(np.isfinite(p)) else math.nan
        t = state.p_true[i]
        true_err = float(np.hypot(*(pd - t))) * 100 if np.all(np.isfinite(t)) else math.nan
        v, w = (float(x) for x in state.commands[i])
        seen = "tracked" if bool(state.tracked[i]) else "**not tracked**"
        self.controls.selected.content = (
            f"**{state.name(i)}** ({seen}) · estimated pose, leader frame: x {p[0] * 100:+.1f} cm, y {p[1] * 100:+.1f} cm,"
            f" heading {math.degrees(a):.0f}° · slot ({pd[0] * 100:+.1f}, {pd[1] * 100:+.1f}) cm ·"
            f" estimated error {err:.1f} cm" + (f" · true error {true_err:.1f} cm" if math.isfinite(true_err) else "")
            + f" · command v {v:+.3f} m/s, ω {w:+.2f} rad/s · link: {state.link_state}")

    def _ask_reset(self) -> None:
        self._reset_asked = True  # the next update places the cameras (on the page's thread)
        self._ask()

    def _rebuild(self, n: int, state: TickState) -> None:
        s = self.server.scene
        for line in self.active + self.picked:  # children of /followers/i: first, or removing the frames took them already
            line.remove()
        for h in self.followers + self.ghosts + self.slot_handles + self.trail_handles:
            h.remove()
        self.followers, self.ghosts, self.slot_handles, self.trail_handles = [], [], [], []
        self.active = [s.add_line_segments(f"/followers/{i}/constrained", _circle(0.22), colors=(220, 30, 30),
                                           thickness=0.02, visible=False) for i in range(n)]
        self.picked = [s.add_line_segments(f"/followers/{i}/picked", _circle(0.3), colors=(250, 176, 5),
                                           thickness=0.03, visible=False) for i in range(n)]  # the one clicked
        self.trails = [deque(maxlen=int(TRAIL_SECONDS * 10)) for _ in range(n)]
        self.controls.robots.options = tuple(f"F{i + 1}" for i in range(n))
        for i in range(n):
            rgb = follower_rgb(i)
            f = s.add_frame(f"/followers/{i}", show_axes=False)
            body = s.add_box(f"/followers/{i}/body", color=(45, 45, 45), dimensions=(0.25, 0.15, 0.10),
                             position=(0, 0, 0.05))
            marker = s.add_box(f"/followers/{i}/marker", color=rgb, dimensions=(0.12, 0.08, 0.01), position=(0, 0, 0.105))
            for part in (body, marker):  # a click on a robot shows its pose, error, command and link
                part.on_click(self._selector(i))
            s.add_arrows(f"/followers/{i}/heading", points=np.array([[[0.1, 0, 0.12], [0.35, 0, 0.12]]]), colors=rgb,
                         shaft_radius=0.01, head_radius=0.03, head_length=0.06)
            s.add_label(f"/followers/{i}/label", state.name(i), position=(0, 0, 0.3))
            self.followers.append(f)
            g = s.add_frame(f"/truth/{i}", show_axes=False, visible=self.controls.show_truth.value)
            s.add_box(f"/truth/{i}/body", color=rgb, dimensions=(0.25, 0.15, 0.10), position=(0, 0, 0.05),
                      wireframe=True)
            self.ghosts.append(g)
            self.trail_handles.append(
                s.add_line_segments(f"/trails/{i}", np.zeros((1, 2, 3)), colors=rgb, thickness=0.01)
            )
        for j in range(state.slot_targets.shape[0]):
            self._add_slot_handle(j, state.slot_targets[j])
        self._n = n

    def _add_slot_handle(self, j: int, xy: np.ndarray) -> None:
        h = self.server.scene.add_transform_controls(
            f"/leader/slots/{j}", scale=0.25, disable_rotations=True, active_axes=(True, True, False),
            position=(float(xy[0]), float(xy[1]), SLOT_Z_M), depth_test=False,
        )
        self.server.scene.add_icosphere(f"/leader/slots/{j}/dot", radius=0.04, color=(200, 40, 40))

        @h.on_update
        def _(event: viser.TransformControlsEvent, j: int = j) -> None:
            x, y = float(h.position[0]), float(h.position[1])
            self.store.update(f"browser:{event.client_id}", slot=(j, x, y))

        self.slot_handles.append(h)

    def update(self, state: TickState) -> None:
        n = state.n
        names = tuple(state.name(i) for i in range(n))  # an arena robot's R id with its slot here
        if n != self._n or len(self.slot_handles) != state.slot_targets.shape[0] or names != self._names:
            self._rebuild(n, state)
            self._names = names
        lx, ly, lth = state.leader
        self.leader.position = (float(lx), float(ly), 0.0)
        self.leader.wxyz = yaw_wxyz(float(lth) - math.pi / 2)

        key = state.slot_targets.tobytes() + state.assignment.tobytes()
        if key != self._slots_key:
            self._slots_key = key
            slots = state.slot_targets
            for j, h in enumerate(self.slot_handles):
                target = (float(slots[j, 0]), float(slots[j, 1]), SLOT_Z_M)
                if np.abs(np.asarray(h.position) - target).max() > 1e-6:
                    h.position = target
            # The formation polygon: leader -> assigned slots in angular order -> leader.
            used = slots[state.assignment]
            order = np.argsort(np.arctan2(used[:, 1], used[:, 0]))
            ring = np.vstack([[0.0, 0.0], used[order], [0.0, 0.0]])
            pts = np.column_stack([ring, np.full(len(ring), 0.015)])
            seg = np.stack([pts[:-1], pts[1:]], axis=1)
            self.formation_line = self.server.scene.add_line_segments(
                "/leader/formation", seg, colors=(200, 40, 40), thickness=0.012,
                visible=bool(self.controls.layers["Formation and slots"].value),
            )

        # Estimated poses (what the controller sees) drawn in the world.
        known = np.all(np.isfinite(state.p_est), axis=1) & np.isfinite(state.a_est)  # vision start-up: not yet
        est_world = leader_to_world(np.where(known[:, None], state.p_est, 0.0), state.leader[:2], float(lth))
        phi = float(lth) - math.pi / 2
        show_truth = bool(self.controls.show_truth.value)
        for i in range(n):
            self.followers[i].position = (float(est_world[i, 0]), float(est_world[i, 1]), 0.0)
            self.followers[i].wxyz = yaw_wxyz(float(state.a_est[i]) + phi if known[i] else phi + math.pi / 2)
            self.followers[i].visible = bool(state.tracked[i]) and bool(known[i])
            tw = state.followers_world[i]
            has_truth = show_truth and bool(np.all(np.isfinite(tw)))  # real robots: no ground truth
            self.ghosts[i].visible = has_truth
            if has_truth:
                self.ghosts[i].position = (float(tw[0]), float(tw[1]), 0.0)
                self.ghosts[i].wxyz = yaw_wxyz(float(tw[2]))
        now = time.monotonic()
        # trails, layers, the card and the cameras at 10 Hz (light mode: each time the view is drawn, once a
        # second), and at once when the operator asked for something (a robot clicked, a layer's box)
        every_tenth = now - self._trail_at >= 0.1 or self.asked
        self.asked = False
        if every_tenth:
            self._trail_at = now
        if every_tenth:
            for i in range(n):
                if not known[i]:
                    continue
                self.trails[i].append((float(est_world[i, 0]), float(est_world[i, 1])))
                pts = np.array(self.trails[i])
                if len(pts) >= 2:
                    p3 = np.column_stack([pts, np.full(len(pts), 0.005)])
                    self.trail_handles[i].points = np.stack([p3[:-1], p3[1:]], axis=1)
        if every_tenth:
            self._safety_view(state, est_world, known)
        if every_tenth:
            self._layers()
            self._describe(state)
            if self._reset_asked or self.controls.camera_view.value != "free":
                self._place_cameras(float(lx), float(ly), float(lth), str(self.controls.camera_view.value))
                self._reset_asked = False

    def _layers(self) -> None:
        """Each layer shown or hidden as the View folder's boxes say."""
        on = {name: bool(box.value) for name, box in self.controls.layers.items()}
        for slot in self.slot_handles:
            slot.visible = on["Formation and slots"]
        if self.formation_line is not None:
            self.formation_line.visible = on["Formation and slots"]
        for trail in self.trail_handles:
            trail.visible = on["Trails"]
        for ring in self.rings:
            ring.visible = on["Working-area rings"]
        self._known_on = on["Obstacles as known"]
        self._safety_on = on["Safety rings"]

    def _place_cameras(self, lx: float, ly: float, lth: float, view: str) -> None:
        """Every browser's 3D camera where the chosen view puts it (``free``: an overview, on reset)."""
        ahead = np.array([math.cos(lth), math.sin(lth)])
        if view == "behind the leader":
            eye, at = np.array([lx, ly]) - BEHIND_M * ahead, np.array([lx, ly]) + 0.8 * ahead
            position, look_at = (float(eye[0]), float(eye[1]), BEHIND_UP_M), (float(at[0]), float(at[1]), 0.0)
        elif view == "above the leader":  # a hair behind: straight down has no "up" on the screen
            position, look_at = (lx - 0.01 * ahead[0], ly - 0.01 * ahead[1], ABOVE_M), (lx, ly, 0.0)
        else:
            position, look_at = (lx - 3.0, ly - 3.0, 3.0), (lx, ly, 0.0)
        for client in list(self.server.get_clients().values()):
            try:  # one client's camera (what its browser last said of it) never stops the others' updates
                with client.atomic():
                    client.camera.position = position
                    client.camera.look_at = look_at
            except (ValueError, ArithmeticError, AttributeError) as exc:
                refuse("dashboard: a client's camera not placed", f"client {client.client_id}", str(exc)[:120], log)

    def _safety_view(self, state: TickState, est_world: np.ndarray, known: np.ndarray) -> None:
        """The obstacles the leader knows (scan and memory), the goal, the planned heading, and a
        red ring on each follower whose command the safety filter is holding back."""
        lx, ly, lth = (float(v) for v in state.leader)
        pts = state.obstacles
        if pts is not None and len(pts) and self._known_on:
            world = leader_to_world(pts, (lx, ly), lth)
            self.known.points = np.column_stack([world, np.full(len(world), 0.03)]).astype(np.float32)
            self.known.visible = True
        else:
            self.known.visible = False
        self.goal.visible = state.goal is not None
        if state.goal is not None:
            self.goal.position = (float(state.goal[0]), float(state.goal[1]), 0.0)
        self.plan.visible = state.goal is not None and bool(np.isfinite(state.heading))
        if self.plan.visible:
            b = float(state.heading)
            self.plan.points = np.array([[[0.0, 0.0, 0.3], [-0.7 * math.sin(b), 0.7 * math.cos(b), 0.3]]],
                                        dtype=np.float32)
        active = state.safety_active if state.safety_active is not None else np.zeros(state.n, dtype=bool)
        for i, ring in enumerate(self.active):
            ring.visible = bool(active[i]) and bool(known[i]) and self._safety_on
        for i, ring in enumerate(self.picked):
            ring.visible = i == self.selected and bool(known[i])
