"""Operator controls. Every callback only writes to the ParamsStore; a store listener
pushes accepted (possibly clamped) values back to the widgets, which viser shows to
every open browser. Callbacks ignore server-set values (event.client_id is None)."""

from __future__ import annotations

import math
import time
from typing import Any
from collections.abc import Callable

import numpy as np
import viser

from core.bounds import PARAMETERS, Parameter

from app.dashboard.health import Health
from app.dashboard.widgets import as_text
from app.keys import follower_name
from app.tick import TickState
from app.params import (
    FORMATION_PRESETS,
    LEADER_MODES,
    MIN_SCALE,
    SAFETY_DISTANCE,
    Notice,
    Params,
    ParamsStore,
    formation_preset,
)

STATUS_S = 0.2  # the live status is redrawn at most this often
# the gains with a slider on the page: the parameter table's gain rows the operator sets
PAGE_GAINS = tuple(n for n, row in PARAMETERS.items() if row.kind == "gain" and "page" in row.setters)


def range_of(name: str) -> tuple[float, float, float]:
    """A control's min, max and step, from the parameter table (core.bounds: the bound on the step's grid)."""
    row: Parameter = PARAMETERS[name]
    lo, hi = row.control_range()
    assert row.step is not None
    return lo, hi, float(row.step)


def add_slider(gui: Any, name: str, label: str | None = None, **kw: Any) -> Any:
    """A slider for the table's row ``name``: its label (unless given), min, max and step."""
    lo, hi, step = range_of(name)
    if PARAMETERS[name].kind == "count":
        return gui.add_slider(label or PARAMETERS[name].label, min=int(lo), max=int(hi), step=int(step), **kw)
    return gui.add_slider(label or PARAMETERS[name].label, min=lo, max=hi, step=step, **kw)


def add_number(gui: Any, name: str, label: str, **kw: Any) -> Any:
    """A number input for the table's row ``name`` (each coordinate of a point or a slot)."""
    lo, hi, step = range_of(name)
    return gui.add_number(label, min=lo, max=hi, step=step, **kw)


class Controls:
    def __init__(self, server: viser.ViserServer, store: ParamsStore) -> None:
        self.server = server
        self.store = store
        gui = server.gui
        p = store.get()
        self.notice = ""
        self.recording = "off"  # what the status says about recording (set by the service)
        self._status_at = -1.0
        self._status_state: tuple[bool, bool] | None = None
        self.replay = False
        self._tracked: list[bool] = []  # the last tick's, for the question before releasing STOP
        self._names: list[str] = []  # the last tick's followers' names (app.keys.follower_name)

        self.who: Callable[[int], str] = lambda client_id: f"client {client_id}"  # the gate's: role and address
        self.stopped_by = ""  # who pressed STOP and when (shown on the status)
        self.cause: Callable[[], str] = lambda: ""  # a cause on the service's side, named beside an alarm (a replay)
        self.health = Health()
        self.stop_button = gui.add_button("STOP", color="red", hint="Command every follower to zero now (keyboard:"
                                                                    " Space, or Escape when no menu is open)."
                                                                    " The loop keeps observing.")
        self.release_button = gui.add_button("Release STOP", color="gray", disabled=True)
        # the card of the robot clicked in the 3D view (or named here): beside the view, right under STOP,
        # so it is in view at once (under the status and the camera it was below a 720-pixel window)
        self.robots = gui.add_button_group("Robot card", options=("F1",),
                                           hint="a robot's figures (or click the robot in the 3D view)")
        self.selected = gui.add_markdown(CARD_HINT)
        self.status = gui.add_markdown("starting ...")
        self.alarm = gui.add_markdown("", visible=False)
        self.acknowledge = gui.add_button("Acknowledge alarms", color="orange", visible=False,
                                          hint="the alarms above were seen; the banner clears until the next")

        with gui.add_folder("Run"):
            self.pause_button = gui.add_button("Pause")
            self.step_button = gui.add_button("Single step", disabled=True)
            self.reset_button = gui.add_button("Reset")
            self.n_slider = add_slider(gui, "n_followers",
                                           initial_value=p.n_followers,
                                           hint="number of simulated followers (resets the team)")
        with gui.add_folder("Leader"):
            self.mode = gui.add_dropdown("Motion", options=LEADER_MODES, initial_value=p.leader_mode,
                                         hint="stop | straight | circle | eq39 (the paper's manoeuvre, eq. 39) |"
                                              " goal (drive to the goal below around obstacles)")
            self.speed = add_slider(gui, "leader_speed_mps",
                                        initial_value=p.leader_speed_mps, hint="leader forward speed v_l")
            self.turn = add_slider(gui, "leader_turn_deg_s",
                                       initial_value=p.leader_turn_deg_s,
                                       hint="leader turn rate w_l (circle), or k1 of eq. 39")
            gx, gy = p.goal if p.goal is not None else (0.0, 2.0)
            self.goal_x = add_number(gui, "goal", "Goal x (m, odometry frame)", initial_value=float(gx),
                                         hint="where the leader drives in goal mode (the floor's"
                                              " frame: where the leader started); or shift-click the floor")
            self.goal_y = add_number(gui, "goal", "Goal y (m, odometry frame)", initial_value=float(gy))
            self.go_button = gui.add_button("Drive to goal", hint="leader mode goal, to the point above")
            self.min_scale = add_slider(gui, "min_scale",
                                            initial_value=p.min_scale, hint=MIN_SCALE.meaning +
                                            " (its width times this, at the least; goal mode)")
        with gui.add_folder("Gains"):
            self.gains: dict[str, Any] = {}
            for name in PAGE_GAINS:
                row = PARAMETERS[name]
                assert row.bound is not None
                self.gains[name] = add_slider(gui, name, initial_value=float(getattr(p.gains, name)),
                                              hint=row.bound.meaning)
        with gui.add_folder("Safety"):
            self.safety = gui.add_checkbox("Safety filter", initial_value=p.safety,
                                           hint="barrier certificates on every command: robots keep the distance below"
                                                " from each other and from the leader (on by default)")
            self.safety_distance = add_slider(gui, "safety_distance_m",
                                                  initial_value=p.safety_distance_m,
                                                  hint=SAFETY_DISTANCE.meaning)
        with gui.add_folder("Formation"):
            self.preset = gui.add_dropdown("Preset", options=FORMATION_PRESETS, initial_value=FORMATION_PRESETS[0])
            self.apply_preset = gui.add_button("Apply preset")
            self.slot_folder = gui.add_folder("Desired positions (leader frame, m)")
            self.slot_inputs: list[tuple[Any, Any]] = []
        with gui.add_folder("View"):
            self.camera_view = gui.add_dropdown("3D camera", options=CAMERA_VIEWS, initial_value=CAMERA_VIEWS[0],
                                                hint="behind: 2.5 m behind the leader and 2 m up, turning with it;"
                                                     " above: straight down on the leader from 6 m; free: yours")
            self.reset_view = gui.add_button("Reset the 3D camera", hint="back to the chosen view's place")
            self.show_truth = gui.add_checkbox("Show true poses", initial_value=True,
                                               hint="simulation: the true pose as a wireframe beside the estimate")
            self.layers = {name: gui.add_checkbox(name, initial_value=True) for name in LAYERS}
            self.light = gui.add_checkbox("Light mode", initial_value=False,
                                          hint="for a browser that draws slowly (no GPU): the 3D view, its trails and"
                                               " the camera once a second (at once after a click), charts every 2 s;"
                                               " a page whose browser is busy over half of each second turns it on"
                                               " by itself")
            gui.add_markdown(LAYER_KEY)
        self._build_slot_inputs(p)
        self._wire()
        store.subscribe(self._on_params)

    def set_replay(self, name: str) -> None:
        """Replay mode: nothing here may command robots; every such control says why."""
        self.replay = True
        self.recording = name
        why = "replay: a recording cannot command robots"
        handles = [self.stop_button, self.release_button, self.pause_button, self.step_button, self.reset_button,
                   self.n_slider, self.mode, self.speed, self.turn, self.preset, self.apply_preset, self.safety,
                   self.safety_distance, self.goal_x, self.goal_y, self.go_button, self.min_scale,
                   self.acknowledge, *self.gains.values(), *(h for pair in self.slot_inputs for h in pair)]
        for h in handles:
            h.disabled = True
            h.hint = why

    # -- building -------------------------------------------------------------------------
    def _build_slot_inputs(self, p: Params) -> None:
        for x_in, y_in in self.slot_inputs:
            x_in.remove()
            y_in.remove()
        self.slot_inputs = []
        with self.slot_folder:
            for j in range(p.slots.shape[0]):
                x_in = add_number(self.server.gui, "slot", f"Slot {j + 1} x", initial_value=float(p.slots[j, 0]))
                y_in = add_number(self.server.gui, "slot", f"Slot {j + 1} y", initial_value=float(p.slots[j, 1]))

                def make_cb(j: int) -> Any:
                    def cb(event: viser.GuiEvent[Any]) -> None:
                        if event.client_id is None:
                            return
                        x_in_, y_in_ = self.slot_inputs[j]
                        self._update(event, slot=(j, x_in_.value, y_in_.value))

                    return cb

                x_in.on_update(make_cb(j))
                y_in.on_update(make_cb(j))
                self.slot_inputs.append((x_in, y_in))

    def _update(self, event: viser.GuiEvent[Any], what: str = "",
                decide: Callable[[Params], dict[str, Any]] | None = None, **changes: Any) -> None:
        """Write to the store; ``what`` names the action in the source (e.g. a preset), for the record;
        ``decide``: changes that depend on what is in force, made in one step (ParamsStore.change)."""
        if self.replay:
            return
        source = f"browser:{event.client_id}" + (f" {what}" if what else "")
        try:
            if decide is not None:
                _, notices = self.store.change(source, decide)
            else:
                _, notices = self.store.update(source, **changes)
        except (ValueError, TypeError, OverflowError) as exc:
            notices = (Notice("input", str(exc)),)
            self._on_params(self.store.get(), "server", ())  # the page shows what is in force, not what was refused
        if notices and event.client is not None:
            text = "; ".join(n.message for n in notices)
            event.client.add_notification("Value adjusted", text, auto_close_seconds=6.0, color="yellow")

    def _wire(self) -> None:
        def on(handle: viser.GuiButtonHandle, **fixed: Any) -> None:
            def _(event: viser.GuiEvent[Any]) -> None:
                self._update(event, **fixed)

            handle.on_click(_)

        @self.stop_button.on_click
        def _(event: viser.GuiEvent[Any]) -> None:
            self._update(event, what=f"STOP by {self.who(event.client_id) if event.client_id is not None else 'the server'}",
                         stop=True)

        @self.acknowledge.on_click
        def _(_: viser.GuiEvent[Any]) -> None:
            self.health.acknowledge()
            self.alarm.visible = self.acknowledge.visible = False

        @self.release_button.on_click
        def _(event: viser.GuiEvent[Any]) -> None:
            lost = [i for i, t in enumerate(self._tracked) if not t]
            if not lost or event.client is None:
                self._update(event, stop=False)
                return
            # a follower the camera does not see gets zero from the controller, but the operator
            # should know before the others move: ask
            names = ", ".join(self._names[i] if i < len(self._names) else follower_name(i) for i in lost)
            with event.client.gui.add_modal("Release STOP?") as modal:
                event.client.gui.add_markdown(f"**{names} {'is' if len(lost) == 1 else 'are'} not tracked.** The"
                                              " others will move; the untracked stay at zero until the camera sees"
                                              " them (and their link answers) again. *Release* lets the leader wait"
                                              " where it is until every follower is tracked; *Release anyway* lets"
                                              " it drive on at once.")
                wait = event.client.gui.add_button("Release, leader waits", color="orange")
                go = event.client.gui.add_button("Release anyway", color="red")
                keep = event.client.gui.add_button("Keep STOP")

                @wait.on_click
                def _(inner: viser.GuiEvent[Any]) -> None:
                    modal.close()
                    self._update(inner, what="release, the leader waits for the team", stop=False)

                @go.on_click
                def _(inner: viser.GuiEvent[Any]) -> None:
                    modal.close()
                    self._update(inner, what="release with followers untracked", stop=False, leader_hold=False)

                @keep.on_click
                def _(_: viser.GuiEvent[Any]) -> None:
                    modal.close()
        on(self.step_button, step_requests=1)
        on(self.reset_button, reset_requests=1)

        @self.pause_button.on_click
        def _(event: viser.GuiEvent[Any]) -> None:
            self._update(event, decide=lambda now: {"paused": not now.paused})

        def on_value(handle: Any, key: str) -> None:
            def _(event: viser.GuiEvent[Any]) -> None:
                if event.client_id is None:  # the server's own echo
                    return
                self._update(event, **{key: handle.value})  # as the browser sent it: the store checks it

            handle.on_update(_)

        on_value(self.n_slider, "n_followers")
        on_value(self.mode, "leader_mode")
        on_value(self.speed, "leader_speed_mps")
        on_value(self.safety, "safety")
        on_value(self.safety_distance, "safety_distance_m")
        on_value(self.turn, "leader_turn_deg_s")
        for name, handle in self.gains.items():
            on_value(handle, name)

        on_value(self.min_scale, "min_scale")

        @self.go_button.on_click
        def _(event: viser.GuiEvent[Any]) -> None:
            self.drive_to(event, (self.goal_x.value, self.goal_y.value))

        @self.apply_preset.on_click
        def _(event: viser.GuiEvent[Any]) -> None:
            p = self.store.get()
            self._update(event, slots=formation_preset(self.preset.value, p.n_followers), what=f"preset {self.preset.value}")

    def drive_to(self, event: Any, goal: tuple[float, float], what: str = "goal") -> None:
        """Goal mode to ``goal`` (floor frame, m): from the button, or a shift-click on the floor.
        A goal the store refuses (off the floor, in an obstacle) leaves the leader as it was."""
        self._update(event, what=what, goal=goal)
        if self.store.get().goal == (float(goal[0]), float(goal[1])):
            self._update(event, what=what, leader_mode="goal")

    # -- store -> widgets -----------------------------------------------------------------
    @staticmethod
    def _set(handle: Any, value: Any) -> None:
        if isinstance(value, float) and isinstance(handle.value, (int, float)):
            if math.isclose(float(handle.value), value, abs_tol=1e-9):
                return
        elif handle.value == value:
            return
        handle.value = value

    def _on_params(self, p: Params, source: str, notices: tuple[Notice, ...]) -> None:
        for name, handle in self.gains.items():
            self._set(handle, float(getattr(p.gains, name)))
        self._set(self.mode, p.leader_mode)
        self._set(self.speed, float(p.leader_speed_mps))
        self._set(self.turn, float(p.leader_turn_deg_s))
        self._set(self.safety, bool(p.safety))
        self._set(self.safety_distance, float(p.safety_distance_m))
        self._set(self.n_slider, int(p.n_followers))
        self._set(self.min_scale, float(p.min_scale))
        if p.goal is not None:
            self._set(self.goal_x, float(np.round(p.goal[0], 3)))
            self._set(self.goal_y, float(np.round(p.goal[1], 3)))
        if len(self.slot_inputs) != p.slots.shape[0]:
            self._build_slot_inputs(p)
        for j, (x_in, y_in) in enumerate(self.slot_inputs):
            self._set(x_in, float(np.round(p.slots[j, 0], 4)))
            self._set(y_in, float(np.round(p.slots[j, 1], 4)))
        if p.stop and not self.stopped_by:
            who = source.split(" STOP by ", 1)[1] if " STOP by " in source else source
            self.stopped_by = f"by {who} at {time.strftime('%H:%M:%S', time.gmtime())} UTC"
        elif not p.stop:
            self.stopped_by = ""
        self.stop_button.disabled = p.stop or self.replay  # a replay commands nothing, whatever it shows
        self.release_button.disabled = not p.stop or self.replay
        self.pause_button.label = "Resume" if p.paused else "Pause"
        self.step_button.disabled = not p.paused or self.replay
        if notices:
            self.notice = "; ".join(n.message for n in notices)

    def judge(self, s: TickState) -> None:
        """The health rules on a live tick (a replay's ticks are history: not judged again)."""
        if not self.replay:
            self.health.check(s)

    def update_status(self, s: TickState) -> None:
        self._tracked = [bool(t) for t in s.tracked]
        self._names = [s.name(i) for i in range(s.n)]
        self.judge(s)
        if not self.replay:
            alarms = self.health.alarms
            cause = self.cause() if alarms else ""
            text = "**ALARM** · " + " · ".join(as_text(a) for a in alarms) + (f" · {as_text(cause)}" if cause else "")
            if alarms and text != self.alarm.content:
                self.alarm.content = text
            if bool(alarms) != self.alarm.visible:
                self.alarm.visible = self.acknowledge.visible = bool(alarms)
        now = time.monotonic()
        state = (s.stopped, s.paused)  # STOPPED, running, PAUSED: shown on the tick it happens, never later
        if now - self._status_at < STATUS_S and not self.replay and state == self._status_state:
            return  # live: 5 Hz is plenty; a replay shows exactly the tick it jumped to
        self._status_at, self._status_state = now, state
        stages = " · ".join(f"{k.split(':')[0]} {v:.2f}" for k, v in s.stage_ms.items() if not k.startswith("publish"))
        lines = [
            (f"**recorded{' (STOPPED)' if s.stopped else ''}** · t = {s.t:.1f} s · loop was {s.rate_hz:.1f} Hz"
             if self.replay else
             f"**{'STOPPED — the leader and every follower at zero' if s.stopped else 'PAUSED' if s.paused else 'running'}**"
             + (f" · {as_text(self.stopped_by)}" if s.stopped and self.stopped_by else "")
             + (f" · leader {s.leader_waits}" if s.leader_waits and not s.stopped else "")
             + (" · by a loop fault (below)" if s.fault and s.stopped else "")
             + f" · t = {s.t:.1f} s · loop {s.rate_hz:.1f} Hz"
             + (f" · frame to command {s.latency_ms:.1f} ms" if np.isfinite(s.latency_ms) else "")
             + beat(s)),
            f"stages (ms): {stages}",
            f"poses from: {'the simulator (truth + noise)' if s.phase == 'truth' else 'vision, ' + _phase_text(s)}",
            (f"followers tracked {int(np.sum(s.tracked))}/{s.n}, lost {s.n - int(np.sum(s.tracked))}"
             if s.phase not in ("find", "base", "probe", "heading") else
             f"start-up ({s.phase}): {int(np.sum(s.tracked))}/{s.n} followers found so far")
            + f" · link: {s.link_state} · " + (f"replaying {as_text(self.recording)}" if self.replay
                                             else f"recording: {as_text(self.recording)}"),
            error_line(s),
            f"safety filter: {s.safety or '-'}"
            + (f" · closest two robots {s.min_distance_m * 100:.0f} cm" if np.isfinite(s.min_distance_m) else "")
            + (f" · obstacle points known {len(s.obstacles)}" if s.obstacles is not None and len(s.obstacles) else ""),
        ]
        if s.goal is not None:
            heading = f"heading {math.degrees(s.heading):+.0f} deg" if np.isfinite(s.heading) else "no way free"
            lines.append(f"goal ({s.goal[0]:.2f}, {s.goal[1]:.2f}) m: " + ("**reached**" if s.goal_reached else
                         f"{math.hypot(s.goal[0] - s.leader[0], s.goal[1] - s.leader[1]):.2f} m to go, {heading}")
                         + f" · formation width {s.formation_scale * 100:.0f} %")
        if s.camera_state:
            lines.append(f"camera: {s.camera_state}")
        if s.link_detail:
            lines.append(f"link detail: {s.link_detail}")
        if s.fault:
            lines.append(f"**loop fault: {s.fault}** · every follower was stopped; release STOP to go on")
        if self.notice:
            lines.append(f"notice: {self.notice}")
        self.status.content = "  \n".join(lines)


CARD_HINT = "<small>click a robot in the 3D view, or its name above, to see its figures</small>"
CAMERA_VIEWS = ("behind the leader", "above the leader", "free")
LAYERS = ("Formation and slots", "Trails", "Obstacles as known", "Working-area rings", "Safety rings")
LAYER_KEY = ("<small>**3D key** · dark box, coloured marker: a follower where the camera sees it (F1, F2, …) ·"
             " wireframe: its true pose (simulation) · red line and red dots: the formation, leader to each slot"
             " (drag a dot to move the slot; shift-click the floor sets a goal) · coloured lines: trails ·"
             " orange points: obstacles as the leader knows them · blue rings: the camera's working area ·"
             " red ring round a follower: the safety filter holding its command back · green pole: the goal</small>")


def beat(s: TickState) -> str:
    """The live state line's mark of the tick it was drawn from (an empty element, nothing shown): the
    page's script (assets/page.js) takes a state line that stops changing for LINK_LOST_S (app.dashboard.gate)
    as no link to the loop, whatever broke it (the service, the loop's process, the network)."""
    return f'<span data-omni-beat="{s.tick}" data-t="{s.t:.1f}" data-hz="{s.rate_hz:.1f}"></span>'


def error_line(s: TickState) -> str:
    """Each follower's distance to its slot in cm, named for what it is: the true error (the
    simulator's true pose) where there is one, else the estimated error (the estimate)."""
    true = np.all(np.isfinite(s.p_true), axis=1)
    pose = np.where(true[:, None], s.p_true, s.p_est)  # real robots: the estimate is all we have
    err = np.linalg.norm(pose - s.p_d, axis=1) * 100
    figures = [f"{s.name(i)} {e:.1f}" if np.isfinite(e) else f"{s.name(i)} -" for i, e in enumerate(err)]
    if true.all():
        return "true error to the slot (cm): " + ", ".join(figures)
    if not true.any():
        return "estimated error to the slot (cm): " + ", ".join(figures)
    return "error to the slot (cm): " + ", ".join(f"{f} ({'true' if t else 'estimated'})" for f, t in zip(figures, true))


def _phase_text(s: TickState) -> str:
    return {"find": "start-up: finding the team by hue", "base": "start-up: base background", "probe": f"start-up: probing F{s.probing + 1}",
            "heading": "start-up: first headings", "tracking": "tracking"}.get(s.phase, s.phase)
