"""An emulated ROS 2 mobile base (``omniformation emulate-base --ros2``): it takes
geometry_msgs/msg/Twist on /cmd_vel and publishes nav_msgs/msg/Odometry on /odom, moved by the
simulator's robot dynamics (core.sim.team.step_team, one robot). A command older than
CMD_TIMEOUT_S is taken as zero, as real bases do. ``speed_scale`` makes it a base that slips
(or is mis-calibrated): it really moves that share of what it is told, and its odometry says
what it really did."""

from __future__ import annotations

import math
import threading
import time
from typing import Any

import numpy as np

from core.sim.team import FollowerDynamics, TeamState, step_team
from core.types import Commands

from app.backends.ros2 import ODOMETRY, TWIST, Ros2Node, finite_twist, header, msg, pose, twist

CMD_TIMEOUT_S = 0.5


class EmulatedBase:
    """One base: its pose (odom frame), its command and the odometry it publishes at ``rate_hz``."""

    def __init__(self, node: Ros2Node, rate_hz: float = 50.0, dynamics: FollowerDynamics | None = None,
                 cmd_topic: str = "/cmd_vel", odom_topic: str = "/odom", speed_scale: float = 1.0) -> None:
        if not (math.isfinite(speed_scale) and speed_scale >= 0.0):
            raise ValueError(f"speed scale {speed_scale!r}: must be a finite number >= 0")
        self.node = node
        self.speed_scale = speed_scale
        self.dt = 1.0 / rate_hz
        self.dynamics = dynamics or FollowerDynamics()
        self.state = TeamState(np.zeros(3), np.array([[0.0, 0.0, math.pi / 2]]), np.zeros((1, 2)))
        self._lock = threading.Lock()
        self._cmd: tuple[float, float, float] = (0.0, 0.0, -math.inf)  # v, w, monotonic time it came
        self.commands: list[tuple[float, float]] = []  # every command taken, in order (for tests and the summary)
        self._odom = node.publisher(odom_topic, ODOMETRY)
        node.subscribe(cmd_topic, TWIST, self._on_cmd)
        self._stop = threading.Event()
        self._rng = np.random.default_rng(0)
        self._thread = threading.Thread(target=self._run, name="omniformation-base", daemon=True)

    def _on_cmd(self, m: Any) -> None:
        v, w = finite_twist(m)
        with self._lock:
            self._cmd = (v, w, time.monotonic())
            self.commands.append((v, w))

    def command(self) -> tuple[float, float]:
        """The command in force: the last one, or zero once it is older than CMD_TIMEOUT_S."""
        with self._lock:
            v, w, at = self._cmd
        return (v, w) if time.monotonic() - at <= CMD_TIMEOUT_S else (0.0, 0.0)

    def step(self) -> None:
        """Move by one period under the command in force (times the speed scale: a slipping base)
        and publish the odometry: what it really did."""
        v, w = (self.speed_scale * c for c in self.command())
        self.state = step_team(self.state, Commands(np.array([v]), np.array([w])), (0.0, 0.0), self.dt, 0.0,
                               self._rng, self.dynamics)
        x, y, theta = (float(q) for q in self.state.followers[0])
        vv, ww = (float(q) for q in self.state.follower_vel[0])
        cov = np.zeros(36)
        self._odom.put(msg(ODOMETRY, header=header("odom"), child_frame_id="base_link",
                           pose=msg("geometry_msgs/msg/PoseWithCovariance", pose=pose(x, y, theta), covariance=cov),
                           twist=msg("geometry_msgs/msg/TwistWithCovariance", twist=twist(vv, ww), covariance=cov)))

    def _run(self) -> None:
        deadline = time.monotonic()
        while not self._stop.is_set():
            self.step()
            deadline += self.dt
            wait = deadline - time.monotonic()
            if wait < -0.25:  # far behind (a busy machine): start afresh rather than burst
                deadline = time.monotonic()
            elif wait > 0:
                self._stop.wait(wait)

    def start(self) -> None:
        self._thread.start()

    def close(self) -> None:
        self._stop.set()
        if self._thread.is_alive():
            self._thread.join(2.0)
        self._odom.close()
