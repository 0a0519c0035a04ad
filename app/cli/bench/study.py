"""Studies: runs per second in this process one after another (the serial sweep `tune` used to be)
against 1 and 2 local Dask workers, for truth and vision points; the engine's overhead per run;
the time to the first result from a cold start; the client's memory over a study of 10^5 short
runs; and a model of 8, 64 and 512 workers from the measured costs (docs/studies.md).

Every figure is a ratio or a cost per unit within one run of this bench (the machine is shared):
runs per second at N workers against the same runs made here one after another."""

from __future__ import annotations

import math
import tempfile
import time
from collections.abc import Callable
from pathlib import Path
from typing import Any
from app.cli.bench.family import Family

TRUTH = """[study]
scenario = "experiment1"
duration_s = 20.0
seed = 1
replicates = {reps}
[grid]
"gains.k_f1" = {{lo = 0.05, hi = 0.4, n = 8}}
"measurement.position_noise_m" = {{lo = 0.0, hi = 0.01, n = 5}}
"""
VISION = """[study]
scenario = "experiment1"
feedback = "vision"
duration_s = 20.0
seed = 1
replicates = {reps}
[grid]
"gains.k_f1" = [0.1, 0.2, 0.3]
"measurement.vision_position_noise_m" = [0.0, 0.01]
"""
# 10^5 short truth runs: what the client and the scheduler hold must not grow with the study
MEMORY = """[study]
scenario = "paper_simulation"
duration_s = 0.5
seed = 1
replicates = 100
[grid]
"gains.k_f1" = {lo = 0.05, hi = 0.5, n = 40}
"gains.k_w2" = {lo = 1.0, hi = 4.0, n = 25}
"""


def _spec(text: str, name: str) -> Any:
    from app.study.session import parse_study_text

    return parse_study_text(text, name)


def serial_rate(spec: Any) -> tuple[float, float]:
    """(runs per second, mean compute per run) of every run made here one after another."""
    from app.study.batch import run_runs, warm_up
    from app.study.engine import pending_runs

    warm_up(spec)
    items = list(pending_runs(spec, set()))
    start = time.perf_counter()
    rows, _ = run_runs(spec, items, "local")
    wall = time.perf_counter() - start
    return len(rows) / wall, sum(r["wall_s"] for r in rows) / max(len(rows), 1)


def engine_rate(spec: Any, workers: int, tmp: Path) -> dict[str, float]:
    """A study on a warm local cluster of ``workers``: runs per second, the compute per run, and
    the time to the first result from a cold start (cluster and kernels included)."""
    from app.study.engine import Engine, run_grid
    from app.study.store import StudyFolder

    t0 = time.monotonic()
    engine = Engine(spec, workers, None)
    try:
        folder = StudyFolder(tmp)
        folder.open(spec, tmp / "study.toml", overwrite=True)
        start = time.monotonic()
        out = run_grid(spec, folder, engine, None, t0)
        wall = time.monotonic() - start
        compute = float(folder.dataset().to_table(columns=["wall_s"]).column("wall_s").to_numpy().sum())
        parts = len(list(folder.results.glob("part-*.parquet")))
    finally:
        engine.close()
    return {"runs_per_s": out.made / wall, "compute_per_run_s": compute / max(out.made, 1),
            "first_result_s": out.first_result_s, "wall_s": wall, "compute_s": compute, "parts": parts,
            "runs": out.made}


def part_write_s(spec: Any, tmp: Path, rows_per_part: int = 500) -> float:
    """Seconds the client takes to write one part of ``rows_per_part`` rows."""
    from app.study.batch import run_runs
    from app.study.engine import pending_runs
    from app.study.store import StudyFolder

    items = list(pending_runs(spec, set()))[:20]
    rows, _ = run_runs(spec, items, "local")
    rows = (rows * (rows_per_part // len(rows) + 1))[:rows_per_part]
    folder = StudyFolder(tmp)
    folder.results.mkdir(parents=True, exist_ok=True)
    start = time.perf_counter()
    for _ in range(20):
        folder.write_part(spec, rows)
    return (time.perf_counter() - start) / 20


def memory_run(tmp: Path, workers: int = 2) -> dict[str, float]:
    """`omniformation study` of 10^5 short truth runs as a user starts it, and its RSS (the client;
    a LocalCluster's scheduler runs in the same process) every second, against the parts written."""
    import subprocess
    import sys

    tmp.mkdir(parents=True, exist_ok=True)
    (tmp / "memory.toml").write_text(MEMORY)
    out = tmp / "out"
    start = time.monotonic()
    proc = subprocess.Popen([sys.executable, "-m", "app.cli", "study", str(tmp / "memory.toml"), "--out", str(out),
                             "--workers", str(workers)], stdout=subprocess.DEVNULL, stderr=subprocess.DEVNULL)
    samples: list[tuple[int, float]] = []
    while proc.poll() is None:
        time.sleep(1.0)
        try:
            status = Path(f"/proc/{proc.pid}/status").read_text()
        except OSError:
            break
        rss = next((int(line.split()[1]) / 1e3 for line in status.splitlines() if line.startswith("VmRSS:")), math.nan)
        if not math.isfinite(rss):  # the process has ended (a zombie has no RSS)
            break
        samples.append((len(list((out / "results").glob("part-*.parquet"))) if (out / "results").exists() else 0, rss))
    proc.wait()
    wall = time.monotonic() - start
    import pyarrow.dataset as pds

    runs = pds.dataset(str(out / "results"), format="parquet").count_rows() if proc.returncode == 0 else 0
    total = max((p for p, _ in samples), default=0) or 1
    running = [(p, m) for p, m in samples if p < total]  # before the last part: the summary and plots come after
    early = [m for p, m in running if 0.1 * total <= p <= 0.3 * total]
    late = [m for p, m in running if p >= 0.7 * total]
    return {"runs": runs, "wall_s": wall, "peak_mb": max((m for _, m in samples), default=math.nan),
            "running_peak_mb": max((m for _, m in running), default=math.nan),
            "early_mb": sum(early) / len(early) if early else math.nan,
            "late_mb": sum(late) / len(late) if late else math.nan}


def scaling_model(compute_s: float, per_task_s: float, part_s: float, batch_s: float,
                  workers: int, scheduler_task_s: float = 1e-3) -> float:
    """Runs per second of ``workers`` by the model: each worker makes runs of ``compute_s`` in
    batches of ``batch_s`` of compute, paying ``per_task_s`` per batch; the client writes one part
    per batch (``part_s``) and the scheduler spends ``scheduler_task_s`` per batch, each on one
    thread: the study goes at the slowest of the workers, the client and the scheduler."""
    runs_per_batch = max(1.0, batch_s / compute_s)
    per_batch = runs_per_batch * compute_s + per_task_s
    workers_rate = workers * runs_per_batch / per_batch
    central_rate = runs_per_batch / (part_s + scheduler_task_s)
    return min(workers_rate, central_rate)


def run_family(print_fn: Callable[[str], None] = print) -> dict[str, float]:
    from app.study.engine import BATCH_S

    figures: dict[str, float] = {}
    with tempfile.TemporaryDirectory(prefix="omniformation-bench-study-") as td:
        tmp = Path(td)
        for kind, template, reps in (("truth", TRUTH, 25), ("vision", VISION, 2)):
            spec = _spec(template.format(reps=reps), f"{kind} study")
            serial, compute = serial_rate(spec)
            one = engine_rate(spec, 1, tmp / f"{kind}-1")
            two = engine_rate(spec, 2, tmp / f"{kind}-2")
            overhead = one["wall_s"] / one["compute_s"] - 1.0
            print_fn(f"study, {kind} points ({spec.runs} runs of {compute * 1e3:.1f} ms): serial {serial:.1f} runs/s;"
                     f" 1 worker {one['runs_per_s']:.1f} runs/s (x{one['runs_per_s'] / serial:.2f}); 2 workers"
                     f" {two['runs_per_s']:.1f} runs/s (x{two['runs_per_s'] / one['runs_per_s']:.2f} of 1 worker;"
                     f" target >= 1.7 for vision); overhead per run on 1 worker {overhead * 100:+.1f} % of its compute"
                     f" (target <= 5 %); first result {two['first_result_s']:.1f} s after a cold start of 2 workers"
                     f" (target <= 10 s)")
            figures.update({f"study_{kind}_serial_runs_per_s": serial, f"study_{kind}_1w_runs_per_s": one["runs_per_s"],
                            f"study_{kind}_2w_runs_per_s": two["runs_per_s"],
                            f"study_{kind}_2w_over_1w": two["runs_per_s"] / one["runs_per_s"],
                            f"study_{kind}_overhead_pct": overhead * 100,
                            f"study_{kind}_first_result_s": two["first_result_s"],
                            f"study_{kind}_compute_per_run_s": compute,
                            f"study_{kind}_per_task_s": max(0.0, (one["wall_s"] - one["compute_s"]) / max(one["parts"], 1))})
        part = part_write_s(_spec(TRUTH.format(reps=1), "truth study"), tmp / "parts")
        figures["study_part_write_s"] = part
        mem = memory_run(tmp / "memory")
        print_fn(f"`study` of {mem['runs']:.0f} short truth runs on 2 workers in {mem['wall_s']:.0f} s: the client's RSS"
                 f" (the LocalCluster's scheduler runs in it) {mem['early_mb']:.0f} MB at 10-30 % of the parts,"
                 f" {mem['late_mb']:.0f} MB from 70 %, peak {mem['running_peak_mb']:.0f} MB while running (target <= 500 MB,"
                 f" flat); {mem['peak_mb']:.0f} MB writing the summary and plots of the whole study")
        figures.update({"study_memory_peak_mb": mem["peak_mb"], "study_memory_running_peak_mb": mem["running_peak_mb"],
                        "study_memory_early_mb": mem["early_mb"],
                        "study_memory_late_mb": mem["late_mb"]})
        print_fn(f"one part of 500 rows written by the client in {part * 1e3:.1f} ms")
        for n in (8, 64, 512):
            rates = [scaling_model(figures[f"study_{k}_compute_per_run_s"], figures[f"study_{k}_per_task_s"], part,
                                   BATCH_S, n) for k in ("truth", "vision")]
            print_fn(f"model, {n} workers: truth {rates[0]:.0f} runs/s, vision {rates[1]:.0f} runs/s"
                     f" (10^6 vision runs in {1e6 / rates[1] / 3600:.1f} h)")
            figures[f"study_model_{n}w_truth_runs_per_s"] = rates[0]
            figures[f"study_model_{n}w_vision_runs_per_s"] = rates[1]
    return figures


FAMILY = Family('study', run_family, 'studies: runs per second serial against 1 and 2 Dask workers, overhead, first result, memory',
                default=False, order=25)
