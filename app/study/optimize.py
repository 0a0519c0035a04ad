"""A study's ``[optimize]``: Optuna's TPE through ask/tell, each trial a point of the study (its
replicates run as batches on the same workers), its objective over the metrics' medians across the
replicates (``converged``: the rate), minimised. The journal file (``optuna.journal``) keeps the
trials: the same command resumes, re-running only what results/ does not hold, and a trial asked
but not told when the last session stopped is finished first.

A run that did not settle has no settling time; the objective sees the run's length for it (the
longest it could have been), so a point that never settles cannot look best.
"""

from __future__ import annotations

import math
import time
from typing import Any

import numpy as np

from app.study.batch import RunItem, run_batch
from app.study.engine import IN_FLIGHT, Engine, Ledger, Outcome, Progress, light
from app.study.store import JOURNAL, StudyFolder
from core.study.point import METRICS
from core.study.spec import StudySpec, evaluate_objective, point_key, run_seed

STUDY_NAME = "omniformation"


def _storage(folder: StudyFolder) -> Any:
    from optuna.storages import JournalStorage
    from optuna.storages.journal import JournalFileBackend

    return JournalStorage(JournalFileBackend(str(folder.out / JOURNAL)))


def _study(spec: StudySpec, folder: StudyFolder) -> Any:
    import optuna
    from optuna.samplers import TPESampler

    optuna.logging.set_verbosity(optuna.logging.WARNING)
    return optuna.create_study(study_name=STUDY_NAME, storage=_storage(folder), direction="minimize",
                               sampler=TPESampler(seed=spec.seed, constant_liar=True), load_if_exists=True)


def run_length_s(spec: StudySpec) -> float:
    if spec.test is not None:
        return spec.test.window_s
    if spec.duration_s is not None:
        return spec.duration_s
    from core.config import parse_scenario

    return max(parse_scenario(s.text, s.source).duration_s for s in spec.scenarios)


def objective(spec: StudySpec, rows: list[dict[str, Any]]) -> float:
    """The objective of one trial's rows (NaN: no run finished)."""
    assert spec.optimize is not None
    if not rows:
        return math.nan
    length = run_length_s(spec)
    medians: dict[str, float] = {}
    for name in METRICS:
        vals = np.array([float(r[name]) if r[name] is not None else math.nan for r in rows], dtype=np.float64)
        if name == "converged":
            medians[name] = float(np.mean(vals))
            continue
        if name == "settling_s":
            vals = np.where(np.isfinite(vals), vals, length)
        finite = vals[np.isfinite(vals)]
        medians[name] = float(np.median(finite)) if finite.size else math.nan
    return evaluate_objective(spec.optimize.objective, medians)


def _values(spec: StudySpec, trial: Any) -> dict[str, Any]:
    out: dict[str, Any] = {}
    for a in spec.optimize_axes:
        if a.integer:
            out[a.name] = int(trial.suggest_int(a.name, int(math.ceil(a.lo)), int(math.floor(a.hi)), log=a.log))
        else:
            out[a.name] = float(trial.suggest_float(a.name, a.lo, a.hi, log=a.log))
    return out


def history(folder: StudyFolder) -> list[tuple[int, float]]:
    """(trial number, objective) of every finished trial in the journal."""
    import optuna

    path = folder.out / JOURNAL
    if not path.exists():
        return []
    optuna.logging.set_verbosity(optuna.logging.WARNING)
    study = optuna.load_study(study_name=STUDY_NAME, storage=_storage(folder))
    return [(t.number, float(t.value)) for t in study.trials
            if t.state == optuna.trial.TrialState.COMPLETE and t.value is not None]


def best(folder: StudyFolder, spec: StudySpec) -> dict[str, Any] | None:
    import optuna

    if not (folder.out / JOURNAL).exists():
        return None
    study = optuna.load_study(study_name=STUDY_NAME, storage=_storage(folder))
    done = [t for t in study.trials if t.state == optuna.trial.TrialState.COMPLETE]
    if not done:
        return None
    b = min(done, key=lambda t: float(t.value if t.value is not None else math.inf))
    return {"trial": b.number, "trials": len(done), "values": dict(b.params),
            "value": float(b.value if b.value is not None else math.nan)}


def run_optimize(spec: StudySpec, folder: StudyFolder, engine: Engine, progress: Progress | None = None,
                 start: float | None = None) -> Outcome:
    """Ask, run, tell until the study's trials are told (or Ctrl-C)."""
    import optuna
    from distributed import as_completed

    assert spec.optimize is not None
    start = time.monotonic() if start is None else start
    study = _study(spec, folder)
    table = folder.table()
    have: dict[str, list[dict[str, Any]]] = {}
    if table.num_rows:
        for r in table.to_pylist():
            have.setdefault(r["point"], []).append(r)
    skipped = sum(len(v) for v in have.values())
    shipped = light(spec)
    workers = engine.workers
    ledger = Ledger(spec, folder, start)
    ac = as_completed()
    open_trials: dict[int, dict[str, Any]] = {}  # trial number -> {"key", "values", "missing": set, "rows"}
    futures: dict[Any, tuple[int, list[RunItem]]] = {}
    interrupted = False
    running = optuna.trial.TrialState.RUNNING

    def told() -> int:
        return sum(1 for t in study.get_trials(deepcopy=False) if t.state != running)

    def launch(number: int, values: dict[str, Any]) -> None:
        key = point_key(values)
        rows = list(have.get(key, []))
        done_reps = {r["replicate"] for r in rows}
        missing = [r for r in range(spec.replicates) if r not in done_reps]
        open_trials[number] = {"key": key, "values": values, "missing": set(missing), "rows": rows}
        if not missing:
            finish(number)
            return
        items = [RunItem(key, values, r, run_seed(spec.seed, key, r)) for r in missing]
        fut = engine.client.submit(run_batch, shipped, items, pure=False)
        futures[fut] = (number, items)
        ac.add(fut)

    def finish(number: int) -> None:
        entry = open_trials.pop(number)
        value = objective(spec, entry["rows"])
        if math.isfinite(value):
            study.tell(number, value)
        else:
            study.tell(number, state=optuna.trial.TrialState.FAIL)

    # trials asked but never told by an earlier session: finish them first
    for t in study.get_trials(deepcopy=False, states=(running,)):
        launch(t.number, {a.name: t.params[a.name] for a in spec.optimize_axes if a.name in t.params})

    def top_up() -> None:
        while len(futures) < IN_FLIGHT * workers and told() + len(open_trials) < spec.optimize.trials:  # type: ignore[union-attr]
            trial = study.ask()
            launch(trial.number, _values(spec, trial))

    try:
        top_up()
        for fut in ac:
            number, items = futures.pop(fut)
            rows = ledger.take(fut, items)
            entry = open_trials.get(number)
            if entry is not None:
                entry["rows"].extend(rows)
                finish(number)
            if progress is not None:
                progress.update(skipped + ledger.made, ledger.failed)
            top_up()
    except KeyboardInterrupt:
        interrupted = True
        for fut in list(futures):
            fut.cancel()
    if progress is not None:
        progress.finish()
    return Outcome(ledger.made, ledger.failed, skipped, spec.runs, time.monotonic() - start, workers, ledger.first,
                   interrupted, engine.dashboard)
