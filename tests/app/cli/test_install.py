"""A non-editable install runs from any folder: `pip install .` into a fresh venv, then the
console script from an unrelated working folder finds its config and scenarios (package
data) and records under that folder, never the checkout.

The fresh venv gets the project's dependencies from the test venv (a path entry, so nothing
is downloaded but the build backend); the project itself is built and installed by pip from
a copy of the sources."""

from __future__ import annotations

import shutil
import subprocess
import sys
import sysconfig
from pathlib import Path

import pytest

from tests.helpers import ROOT, serve_then_signal


@pytest.fixture(scope="module")
def installed(tmp_path_factory: pytest.TempPathFactory) -> Path:
    base = tmp_path_factory.mktemp("install")
    src = base / "src"
    for name in ("app", "core", "static_config"):
        shutil.copytree(ROOT / name, src / name, ignore=shutil.ignore_patterns("__pycache__", "*.nbi", "*.nbc"))
    for name in ("pyproject.toml", "README.md"):
        shutil.copy2(ROOT / name, src / name)
    venv = base / "venv"
    subprocess.run([sys.executable, "-m", "venv", str(venv)], check=True, timeout=120)
    purelib = Path(subprocess.run([str(venv / "bin" / "python"), "-c",
                                   "import sysconfig; print(sysconfig.get_paths()['purelib'])"],
                                  capture_output=True, text=True, check=True).stdout.strip())
    (purelib / "project_deps.pth").write_text(sysconfig.get_paths()["purelib"] + "\n")
    out = subprocess.run([str(venv / "bin" / "python"), "-m", "pip", "install", "--quiet", "--no-deps", str(src)],
                         capture_output=True, text=True, timeout=600)
    assert out.returncode == 0, out.stderr[-3000:]
    shutil.rmtree(src)  # nothing may be read from the sources once installed
    return venv


def test_the_installed_package_is_not_the_checkout(installed: Path, tmp_path: Path) -> None:
    out = subprocess.run([str(installed / "bin" / "python"), "-c",
                          "import app, core, static_config; print(app.__file__); print(static_config.__file__)"],
                         capture_output=True, text=True, check=True, cwd=tmp_path)
    for line in out.stdout.split():
        assert str(installed) in line and str(ROOT) not in line
    shipped = Path(out.stdout.split()[1]).parent
    for sub in ("scenarios/vee3.toml", "fleets/three_teams.toml", "camera/synthetic.toml"):
        assert (shipped / sub).is_file(), sub  # the shipped config travels with the install
    head = subprocess.run([str(installed / "bin" / "python"), "-c",
                           "from app.dashboard.gate import page_head; print(page_head('replay').decode())"],
                          capture_output=True, text=True, cwd=tmp_path)
    assert head.returncode == 0, head.stderr  # the page's added files travel with it too
    assert "omni-stopbar" in head.stdout and 'kind: "replay"' in head.stdout


def test_simulate_runs_from_an_unrelated_folder(installed: Path, tmp_path: Path) -> None:
    out = subprocess.run([str(installed / "bin" / "omniformation"), "simulate", "paper_simulation", "--duration", "3",
                          "--out", "run.csv"], capture_output=True, text=True, cwd=tmp_path, timeout=300)
    assert out.returncode == 0, out.stderr
    assert "paper_simulation: 3 s at 100 Hz, 2 followers" in out.stdout
    assert (tmp_path / "run.csv").stat().st_size > 0


def test_run_serves_and_records_under_the_working_folder(installed: Path, tmp_path: Path) -> None:
    run = serve_then_signal("--port", "0", "--feedback", "truth", command=[str(installed / "bin" / "omniformation"), "run"],
                            cwd=tmp_path, start_timeout_s=120)
    assert "dashboard at http://127.0.0.1:" in run.startup, run.startup + run.stderr
    assert run.returncode == 0, run.stderr
    recorded = list((tmp_path / "recordings").glob("*.mcap"))
    assert len(recorded) == 1 and recorded[0].stat().st_size > 0, run.startup + run.stdout
    assert "recording to recordings/" in run.startup


def test_run_no_record_leaves_the_folder_alone(installed: Path, tmp_path: Path) -> None:
    run = serve_then_signal("--no-record", "--port", "0", "--feedback", "truth", hold_s=0.0,
                            command=[str(installed / "bin" / "omniformation"), "run"], cwd=tmp_path, start_timeout_s=120)
    assert "dashboard at" in run.startup and run.returncode == 0, run.stderr
    assert list(tmp_path.iterdir()) == []
