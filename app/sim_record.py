"""`simulate --record FILE`: an offline run written as the same MCAP a live session makes."""

from __future__ import annotations

from pathlib import Path

import numpy as np

from app.loop import TickState
from app.params import Params
from app.recorder import Recorder
from core.sim.run import SimulationLog


def record_simulation(
    log: SimulationLog,
    path: Path,
    metadata: dict[str, str],
    tracked: np.ndarray | None = None,
    phases: tuple[str, ...] | None = None,
    frames: dict[int, bytes] | None = None,
    a_raw: np.ndarray | None = None,
    frame_rate_hz: float = 10.0,
) -> int:
    """Write every row of ``log`` as a tick, and the JPEG frames given (by row); returns the ticks."""
    sc = log.scenario
    n = log.n
    params = Params(gains=sc.gains, slots=sc.slots.copy(), n_followers=n, leader_mode="stop")
    rec = Recorder(path, metadata, params, frame_rate_hz=frame_rate_hz, start_ns=0)
    v_lyap = log.v_lyap
    try:
        for k in range(len(log.t)):
            rec.on_tick(TickState(
                tick=k, t=float(log.t[k]) - float(log.t[0]), leader=log.leader[k],
                leader_twist=(float(log.leader_twist[k, 0]), float(log.leader_twist[k, 1])),
                followers_world=log.followers_world[k], p_est=log.p_meas[k], a_est=log.a_meas[k],
                tracked=tracked[k] if tracked is not None else np.ones(n, dtype=bool),
                p_true=log.p[k], a_true=log.a[k], p_d=log.p_d[k], slot_targets=sc.slots,
                assignment=log.assignment, commands=log.commands[k], a_err=log.a_err[k],
                v_lyap=v_lyap[k], gains=sc.gains, params_version=0, stopped=False, paused=False,
                link_state="simulated", rate_hz=sc.rate_hz, stage_ms={},
                phase=phases[k] if phases is not None else "truth",
                a_raw=a_raw[k] if a_raw is not None else None,
            ))
            if frames is not None and k in frames:
                rec.add_jpeg(float(log.t[k]) - float(log.t[0]), frames[k])
    finally:
        rec.close()
    return len(log.t)
