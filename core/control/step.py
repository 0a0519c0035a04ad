"""The team's control step: one tick from what was observed to the commands sent.

Everything that drives a team runs this one function: the live loop (simulated team, real
robots, a fleet's arena) and the stepped simulator (and with it the tuning bench's sweeps).
Per tick, in the leader's frame (paper §2):

    the formation changed → eq. 33 again, keeping the current assignment unless a new one is
    cheaper by ``REASSIGN_MARGIN_M2`` → the slots (scaled by the goal mode's narrowing) are
    moved towards their targets at a bounded speed (core.control.targets), round the leader's
    body when the filter is on → the controller (eq. 5–11, core.control.formation) → which
    limits bound it (core.control.tuning) → the safety filter (core.control.safety, §6).

What is not a team's step stays with the caller: where the observation comes from (truth,
the vision pipeline, an arena), the leader's twist (a profile, the operator's mode, the goal
navigator), the start-up manoeuvres of §3.1–3.2, STOP, and what was sent on a radio.
"""

from __future__ import annotations

import dataclasses
from dataclasses import dataclass

import numpy as np

from core.control.assignment import assign_slots
from core.control.formation import ControlOutput, ControllerState, compute_commands
from core.control.safety import SafetyResult, SafetySettings, filter_commands, obstacle_rows
from core.control.targets import SlotMotion, step_slots
from core.control.tuning import FILTER, limit_flags
from core.types import BoolArray, Commands, FloatArray, Gains, IntArray

REASSIGN_MARGIN_M2 = 0.05  # eq. 33 re-solved for new slots keeps the old assignment unless this much cheaper
KEEP_OUT_MARGIN_M = 0.2  # moving slots go round the leader at the safety distance plus this


def due(t: float, at: float, dt: float) -> bool:
    """Whether something scheduled ``at`` (s, e.g. a formation switch) is due at the tick at ``t``:
    within half a tick counts. A clock that sums its ticks' dt (the live loop's) and one that
    counts them (k·dt, the simulator's) then agree on the tick, whatever the rounding."""
    return t >= at - 0.5 * dt


def keep_out_m(safety: SafetySettings | None) -> float:
    """How far from the leader's centre a moving slot keeps (0: the filter is off)."""
    return safety.min_distance_m + KEEP_OUT_MARGIN_M if safety is not None else 0.0


@dataclass(frozen=True)
class TeamMemory:
    """What the step carries from one tick to the next."""

    controller: ControllerState
    slots: SlotMotion  # the desired positions and their velocities now
    assignment: IntArray  # follower i holds slot assignment[i] (eq. 33)
    formation: FloatArray  # the slots the assignment was solved for

    @staticmethod
    def start(p: FloatArray, formation: FloatArray) -> TeamMemory:
        """Eq. 33 on the first poses known; the slots at rest where they are assigned."""
        assignment = np.asarray(assign_slots(p, formation))
        return TeamMemory(ControllerState.initial(len(assignment)), SlotMotion.at_rest(formation[assignment]),
                          assignment, formation)  # kept as given: the caller's slots are never changed in place

    @staticmethod
    def placeholder(n: int, formation: FloatArray) -> TeamMemory:
        """Before the poses are known (a camera's start-up): slots by index, until :meth:`start`."""
        assignment = np.arange(n) % formation.shape[0]
        return TeamMemory(ControllerState.initial(n), SlotMotion.at_rest(formation[assignment]), assignment, formation)

    def halted(self) -> TeamMemory:
        """The controller started afresh (every follower commanded to zero meanwhile)."""
        return dataclasses.replace(self, controller=ControllerState.initial(len(self.assignment)))

    def slots_on(self, p: FloatArray, formation: FloatArray, scale: float, dt: float, keep_out: float,
                 advance: bool = True, smooth: bool = True) -> TeamMemory:
        """The slots of this tick: eq. 33 again if the formation changed, then (``advance``) one
        tick on towards their targets."""
        memory = self.with_formation(p, formation)
        return memory.moved(scale, dt, keep_out, smooth) if advance else memory

    def with_formation(self, p: FloatArray, formation: FloatArray) -> TeamMemory:
        """New slots: eq. 33 again, the current assignment kept unless clearly beaten."""
        if self.formation is formation or (self.formation.shape == formation.shape
                                           and np.array_equal(self.formation, formation)):
            return self
        assignment = np.asarray(assign_slots(p, formation, current=self.assignment, margin_m2=REASSIGN_MARGIN_M2))
        return dataclasses.replace(self, assignment=assignment, formation=formation)

    def moved(self, scale: float, dt: float, keep_out: float, smooth: bool = True) -> TeamMemory:
        """The slots one tick on towards their targets (narrowed by ``scale`` across, not along)."""
        targets = self.formation[self.assignment] * np.array([scale, 1.0])
        slots = step_slots(self.slots, targets, dt, keep_out_m=keep_out) if smooth else SlotMotion.at_rest(targets)
        return dataclasses.replace(self, slots=slots)


@dataclass(frozen=True)
class TeamStep:
    """One tick's result."""

    control: ControlOutput  # the commands (after the filter) and how the controller came to them
    memory: TeamMemory
    flags: IntArray  # (n,) limit bits (core.control.tuning), FILTER where the filter changed a command
    safety: SafetyResult | None  # None: the filter was not run
    err_norm: FloatArray  # (n,) |p_d - p|, what the next tick's navigator and pipeline see
    nominal: Commands  # the controller's commands, before the filter (what limit_flags judges)
    drive: BoolArray  # (n,) who may be driven this tick
    acting: FloatArray  # (n, 2) where each follower was taken to be (the commands' p)
    w_l: float  # the leader's turn rate this tick


def team_step(
    memory: TeamMemory,
    p: FloatArray,
    a: FloatArray,
    tracked: BoolArray,
    formation: FloatArray,
    twist: tuple[float, float],
    gains: Gains,
    dt: float,
    *,
    active: BoolArray | None = None,
    obstacles: FloatArray | None = None,
    safety: SafetySettings | None = None,
    filter_now: bool = True,
    scale: float = 1.0,
    advance: bool = True,
    smooth: bool = True,
    acting: tuple[FloatArray, FloatArray] | None = None,
    limits: bool = True,
) -> TeamStep:
    """One tick of the team. ``p``/``a``: where the followers are seen (leader frame, finite);
    ``tracked``: which of them the observation knows; ``formation``: the slots asked for now;
    ``twist``: the leader's (v, ω) this tick.

    ``active``: who may be driven (default ``tracked``); ``obstacles``: (m, 2) points the leader
    knows (leader frame); ``safety``: the filter's settings (None: off; the slots then move
    without keeping out of the leader's way); ``filter_now`` false skips the filter this tick
    (STOP: every command is zero anyway); ``scale``: the goal mode's narrowing; ``advance``
    false holds the slots (paused); ``smooth`` false puts them at their targets at once (a
    scenario whose slots never move); ``acting``: where each follower will be when this
    command acts (a latency bridged, core.control.prediction), default where it is seen;
    ``limits`` false skips naming the limits that bound each command (the stepped simulator logs
    its own saturation; the flags are then 0 but the filter's)."""
    memory = memory.slots_on(p, formation, scale, dt, keep_out_m(safety), advance, smooth)
    p_d, v_d = memory.slots.p_d, memory.slots.v_d
    pa, aa = acting if acting is not None else (p, a)
    drive = tracked if active is None else active
    out = compute_commands(pa, aa, p_d, v_d, twist[0], twist[1], gains, memory.controller, dt, drive)
    nominal = out.commands
    flags = np.zeros(len(drive), dtype=np.int64)  # the filter's bits; the limits' by step_limits
    result = None
    if safety is not None and filter_now:
        pts = obstacles if obstacles is not None else np.zeros((0, 2))
        result = filter_commands(pa, aa, out.commands, twist, obstacle_rows(pts, pa[tracked], safety), safety,
                                 known=tracked, limits=(gains.v_max, gains.w_max))
        if result.status != "inactive":
            out = dataclasses.replace(out, commands=result.commands)
        flags = flags | np.where(result.active, FILTER, 0)
    memory = dataclasses.replace(memory, controller=out.state)
    err_norm = np.hypot(p_d[:, 0] - pa[:, 0], p_d[:, 1] - pa[:, 1])
    step = TeamStep(out, memory, np.asarray(flags), result, err_norm, nominal, np.asarray(drive, dtype=bool), pa,
                    float(twist[1]))
    return dataclasses.replace(step, flags=step_limits(step, gains)) if limits else step


def step_limits(step: TeamStep, gains: Gains) -> IntArray:
    """The flags of a step taken with ``limits=False`` as ``limits=True`` gives them (team_step
    asks this too): what bound each command (core.control.tuning) and where the filter changed
    one. Only the page needs them, so the live loop asks once the step's commands are on their way."""
    out = step.control
    return np.asarray(step.flags | limit_flags(step.acting, step.memory.slots.p_d, out.a_err, out.zeta_r,
                                               out.a_r_dot, step.w_l,
                                               np.column_stack([step.nominal.v, step.nominal.w]), gains, step.drive))
