"""How `omniformation bench` runs its families (app.cli.bench.family): found from their modules,
chosen by default, --full or --family; one line per figure on the console, everything else in
the log it names; every run saved as JSON and two compared figure by figure. The families'
figures themselves are not asserted (the machines are shared)."""

from __future__ import annotations

import io
import json
import logging
import subprocess
import sys
from pathlib import Path

from app.cli.bench import run_bench
from app.cli.bench.family import Family, choose, families
from tests.helpers import ROOT, main_cli


def test_every_family_module_declares_its_family_and_the_names_are_unique():
    found = families()
    names = [f.name for f in found]
    assert len(names) == len(set(names))
    modules = sorted(p.stem for p in (ROOT / "app" / "cli" / "bench").glob("*.py")
                     if "def run_family(" in p.read_text(encoding="utf-8"))
    assert sorted(names) == modules  # a module that measures is a family: none forgotten
    assert [f.name for f in choose(found, False, None)] == [f.name for f in found if f.default]
    assert choose(found, True, None) == found
    assert [f.name for f in choose(found, False, ["ros2", "speed", "ros2"])] == ["ros2", "speed"]


def test_an_unknown_family_is_refused_in_one_line_naming_the_families():
    out = main_cli("bench", "--family", "nosuch")
    assert out.returncode == 2
    lines = out.stderr.strip().splitlines()
    assert len(lines) == 1 and "--family nosuch: no such family; the families are " in lines[0]
    assert all(f.name in lines[0] for f in families())


def _tiny(print_fn):
    print_fn("a detail line")
    print("a service printing")
    logging.getLogger("app.services.tiny").warning("refused something")
    subprocess.run([sys.executable, "-c", "import sys; print('a child process'); print('its error', file=sys.stderr)"],
                   check=True)
    return {"first_ms": 1.5, "second_hz": 30.0}


def test_a_run_prints_one_line_per_figure_logs_the_rest_and_is_saved(tmp_path: Path) -> None:
    console = io.StringIO()
    figures = run_bench([Family("tiny", _tiny, "a family for this test")], tmp_path, console=console)
    assert figures == {"tiny": {"first_ms": 1.5, "second_hz": 30.0}}
    lines = console.getvalue().splitlines()
    assert len(lines) == 4  # where the log is, the two figures, where the run is saved
    assert lines[1].split() == ["tiny", "first_ms", "1.5"] and lines[2].split() == ["tiny", "second_hz", "30"]
    log = next(tmp_path.glob("bench-*.log"))
    assert str(log) in lines[0]
    text = log.read_text(encoding="utf-8")
    for said in ("a detail line", "a service printing", "refused something", "a child process", "its error"):
        assert said in text and said not in console.getvalue()
    saved = next(tmp_path.glob("bench-*.json"))
    assert str(saved) in lines[3]
    run = json.loads(saved.read_text(encoding="utf-8"))
    assert run["figures"] == {"tiny": {"first_ms": 1.5, "second_hz": 30.0}}
    assert len(run["commit"]) >= 40  # this work tree's commit
    assert run["machine"]["cpu_count"] >= 1 and run["machine"]["cpu_model"]
    assert len(run["machine"]["load_before"]) == 3 and len(run["machine"]["load_after"]) == 3


def test_two_runs_are_compared_figure_by_figure(tmp_path: Path) -> None:
    a, b = tmp_path / "a.json", tmp_path / "b.json"
    a.write_text(json.dumps({"figures": {"speed": {"controller_3_us": 10.0, "gone_ms": 1.0}}}), encoding="utf-8")
    b.write_text(json.dumps({"figures": {"speed": {"controller_3_us": 20.0, "new_ms": 2.0}}}), encoding="utf-8")
    out = main_cli("bench", "--compare", str(a), str(b))
    assert out.returncode == 0, out.stderr
    rows = {line.split()[0]: line.split()[1:] for line in out.stdout.splitlines()[1:]}
    assert rows["speed.controller_3_us"] == ["10", "20", "x2.000"]
    assert rows["speed.gone_ms"] == ["only", "in", "A"] and rows["speed.new_ms"] == ["only", "in", "B"]
    b.write_text("not json", encoding="utf-8")
    out = main_cli("bench", "--compare", str(a), str(b))
    assert out.returncode == 2 and out.stderr.strip().splitlines() == [
        f"omniformation: error: {b}: not JSON (a file `omniformation bench` saved)"]
