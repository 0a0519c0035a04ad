"""What one tick of the loop produced: the value the dashboard, the recorder and a replay
read, and the publisher that hands the newest of them to a slow reader (the page, the fleet's
bus). Its own module, so that they need not import the loop (and through it every backend)."""

from __future__ import annotations

import logging
import threading
from collections.abc import Callable
from dataclasses import dataclass, field

import numpy as np

from core.types import FloatArray, Gains, Image, IntArray
from core.vision.freespace import Scan

from app.keys import follower_name


@dataclass(frozen=True)
class TickState:
    """Everything one tick produced, published to the dashboard and recorder."""

    tick: int
    t: float
    leader: FloatArray  # (3,) world x, y, theta
    leader_twist: tuple[float, float]
    followers_world: FloatArray  # (n, 3) true, simulation only
    p_est: FloatArray  # (n, 2) leader frame, what the controller used
    a_est: FloatArray  # (n,)
    tracked: FloatArray  # (n,) bool
    p_true: FloatArray  # (n, 2)
    a_true: FloatArray  # (n,)
    p_d: FloatArray  # (n, 2) desired position of each follower (ramped)
    slot_targets: FloatArray  # (m, 2) the formation as set
    assignment: IntArray  # (n,) slot of each follower
    commands: FloatArray  # (n, 2) v, w sent
    a_err: FloatArray  # (n,)
    v_lyap: FloatArray  # (n,)
    gains: Gains
    params_version: int
    stopped: bool
    paused: bool
    link_state: str
    rate_hz: float
    stage_ms: dict[str, float] = field(default_factory=dict)
    phase: str = "truth"  # where poses come from: "truth", or the vision pipeline's phase
    probing: int = -1  # the follower the pipeline is probing (start-up), -1 otherwise
    a_raw: FloatArray | None = None  # (n,) last raw heading measurement (eq. 34-37), held
    frame: Image | None = None  # the camera image (BGR) this tick, vision only; np.asarray(frame) for its pixels
    windows: np.ndarray | None = None  # (n, 4) CAMSHIFT windows, pixels
    hues_deg: FloatArray | None = None  # (n,) learned marker colours
    link_detail: str = ""  # per follower: round trip, lost replies, CRC errors, battery (serial link)
    fault: str = ""  # the last exception inside a tick, if the loop caught one
    camera_state: str = ""  # a real camera's state ("" for the synthetic camera)
    safety: str = ""  # the safety filter's state for people ("off", "on, inactive", "on, changed F2 0.04 m/s", ...)
    safety_changed: FloatArray | None = None  # (n,) how much the filter moved each follower's command (m/s)
    min_distance_m: float = float("nan")  # the smallest centre distance between two robots this tick
    safety_active: np.ndarray | None = None  # (n,) bool: a constraint of this follower is at its limit
    obstacles: FloatArray | None = None  # (k, 2) leader frame: the obstacle points the leader knows
    scan: Scan | None = None  # this frame's free-space scan (vision)
    goal: tuple[float, float] | None = None  # leader mode "goal": where it drives (world / odometry frame)
    heading: float = float("nan")  # the goal mode's chosen bearing (rad, leader frame)
    formation_scale: float = 1.0  # how far the formation is narrowed for a gap
    goal_reached: bool = False
    limits: IntArray | None = None  # (n,) bits of core.control.tuning.LIMIT_NAMES active this tick
    v_rate: FloatArray | None = None  # (n,) dV/dt per follower (m²/s) over the last half second
    latency_ms: float = float("nan")  # from what this tick observed (a camera frame's arrival) to its commands written
    fresh: bool = True  # this tick observed anew (False: a camera without a new frame, or paused: the last one stood)
    leader_waits: str = ""  # why the leader stands still ("STOP", "waiting for F2 to be tracked"); "" when it may drive
    robots: tuple[int, ...] | None = None  # an arena leader's: the fleet's robot index of each follower

    @property
    def n(self) -> int:
        return int(self.p_est.shape[0])

    def name(self, i: int) -> str:
        """Follower ``i``'s name for people: "R3 (F1)" in a fleet's arena, else "F1" (app.keys)."""
        return follower_name(i, self.robots if self.robots is not None and len(self.robots) == self.n else None)


class SessionClock:
    """The time of a session, which never goes back: the loop's own clock (each tick's ``t``)
    starts again at 0 after a reset; this one goes on from where it was, one tick later. The
    recording's log time and a leader's ``t`` on the fleet bus are this clock."""

    def __init__(self, start: float = 0.0) -> None:
        """``start``: the session's time at the loop's first tick (a leader that waited for
        robots before its loop ran goes on from the time it published while waiting)."""
        self._prev: float | None = None  # the loop's t at the last tick
        self._offset = start  # session time minus the loop's, grown at each reset
        self._step = 0.0  # the last tick's step of the loop's clock
        self.last = start  # the session's time of the last tick (s)

    def __call__(self, t: float) -> float:
        """The session's time of a tick whose loop time is ``t``."""
        if self._prev is not None and t < self._prev - 1e-9:  # a reset
            self._offset = self.last + self._step - t
        elif self._prev is not None and t > self._prev:
            self._step = t - self._prev
        self._prev = t
        self.last = self._offset + t
        return self.last


class LatestStatePublisher:
    """Publishes on its own thread, always the newest state; the loop only hands states over.

    The robots' loop must never wait for the page server: drawing the scene, encoding the
    camera JPEG and serialising plots for every connected browser happen here, and a state
    that is superseded before it could be drawn is skipped (the plots keep their time axis).
    """

    def __init__(self, publish: Callable[[TickState], bool | None], name: str = "omniformation-dashboard") -> None:
        """``publish`` returns False for a state it could not draw (counted as skipped); ``name``
        names the thread (the page's, the ROS 2 bridge's)."""
        self._publish = publish
        self._cv = threading.Condition()
        self._state: TickState | None = None
        self._closed = False
        self.published = 0
        self.skipped = 0
        self._thread = threading.Thread(target=self._run, name=name, daemon=True)
        self._thread.start()

    def __call__(self, state: TickState) -> None:
        with self._cv:
            if self._state is not None:
                self.skipped += 1
            self._state = state
            self._cv.notify()

    def _run(self) -> None:
        while True:
            with self._cv:
                while self._state is None and not self._closed:
                    self._cv.wait()
                if self._closed:
                    return
                state, self._state = self._state, None
            assert state is not None  # the wait above ends with a state, or on close
            try:
                if self._publish(state) is False:
                    self.skipped += 1
                else:
                    self.published += 1
            except Exception:  # a broken view must not take the page down with it
                logging.getLogger(__name__).exception("state publish failed")

    def close(self) -> None:
        with self._cv:
            self._closed = True
            self._cv.notify()
        self._thread.join(5.0)
