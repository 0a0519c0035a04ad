"""One `omniformation study` session: read the study file, open (or resume) its folder, run what is
missing on the engine, then write the summary and the plots."""

from __future__ import annotations

import sys
import time
from dataclasses import dataclass
from pathlib import Path
from typing import Any

from app.files import UserError, display_path, read_text, resolve_scenario_path
from app.study.engine import Engine, Outcome, Progress
from app.study.store import MANIFEST, StudyFolder
from core.study.spec import ScenarioSource, StudySpec


def scenario_source(name_or_path: str, relative_to: Path | None = None) -> ScenarioSource:
    """A scenario by name (static_config/scenarios) or .toml path (relative to the study file)."""
    if relative_to is not None and name_or_path.endswith(".toml") and not Path(name_or_path).is_absolute():
        candidate = relative_to / name_or_path
        if candidate.exists():
            name_or_path = str(candidate)
    path = resolve_scenario_path(name_or_path)
    text = read_text(path, "scenario")
    name = path.stem if name_or_path.endswith(".toml") else name_or_path
    return ScenarioSource(name, text, display_path(path))


def parse_study_text(text: str, source: str, relative_to: Path | None = None) -> StudySpec:
    from core.config import ConfigError
    from core.study.spec import parse_study

    try:
        return parse_study(text, source, lambda n: scenario_source(n, relative_to))
    except ConfigError as exc:
        raise UserError(str(exc)) from None
    except ValueError as exc:
        raise UserError(f"{source}: {exc}") from None


def load_study(path: Path) -> StudySpec:
    """Read and check a study file; any problem is one UserError line."""
    if path.is_dir():
        raise UserError(f"{display_path(path)}: is a folder; give the study's .toml file")
    return parse_study_text(read_text(path, "study"), display_path(path), path.parent)


def spec_of_folder(out: Path) -> StudySpec:
    """The study a folder holds, from its manifest (the study's text and its scenarios' texts)."""
    folder = StudyFolder(out)
    m = folder.manifest()
    scen: dict[str, str] = m.get("scenarios", {}) if isinstance(m.get("scenarios"), dict) else {}
    from core.config import ConfigError
    from core.study.spec import parse_study

    def source(name: str) -> ScenarioSource:
        key = Path(name).stem if name.endswith(".toml") else name
        if key in scen:
            return ScenarioSource(key, scen[key], f"{MANIFEST} ({key})")
        return scenario_source(name)

    try:
        return parse_study(m["study_text"], f"{display_path(out / MANIFEST)}", source)
    except ConfigError as exc:
        raise UserError(str(exc)) from None


@dataclass
class SessionResult:
    outcome: Outcome
    summary: Path
    plots: list[Path]
    best: dict[str, Any] | None


def run_session(spec: StudySpec, study_path: Path, out: Path, workers: int | None = None, cluster: str | None = None,
                overwrite: bool = False, say: Any = print, progress_out: Any = None) -> SessionResult:
    start = time.monotonic()
    folder = StudyFolder(out)
    resumed = folder.open(spec, study_path, overwrite)
    done = len(folder.done()) if resumed else 0
    what = "optimisation" if spec.optimize else "study"
    say(f"{what}: {spec.points} {'trials' if spec.optimize else 'points'} x {spec.replicates} replicates ="
        f" {spec.runs} runs, {spec.feedback} feedback -> {display_path(out)}"
        + (f" (resumed: {done} runs already there)" if resumed else ""))
    if not spec.optimize and done >= spec.runs:
        say(f"study: all {spec.runs} runs are in {display_path(out / 'results')}: 0 to run")
        return _finish(spec, folder, Outcome(0, 0, done, spec.runs, 0.0, 0, float("nan")))
    engine = Engine(spec, workers, cluster)
    try:
        where = cluster or f"a local cluster of {engine.workers} worker{'s' if engine.workers != 1 else ''}"
        say(f"study: on {where}; Dask dashboard: {engine.dashboard or 'none (bokeh missing)'}")
        progress = Progress(spec.runs, done, spec.points, spec.replicates,
                            out=progress_out if progress_out is not None else sys.stderr)
        if spec.optimize is not None:
            from app.study.optimize import run_optimize

            outcome = run_optimize(spec, folder, engine, progress, start)
        else:
            from app.study.engine import run_grid

            outcome = run_grid(spec, folder, engine, progress, start)
    finally:
        engine.close()
    return _finish(spec, folder, outcome)


def _finish(spec: StudySpec, folder: StudyFolder, outcome: Outcome) -> SessionResult:
    from app.study.summary import draw_plots, write_summary

    best = None
    if spec.optimize is not None:
        from app.study.optimize import best as best_of

        best = best_of(folder, spec)
    summary = write_summary(spec, folder, outcome.seconds if outcome.made else None, outcome.workers or None, best)
    plots = draw_plots(spec, folder)
    return SessionResult(outcome, summary, plots, best)


def redraw(out: Path, fmt: str = "png") -> list[Path]:
    """`report DIR`: the summary and the plots again, from the folder's files alone."""
    from app.study.summary import draw_plots, write_summary

    spec = spec_of_folder(out)
    folder = StudyFolder(out)
    best = None
    if spec.optimize is not None:
        from app.study.optimize import best as best_of

        best = best_of(folder, spec)
    return [write_summary(spec, folder, best=best), *draw_plots(spec, folder, fmt)]
