"""Writing a simulation log as CSV (the column layout the issue and users rely on)."""

from __future__ import annotations

from pathlib import Path

import numpy as np

from core.sim.run import SimulationLog


def csv_columns(n: int) -> list[str]:
    cols = ["t", "leader_x", "leader_y", "leader_theta", "leader_v", "leader_w"]
    for i in range(1, n + 1):
        cols += [f"f{i}_{k}" for k in ("x", "y", "a", "xd", "yd", "v", "w")]
    return cols


def log_table(log: SimulationLog) -> np.ndarray:
    """(T, 6 + 7 n) rows in csv_columns order: SI units, radians, followers in the leader frame."""
    per_follower = np.concatenate(
        [log.p, log.a[..., None], log.p_d, log.commands], axis=-1
    )  # (T, n, 7)
    return np.column_stack(
        [log.t, log.leader, log.leader_twist, per_follower.reshape(len(log.t), -1)]
    )


def write_csv(log: SimulationLog, path: Path) -> None:
    np.savetxt(path, log_table(log), delimiter=",", header=",".join(csv_columns(log.n)), comments="", fmt="%.6g")
