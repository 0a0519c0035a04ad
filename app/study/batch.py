"""What a worker runs: a batch of a study's runs, each through the one point function
(core.study.point.run_point), timed, and caught one by one (a run that raises is a failure row,
the batch goes on). Also the warm-up each worker does once before its first batch.

This module is imported by Dask's workers (on this machine or a cluster's): it holds no Dask
object, so the same functions run in-process (:func:`run_runs`) for the serial sweep and tests.
"""

from __future__ import annotations

import time
from dataclasses import dataclass
from typing import Any

from core.study.point import Step, run_point
from core.study.spec import SCENARIO_AXIS, StudySpec, scenario_for

_RIGS: dict[str, Any] = {}  # the synthetic rig and its Γ, loaded once per process


@dataclass(frozen=True)
class RunItem:
    """One run: the point's key and values, the replicate and its seed."""

    point: str
    values: dict[str, Any]
    replicate: int
    seed: int


def _rig(camera: str | None = None, calibration: str | None = None) -> Any:
    """The synthetic rig and its Γ (the shipped ones unless the study names others)."""
    from pathlib import Path

    from app.files import SYNTHETIC_CALIBRATED, SYNTHETIC_CAMERA, load_synthetic_rig

    cam = Path(camera) if camera else SYNTHETIC_CAMERA
    cal = Path(calibration) if calibration else SYNTHETIC_CALIBRATED
    key = f"{cam}|{cal}"
    if key not in _RIGS:
        _RIGS[key] = load_synthetic_rig(cam, cal)
    return _RIGS[key]


def run_one(spec: StudySpec, item: RunItem) -> dict[str, Any]:
    """One run's metrics (core.study.point.METRICS); raises what the run raises."""
    name = item.values.get(SCENARIO_AXIS, spec.scenarios[0].name)
    source = next(s for s in spec.scenarios if s.name == name)
    scenario = scenario_for(spec, source, item.values, item.seed)
    rig, gamma = _rig(spec.camera, spec.calibration) if spec.vision else (None, None)
    step = None
    if spec.test is not None:
        from core.study.point import LEAD_S, settled_start

        twist = scenario.leader.twist(0.0)
        step = Step(spec.test, (float(twist[0]), float(twist[1])), LEAD_S)
        scenario = settled_start(scenario)
    return run_point(scenario, rig, gamma, step).metrics


def run_runs(spec: StudySpec, items: list[RunItem], worker: str) -> tuple[list[dict[str, Any]], list[dict[str, Any]]]:
    """A batch: (rows, failures), each a dict of the results' columns."""
    rows: list[dict[str, Any]] = []
    failures: list[dict[str, Any]] = []
    for item in items:
        head: dict[str, Any] = {"point": item.point, "replicate": item.replicate, "seed": item.seed, **item.values}
        start = time.perf_counter()
        try:
            metrics = run_one(spec, item)
        except Exception as exc:  # noqa: BLE001 - one run that raises is a failure row; the study goes on
            failures.append({**head, "error": f"{type(exc).__name__}: {exc}"[:500], "worker": worker})
            continue
        rows.append({**head, **metrics, "wall_s": time.perf_counter() - start, "worker": worker})
    return rows, failures


def run_batch(spec: StudySpec, items: list[RunItem]) -> tuple[list[dict[str, Any]], list[dict[str, Any]]]:
    """The task a Dask worker runs: :func:`run_runs`, named by the worker it ran on."""
    return run_runs(spec, items, _worker_name())


def _worker_name() -> str:
    try:
        from distributed import get_worker

        w = get_worker()
        return str(w.name) if w.name is not None else str(w.address)
    except ValueError:  # not on a worker: in this process
        return "local"


def warm_up(spec: StudySpec) -> float:
    """Load the kernels this study's runs use (from numba's cache on disk, which every worker
    process on one machine shares: numba writes a cache file under a temporary name and renames it,
    so a reader never sees half of one) and, for vision, its rig: the study's first point, two
    ticks long, through the same path as every run. Returns the seconds it took."""
    import dataclasses

    start = time.perf_counter()
    values = spec.point(0) if spec.optimize is None else {}
    name = values.get(SCENARIO_AXIS, spec.scenarios[0].name)
    source = next(s for s in spec.scenarios if s.name == name)
    scenario = scenario_for(spec, source, values, 0)
    scenario = scenario.replace(duration_s=2.0 / scenario.rate_hz)
    rig, gamma = _rig(spec.camera, spec.calibration) if spec.vision else (None, None)
    step = None
    if spec.test is not None:
        from core.study.point import settled_start

        twist = scenario.leader.twist(0.0)
        step = Step(dataclasses.replace(spec.test, window_s=WARM_WINDOW_S), (float(twist[0]), float(twist[1])), 0.0)
        scenario = settled_start(scenario)
    run_point(scenario, rig, gamma, step)
    return time.perf_counter() - start


WARM_WINDOW_S = 3.0  # the shortest window a step test takes (core.control.tuning.WINDOW_S)
