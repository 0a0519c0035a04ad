"""The command line as a user runs it: a real subprocess, real files."""

import csv

import numpy as np
import pytest

from tests.helpers import SCENARIOS
from tests.helpers import main_cli, run_cli

SCENARIO = SCENARIOS / "experiment2.toml"


def test_help_lists_the_subcommands():
    out = run_cli("--help")
    assert out.returncode == 0
    for cmd in ("simulate", "bench"):
        assert cmd in out.stdout


def test_simulate_writes_csv_and_plot(tmp_path):
    csv_path, png = tmp_path / "run.csv", tmp_path / "run.png"
    out = run_cli("simulate", "paper_simulation", "--out", str(csv_path), "--plot", str(png),
                  "--duration", "20", "--rate", "50")
    assert out.returncode == 0, out.stderr
    rows = list(csv.reader(csv_path.open()))
    header = rows[0]
    assert header[:6] == ["t", "leader_x", "leader_y", "leader_theta", "leader_v", "leader_w"]
    assert header[6:13] == ["f1_x", "f1_y", "f1_a", "f1_xd", "f1_yd", "f1_v", "f1_w"]
    assert header[13:] == ["f2_x", "f2_y", "f2_a", "f2_xd", "f2_yd", "f2_v", "f2_w"]
    assert len(rows) == 1 + 20 * 50 + 1
    first = dict(zip(header, map(float, rows[1])))
    assert first["f1_x"] == pytest.approx(-0.70) and first["f1_a"] == pytest.approx(2.35619, abs=1e-4)
    assert first["f1_xd"] == pytest.approx(-0.50) and first["leader_v"] == pytest.approx(0.06)
    assert png.read_bytes()[:8] == b"\x89PNG\r\n\x1a\n" and png.stat().st_size > 20_000


def test_simulate_takes_a_path_and_a_seed(tmp_path):
    out = run_cli("simulate", str(SCENARIO), "--duration", "5", "--seed", "7")
    assert out.returncode == 0, out.stderr
    assert "experiment2" in out.stdout


@pytest.mark.parametrize(
    ("args", "message"),
    [
        (("simulate", "no_such_scenario"), "scenario 'no_such_scenario' not found"),
        (("simulate", "paper_simulation", "--rate", "abc"), "argument --rate: 'abc' is not a number"),
        (("simulate", "paper_simulation", "--duration", "-1"), "argument --duration: -1 is outside"),
        (("simulate", "paper_simulation", "--seed", "-4"), "argument --seed: -4 is outside 0..4294967295"),
        (("run", "--followers", "9"), "argument --followers: 9 is outside 1..8"),
        (("run", "--port", "http"), "argument --port: 'http' is not a whole number"),
        (("frobnicate",), "invalid choice: 'frobnicate'"),
    ],
)
def test_bad_arguments_exit_2_with_one_line(args, message):
    out = main_cli(*args)
    assert out.returncode == 2
    assert message in out.stderr
    assert len(out.stderr.strip().splitlines()) == 1
    assert "Traceback" not in out.stderr


def test_bad_scenario_file_exits_2_naming_file_key_value(tmp_path):
    bad = tmp_path / "bad.toml"
    bad.write_text(SCENARIO.read_text().replace("turn_deg_s = 1.5", "turn_deg_s = 400"))
    out = main_cli("simulate", str(bad))
    assert out.returncode == 2
    assert "bad.toml: leader.turn_deg_s = 400: must be a number in [-30, 30] deg/s" in out.stderr
    assert len(out.stderr.strip().splitlines()) == 1


def test_missing_output_folder_is_refused_before_running(tmp_path):
    out = main_cli("simulate", "paper_simulation", "--out", str(tmp_path / "nope" / "x.csv"))
    assert out.returncode == 2
    assert "does not exist" in out.stderr


def test_simulate_with_vision_adds_the_estimates(tmp_path):
    csv_path = tmp_path / "vision.csv"
    out = run_cli("simulate", "experiment1", "--vision", "--duration", "4", "--out", str(csv_path))
    assert out.returncode == 0, out.stderr
    assert "start-up manoeuvres took" in out.stdout and "heading RMS" in out.stdout
    rows = list(csv.reader(csv_path.open()))
    header = rows[0]
    for i in (1, 2):
        assert [f"f{i}_x_est", f"f{i}_y_est", f"f{i}_a_est", f"f{i}_tracked"] == header[
            header.index(f"f{i}_w") + 1: header.index(f"f{i}_w") + 5]
    table = np.array(rows[1:], dtype=float)
    t = table[:, 0]
    assert t[0] < -3.0 and abs(t[-1] - 4.0) < 1e-6  # start-up takes simulated time, then 4 s
    col = {name: k for k, name in enumerate(header)}
    after = t >= 0
    assert np.all(table[after, col["f1_tracked"]] == 1.0)
    assert np.all(np.abs(table[after, col["f1_x_est"]] - table[after, col["f1_x"]]) < 0.03)


def test_the_soaks_gc_monitor_counts_each_collection_once_and_lets_go():
    import gc

    from app.cli.bench import GcPauses

    pauses = GcPauses()
    gc.disable()  # no automatic collections (a service's collector thread, app.memory, may still run one)
    try:
        before = list(pauses.counts)
        gc.collect(2)
        gc.collect(0)
        assert pauses.counts[2] >= before[2] + 1 and pauses.counts[0] >= before[0] + 1
        worst = pauses.take()
        assert worst > 0.0 and pauses.worst[0] >= worst
        assert pauses.take() == 0.0  # the window starts again after each take()
    finally:
        pauses.close()
        gc.enable()
    assert pauses._on not in gc.callbacks
    counted = list(pauses.counts)
    gc.collect(2)
    assert pauses.counts == counted


def test_the_long_recording_benchs_replay_probe_opens_seeks_and_reports_its_own_memory():
    """bench --long-recording measures replay in a fresh process with this probe: one JSON line."""
    import json
    import subprocess
    import sys

    from tests.helpers import ROOT, SAMPLES

    out = subprocess.run(
        [sys.executable, "-c", "import sys; from app.cli.bench import replay_probe; replay_probe(sys.argv[1], 3)",
         str(SAMPLES / "experiment2-vision.mcap")], capture_output=True, text=True, cwd=ROOT, timeout=120)
    assert out.returncode == 0, out.stderr
    probe = json.loads(out.stdout.strip().splitlines()[-1])
    assert probe["frame"] is True and probe["seeks"] == 3
    assert 0 < probe["first_s"] and 0 < probe["seek_median_s"] <= probe["seek_max_s"] and probe["peak_mb"] > 50
