"""What a benchmark family is, how `bench` finds the families, and the record of a run.

A family is one module of app/cli/bench/ with a ``FAMILY = Family(...)`` at module level: its
name (``bench --family NAME``), the function that measures (takes ``print_fn`` for its detail
lines, returns its figures by name), whether plain `bench` runs it (the families that answer "did
this change make it slower?" within minutes; `bench --full` runs every one) and its place in the
order. Adding a family is adding that one module: :func:`families` finds it.

Every run is saved as JSON (:func:`record`): the figures, the commit, the machine (CPU model and
count, its load before and after), so a change is judged against its parent on one machine
(`bench --compare A.json B.json`, :func:`compare`).
"""

from __future__ import annotations

import importlib
import json
import math
import os
import pkgutil
import platform
import subprocess
from collections.abc import Callable
from dataclasses import dataclass
from pathlib import Path
from typing import Any

PrintFn = Callable[[str], None]


@dataclass(frozen=True)
class Family:
    """One benchmark family: ``run(print_fn)`` returns its figures by name."""

    name: str
    run: Callable[[PrintFn], dict[str, float]]
    what: str
    default: bool = False  # plain `bench` runs it (else only --full and --family)
    order: int = 100  # families run in this order (then by name)


def families() -> list[Family]:
    """Every family of app/cli/bench/ (each module's ``FAMILY``), in their order: the modules
    beside this one, by their files (this module is below them: it imports none by name)."""
    package = __name__.rpartition(".")[0]
    found = []
    for info in pkgutil.iter_modules([str(Path(__file__).resolve().parent)]):
        family = getattr(importlib.import_module(f"{package}.{info.name}"), "FAMILY", None)
        if isinstance(family, Family):
            found.append(family)
    return sorted(found, key=lambda f: (f.order, f.name))


def choose(everything: list[Family], full: bool, names: list[str] | None) -> list[Family]:
    """The families a run measures: ``names`` (each one that exists), else every one with
    ``full``, else the default ones. ValueError in one line for a name that is no family."""
    if names:
        by_name = {f.name: f for f in everything}
        unknown = [n for n in names if n not in by_name]
        if unknown:
            raise ValueError(f"--family {unknown[0]}: no such family; the families are "
                             + ", ".join(f.name for f in everything))
        return [by_name[n] for n in dict.fromkeys(names)]
    return list(everything) if full else [f for f in everything if f.default]


def figure_line(family: str, name: str, value: float) -> str:
    """One figure, one line: ``family  figure  value``."""
    shown = f"{value:.4g}" if math.isfinite(value) else str(value)
    return f"{family:<9} {name:<48} {shown:>12}"


def machine() -> dict[str, Any]:
    """The CPU's model and count and the machine's load now (1, 5 and 15 minutes)."""
    model = platform.processor() or platform.machine()
    try:
        with open("/proc/cpuinfo", encoding="utf-8") as f:
            for line in f:
                if line.startswith("model name"):
                    model = line.split(":", 1)[1].strip()
                    break
    except OSError:
        pass
    return {"cpu_model": model, "cpu_count": os.cpu_count(), "load": list(os.getloadavg()),
            "python": platform.python_version()}


def commit() -> str:
    """The checked-out commit (with ``+changes`` when the work tree differs from it), or ''."""
    here = Path(__file__).resolve().parent
    try:
        head = subprocess.run(["git", "rev-parse", "HEAD"], cwd=here, capture_output=True, text=True,
                              timeout=10).stdout.strip()
        dirty = subprocess.run(["git", "status", "--porcelain", "--untracked-files=no"], cwd=here,
                               capture_output=True, text=True, timeout=10).stdout.strip()
    except (OSError, subprocess.SubprocessError):
        return ""
    return head + ("+changes" if head and dirty else "")


def record(figures: dict[str, dict[str, float]], started: float, seconds: float,
           before: dict[str, Any], log: Path) -> dict[str, Any]:
    """The saved form of a run: figures by family, the commit, the machine (its load before and after)."""
    after = machine()
    return {"format": "omniformation-bench/1", "commit": commit(), "started_unix": started, "seconds": seconds,
            "machine": {**{k: v for k, v in before.items() if k != "load"}, "load_before": before["load"],
                        "load_after": after["load"]},
            "log": str(log), "figures": {fam: {k: _jsonable(v) for k, v in figs.items()} for fam, figs in figures.items()}}


def _jsonable(value: float) -> float | str:
    return value if math.isfinite(value) else str(value)  # JSON has no inf or nan


def read_run(path: Path) -> dict[str, float]:
    """A saved run's figures as ``family.figure -> value``; ValueError in one line for a file that is not one."""
    try:
        data = json.loads(path.read_text(encoding="utf-8"))
    except OSError as exc:
        raise ValueError(f"{path}: cannot read ({exc.strerror or exc})") from None
    except (ValueError, UnicodeDecodeError, RecursionError):
        raise ValueError(f"{path}: not JSON (a file `omniformation bench` saved)") from None
    figures = data.get("figures") if isinstance(data, dict) else None
    if not isinstance(figures, dict) or not all(isinstance(v, dict) for v in figures.values()):
        raise ValueError(f"{path}: no figures by family (a file `omniformation bench` saved)")
    out: dict[str, float] = {}
    for fam, figs in figures.items():
        for name, value in figs.items():
            try:
                out[f"{fam}.{name}"] = float(value)
            except (TypeError, ValueError):
                raise ValueError(f"{path}: figure {fam}.{name} = {value!r} is not a number") from None
    return out


def compare(a: dict[str, float], b: dict[str, float]) -> list[str]:
    """One line per figure: its value in ``a`` and in ``b`` and the ratio b / a (figures in only one marked)."""
    lines = []
    for key in sorted(a.keys() | b.keys()):
        if key not in b or key not in a:
            lines.append(f"{key:<58} {'only in ' + ('A' if key in a else 'B'):>30}")
            continue
        x, y = a[key], b[key]
        ratio = f"x{y / x:.3f}" if x and math.isfinite(x) and math.isfinite(y) else "-"
        lines.append(f"{key:<58} {x:>12.4g} {y:>12.4g} {ratio:>9}")
    return lines
