"""Writing a simulation log as CSV (the column layout users and their scripts rely on: see README)."""

from __future__ import annotations

from pathlib import Path

import numpy as np

from core.sim.run import SimulationLog


_TRUTH = ("x", "y", "a", "xd", "yd", "v", "w")
_VISION = ("x_est", "y_est", "a_est", "tracked")


def csv_columns(n: int, vision: bool = False) -> list[str]:
    cols = ["t", "leader_x", "leader_y", "leader_theta", "leader_v", "leader_w"]
    for i in range(1, n + 1):
        cols += [f"f{i}_{k}" for k in _TRUTH + (_VISION if vision else ())]
    return cols


def log_table(log: SimulationLog, tracked: np.ndarray | None = None) -> np.ndarray:
    """Rows in csv_columns order: SI units, radians, followers in the leader frame.

    With ``tracked`` (a vision run) each follower also gets the pipeline's estimate
    (x_est, y_est, a_est; NaN until first seen) and whether it was tracked (1/0).
    """
    parts = [log.p, log.a[..., None], log.p_d, log.commands]
    if tracked is not None:
        parts += [log.p_meas, log.a_meas[..., None], tracked[..., None].astype(np.float64)]
    per_follower = np.concatenate(parts, axis=-1)  # (T, n, 7 or 11)
    return np.column_stack(
        [log.t, log.leader, log.leader_twist, per_follower.reshape(len(log.t), -1)]
    )


def write_csv(log: SimulationLog, path: Path, tracked: np.ndarray | None = None) -> None:
    header = ",".join(csv_columns(log.n, vision=tracked is not None))
    np.savetxt(path, log_table(log, tracked), delimiter=",", header=header, comments="", fmt="%.6g")
