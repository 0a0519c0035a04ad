"""Step tests on the live team: the operator picks a test and presses Run; the service applies
it through the ParamsStore (as the operator would), measures each follower's response over
the test's window (core.control.tuning.score_step) and adds a row to the table of trials.

The runner is one of the loop's subscribers: it sees every tick, in order, on the loop's own
thread, so it applies the step, collects the response and restores what it changed without
a thread of its own. The operator's request (from the page's thread pool) only leaves a
pending test behind, checked once more on the next tick.

A test is refused, with the reason, when it cannot run: STOP engaged, the loop paused, the
vision start-up not finished, a follower not tracked, a test already running, or a turn step
while the leader follows eq. 39 or a goal. It is aborted (a row says why) when STOP is
pressed, a follower is lost, the team is reset or resized, or the gains change during it.
STOP is never touched, and the safety filter stays as the operator set it.
"""

from __future__ import annotations

import dataclasses
import io
import math
import threading
from collections.abc import Callable
from dataclasses import dataclass, field
from typing import Any

import numpy as np

from core.config import MeasurementNoise, Scenario
from core.control.safety import SafetySettings
from core.control.tuning import StepScore, StepTest, check_step_test, score_step, stepped_slots
from core.sim.profiles import ConstantProfile
from core.sim.team import FollowerDynamics
from core.types import FloatArray, Gains

from app.params import Params, ParamsStore
from app.tick import TickState

READY_PHASES = ("truth", "tracking")
TURN_MODES = ("stop", "straight", "circle")


def team_not_ready(s: TickState | None, needs: str) -> str | None:
    """Why the team as the last tick saw it cannot be measured (``needs``: what for), or None."""
    if s is None:
        return "the loop has not ticked yet"
    if s.phase not in READY_PHASES:
        return f"the vision start-up is not finished (phase {s.phase})"
    lost = [f"F{i + 1}" for i in range(s.n) if not bool(s.tracked[i])]
    if lost:
        return f"{', '.join(lost)} not tracked: {needs}"
    return None


@dataclass(frozen=True)
class Trial:
    """One row of the table: the test, the gains it ran with, and the scores (None: aborted)."""

    number: int
    test: StepTest
    gains: Gains
    t0: float  # s of the session: the first tick with the step applied
    status: str  # "done" or "aborted: why"
    score: StepScore | None
    wheel_base_m: float = 0.12  # what the effort was computed with
    disturbed: str = ""  # what besides the controller moved the team while measured (the scores include it)

    def payload(self) -> dict[str, Any]:
        """As recorded (/omniformation/trials) and exported."""
        s = self.score
        per = None if s is None else [
            {"follower": i + 1, "settling_s": _num(s.settling_s[i]), "overshoot_m": _num(s.overshoot_m[i]),
             "steady_rms_m": _num(s.steady_rms_m[i]), "effort": _num(s.effort[i])} for i in range(len(s.settling_s))]
        return {"number": self.number, "test": dataclasses.asdict(self.test), "label": self.test.label(),
                "gains": self.gains.as_dict(), "t0": self.t0, "wheel_base_m": self.wheel_base_m, "status": self.status, "disturbed": self.disturbed, "followers": per,
                "team": None if s is None else {k: _num(v) for k, v in s.worst.items()}}


def _num(x: float) -> float | None:
    return float(x) if math.isfinite(float(x)) else None


TRIAL_COLUMNS = ("trial", "test", "status", "t0_s", *Gains().as_dict(), "settling_s", "overshoot_cm",
                 "steady_rms_cm", "effort_m2_per_s")


def trial_cells(t: Trial) -> list[str]:
    """One CSV / table row: the team's figures (per follower in the recorded message)."""
    w = t.score.worst if t.score is not None else {}

    def fmt(key: str, scale: float = 1.0, digits: int = 2) -> str:
        v = w.get(key, math.nan)
        return f"{v * scale:.{digits}f}" if math.isfinite(v) else ("not settled" if key == "settling_s" and w else "")

    status = f"{t.status} (warning: {t.disturbed})" if t.disturbed else t.status
    return [str(t.number), t.test.label(), status, f"{t.t0:.3f}", *(f"{v:g}" for v in t.gains.as_dict().values()),
            fmt("settling_s"), fmt("overshoot_m", 100), fmt("steady_rms_m", 100, 3), fmt("effort", 1.0, 4)]


def trials_csv(trials: list[Trial]) -> bytes:
    out = io.StringIO()
    out.write(",".join(TRIAL_COLUMNS) + "\n")
    for t in trials:
        out.write(",".join(f'"{c}"' if "," in c else c for c in trial_cells(t)) + "\n")
    return out.getvalue().encode()


FILTER_NOTICED_MPS = 0.005  # a command the filter moved by less than this (m/s) counts as unchanged


def share_text(part: int, whole: int) -> str:
    """``part`` of ``whole`` as a percentage that is never "0 %" for a part over 0 (0.3 %, 4 %)."""
    pct = 100.0 * part / max(1, whole)
    return f"{pct:.1f} %" if 0 < pct < 10 else f"{pct:.0f} %"


@dataclass
class _Running:
    test: StepTest
    version: int  # the params version that carries the step
    restore: dict[str, Any]  # what to set back afterwards
    stepped: dict[str, Any]  # what the step set (restored only if still so)
    gains: Gains
    n: int
    t0: float = math.nan
    rows: list[tuple[float, FloatArray, FloatArray, FloatArray]] = field(default_factory=list)
    filtered: int = 0  # measured ticks on which the safety filter changed a command noticeably (FILTER_NOTICED_MPS)
    twist0: tuple[float, float] | None = None  # the leader's twist at the first measured tick
    leader_changed: bool = False  # it changed during the window (the goal navigator, an operator)

    def disturbed(self) -> str:
        """What besides the controller moved the team while it was measured ('' when nothing)."""
        notes = []
        if self.filtered:  # none: no warning (a filter on but never moving a command is not a disturbance)
            notes.append(f"the safety filter changed commands on {self.filtered} of {len(self.rows)} measured ticks"
                         f" ({share_text(self.filtered, len(self.rows))})")
        if self.leader_changed:
            notes.append("the leader's motion changed while it was measured")
        return "; ".join(notes)


class StepTests:
    """Runs the operator's step tests; subscribe :meth:`on_tick` to the loop."""

    def __init__(self, store: ParamsStore, wheel_base_m: float) -> None:
        self.store = store
        self.wheel_base_m = wheel_base_m
        self.trials: list[Trial] = []
        self.listeners: list[Callable[[Trial], None]] = []
        self._lock = threading.Lock()
        self._pending: StepTest | None = None
        self._running: _Running | None = None
        self._last: TickState | None = None

    # -- the operator's side (any thread) -------------------------------------------------
    def request(self, test: StepTest) -> str | None:
        """Queue a test for the next tick; the reason it cannot run, or None."""
        with self._lock:
            if self._pending is not None or self._running is not None:
                return "a step test is running: wait for its row, or cancel it"
            why = self._why_not(test, self._last)
            if why is None:
                self._pending = test
            return why

    def cancel(self) -> bool:
        """Abort the running test (its row says so); whether one was running."""
        with self._lock:
            if self._pending is not None:
                self._pending = None
                return True
            running = self._running is not None
        if running:
            self._abort("cancelled by the operator")
        return running

    @property
    def status(self) -> str:
        """What the runner is doing, for people."""
        r, last = self._running, self._last
        if self._pending is not None:
            return f"{self._pending.label()}: starting"
        if r is None:
            return "idle"
        if math.isnan(r.t0) or last is None:
            return f"{r.test.label()}: applying"
        return f"{r.test.label()}: measuring, {max(0.0, last.t - r.t0):.1f} of {r.test.window_s:g} s"

    def _why_not(self, test: StepTest, s: TickState | None) -> str | None:
        if s is not None and s.stopped:
            return "STOP is engaged: release it first"
        if s is not None and s.paused:
            return "the loop is paused: resume it first"
        not_ready = team_not_ready(s, "a step test needs every follower in view")
        if not_ready or s is None:
            return not_ready or "the loop has not ticked yet"
        why = check_step_test(test, s.n)
        if why:
            return why
        mode = self.store.get().leader_mode
        if test.kind == "turn" and mode not in TURN_MODES:
            return f"a turn step needs the leader in {', '.join(TURN_MODES)} mode (it is in {mode})"
        return None

    # -- the loop's side ------------------------------------------------------------------
    def on_tick(self, s: TickState) -> None:
        with self._lock:
            self._last = s
            if self._pending is not None:
                test, self._pending = self._pending, None
                why = self._why_not(test, s)
                if why:
                    self._emit_locked(Trial(len(self.trials) + 1, test, s.gains, s.t, f"aborted: {why}", None))
                    return
                self._apply(test, s)
                return
            r = self._running
        if r is None or s.params_version < r.version:
            return
        why = self._broken(r, s)
        if why:
            self._abort(why)
            return
        if math.isnan(r.t0):
            r.t0 = s.t
        twist = (float(s.leader_twist[0]), float(s.leader_twist[1]))
        if r.twist0 is None:
            r.twist0 = twist
        elif abs(twist[0] - r.twist0[0]) > 1e-3 or abs(twist[1] - r.twist0[1]) > 1e-3:
            r.leader_changed = True
        if s.safety_changed is not None and bool(np.any(np.abs(s.safety_changed) >= FILTER_NOTICED_MPS)):
            r.filtered += 1
        target = s.slot_targets[s.assignment] * np.array([s.formation_scale, 1.0])
        r.rows.append((s.t, s.p_est.copy(), target, s.commands.copy()))
        if s.t >= r.t0 + r.test.window_s - 1e-9:
            self._finish(r)

    def _apply(self, test: StepTest, s: TickState) -> None:
        params = self.store.get()
        restore: dict[str, Any]
        stepped: dict[str, Any]
        if test.kind == "turn":
            restore = {"leader_mode": params.leader_mode, "leader_turn_deg_s": params.leader_turn_deg_s}
            base = params.leader_turn_deg_s if params.leader_mode == "circle" else 0.0
            stepped = {"leader_mode": "circle", "leader_turn_deg_s": base + math.degrees(test.size)}
            if params.leader_mode == "stop":
                restore["leader_speed_mps"] = params.leader_speed_mps
                stepped["leader_speed_mps"] = 0.0  # a leader at rest turns on the spot
        else:
            restore = {"slots": params.slots.copy()}
            stepped = {"slots": stepped_slots(test, params.slots, s.assignment)}
        new, _ = self.store.update("tuning", **stepped)
        stepped = {k: getattr(new, k) for k in stepped}
        self._running = _Running(test, new.version, restore, stepped, new.gains, s.n)

    def _broken(self, r: _Running, s: TickState) -> str | None:
        if s.stopped:
            return "STOP"
        if s.n != r.n:
            return "the team was resized"
        if not math.isnan(r.t0) and s.t < r.t0:
            return "the team was reset"
        lost = [f"F{i + 1}" for i in range(s.n) if not bool(s.tracked[i])]
        if lost:
            return f"{', '.join(lost)} lost"
        if s.gains != r.gains:
            return "the gains changed during the test"
        return None

    def _finish(self, r: _Running) -> None:
        t = np.array([row[0] for row in r.rows])
        p = np.array([row[1] for row in r.rows])
        target = np.array([row[2] for row in r.rows])
        cmd = np.array([row[3] for row in r.rows])
        score = score_step(t, p, target, cmd, r.t0, r.test.window_s, self.wheel_base_m)
        with self._lock:
            if self._running is not r:  # cancelled meanwhile: its row is written
                return
            self._restore(r)
            self._emit_locked(Trial(len(self.trials) + 1, r.test, r.gains, r.t0, "done", score,
                                     self.wheel_base_m, r.disturbed()))

    def _abort(self, why: str) -> None:
        with self._lock:
            r = self._running
            if r is None:
                return
            self._restore(r)
            self._emit_locked(Trial(len(self.trials) + 1, r.test, r.gains, r.t0, f"aborted: {why}", None))

    def _restore(self, r: _Running) -> None:
        """Set back what the test changed, unless the operator has changed it since."""
        self._running = None
        now = self.store.get()
        same = all(np.array_equal(getattr(now, k), v) if isinstance(v, np.ndarray) else getattr(now, k) == v
                   for k, v in r.stepped.items())
        if same:
            self.store.update("tuning", **r.restore)

    def _emit_locked(self, trial: Trial) -> None:
        self.trials.append(trial)
        for fn in list(self.listeners):
            fn(trial)


def live_base(state: TickState | None, params: Params, dynamics: FollowerDynamics, noise: MeasurementNoise,
              rate_hz: float, seed: int) -> tuple[Scenario, tuple[float, float]] | str:
    """The team as it is now, as a scenario for the simulator (follower i on its slot i, starting
    where it is seen now; the leader holding its present twist): what a sweep starts from. The
    reason it cannot be made, as a string. The world's obstacles are not carried over: a sweep
    measures the controller, not the way round a box."""
    not_ready = team_not_ready(state, "a sweep starts from where every follower is seen now")
    if not_ready or state is None:
        return not_ready or "the loop has not ticked yet"
    n = state.n
    slots = np.asarray(params.slots)[state.assignment][:n]
    scenario = Scenario(
        name="live", description="the live team at the moment the sweep started", duration_s=1.0, rate_hz=rate_hz,
        seed=seed, leader=ConstantProfile(*state.leader_twist), initial_p=np.array(state.p_est, dtype=np.float64),
        initial_a=np.array(state.a_est, dtype=np.float64), slots=np.array(slots, dtype=np.float64),
        gains=params.gains, dynamics=dynamics, measurement=noise, disturbances=(),
        safety=SafetySettings.for_distance(params.safety_distance_m) if params.safety else None,
    )
    return scenario, (float(state.leader_twist[0]), float(state.leader_twist[1]))
