"""`omniformation study` as a user runs it: a real LocalCluster (--workers), a real `dask scheduler`
and two `dask worker` processes started here (--cluster), real Parquet files read back with
pyarrow.dataset. What must hold: every run appears exactly once whatever happens to a worker or to
the command (SIGKILL, Ctrl-C, resume), and a run's numbers depend only on the study file and the
run: the same on one worker, two, a cluster, in this process one run after another, and from
`simulate` of that scenario with those values and that seed."""

from __future__ import annotations

import json
import math
import os
import random
import re
import signal
import subprocess
import sys
from collections.abc import Iterator
from pathlib import Path

import pyarrow.dataset as ds
import pyarrow.parquet as pq
import pytest

from app.study.batch import run_runs
from app.study.engine import pending_runs
from app.study.session import load_study
from core.study.point import METRICS
from tests.helpers import ROOT, run_cli, wait_for

DASK = Path(sys.executable).parent / "dask"

# stepped runs (latency): about a tenth of a second each, so a study of 60 lasts long enough to be
# stopped in the middle
SLOW = """
[study]
scenario = "experiment1"
duration_s = 12.0
seed = 3
replicates = 3

[grid]
"gains.k_f1" = [0.1, 0.3]
"latency.camera_ms" = {lo = 40.0, hi = 120.0, n = 10}
"""

FAST = """
[study]
scenario = "paper_simulation"
duration_s = 6.0
seed = 9
replicates = 2

[grid]
"gains.k_w2" = [1.0, 3.0]
"measurement.position_noise_m" = [0.0, 0.01]

[sample]
n = 3
"start.offset_m" = {lo = 0.1, hi = 0.8}
"""

COMPARED = [m for m in METRICS] + ["point", "replicate", "seed"]


def rows_by_run(out: Path) -> dict[tuple[str, int], dict]:
    table = ds.dataset(str(out / "results"), format="parquet").to_table()
    rows = table.to_pylist()
    keys = [(r["point"], r["replicate"]) for r in rows]
    assert len(keys) == len(set(keys)), "a run appears twice in results/"
    return dict(zip(keys, rows))


def same(a: dict, b: dict) -> bool:
    for k in COMPARED:
        x, y = a[k], b[k]
        if isinstance(x, float) and math.isnan(x):
            if not (isinstance(y, float) and math.isnan(y)):
                return False
        elif x != y:
            return False
    return True


def spawn_study(*args: str) -> subprocess.Popen[str]:
    return subprocess.Popen([sys.executable, "-m", "app.cli", "study", *args], cwd=ROOT, stdout=subprocess.PIPE,
                            stderr=subprocess.PIPE, text=True)


def parts(out: Path) -> list[Path]:
    return sorted((out / "results").glob("part-*.parquet")) if (out / "results").exists() else []


@pytest.fixture(scope="module")
def cluster(tmp_path_factory: pytest.TempPathFactory) -> Iterator[dict]:
    """`dask scheduler` and two `dask worker` processes (no nanny: a killed worker stays dead)."""
    tmp = tmp_path_factory.mktemp("dask")
    sched_file = tmp / "scheduler.json"
    env = {**os.environ, "DASK_DISTRIBUTED__WORKER__DAEMON": "False"}
    sched = subprocess.Popen([str(DASK), "scheduler", "--host", "127.0.0.1", "--port", "0", "--dashboard-address",
                              "127.0.0.1:0", "--scheduler-file", str(sched_file)], cwd=ROOT, env=env,
                             stdout=subprocess.DEVNULL, stderr=subprocess.DEVNULL)
    procs = [sched]
    try:
        wait_for(lambda: sched_file.exists() and sched_file.stat().st_size > 0, 60, "the scheduler's file")
        address = json.loads(sched_file.read_text())["address"]
        workers = [subprocess.Popen([str(DASK), "worker", address, "--nthreads", "1", "--no-nanny",
                                     "--no-dashboard", "--host", "127.0.0.1"], cwd=ROOT, env=env,
                                    stdout=subprocess.DEVNULL, stderr=subprocess.DEVNULL) for _ in range(2)]
        procs += workers
        from distributed import Client

        with Client(address, timeout="30s") as c:
            c.wait_for_workers(2, timeout=120)
        yield {"address": address, "workers": workers, "tmp": tmp}
    finally:
        for p in reversed(procs):
            if p.poll() is None:
                p.terminate()
        for p in procs:
            try:
                p.wait(timeout=20)
            except subprocess.TimeoutExpired:
                p.kill()


@pytest.fixture(scope="module")
def slow_file(tmp_path_factory: pytest.TempPathFactory) -> Path:
    path = tmp_path_factory.mktemp("slow") / "slow.toml"
    path.write_text(SLOW)
    return path


@pytest.fixture(scope="module")
def fast_file(tmp_path_factory: pytest.TempPathFactory) -> Path:
    path = tmp_path_factory.mktemp("fast") / "fast.toml"
    path.write_text(FAST)
    return path


@pytest.fixture(scope="module")
def slow_on_cluster(cluster: dict, slow_file: Path) -> dict:
    """The slow study on the cluster, one worker SIGKILLed once the first part is written."""
    out = cluster["tmp"] / "slow-cluster"
    proc = spawn_study(str(slow_file), "--out", str(out), "--cluster", cluster["address"])
    try:
        wait_for(lambda: parts(out) or proc.poll() is not None, 180, "the first part")
        killed_with = len(parts(out))
        cluster["workers"][0].send_signal(signal.SIGKILL)
        stdout, stderr = proc.communicate(timeout=300)
    finally:
        if proc.poll() is None:
            proc.kill()
    return {"out": out, "rc": proc.returncode, "stdout": stdout, "stderr": stderr, "killed_with": killed_with}


def test_a_worker_killed_mid_study_loses_and_repeats_no_run(slow_on_cluster: dict, slow_file: Path) -> None:
    r = slow_on_cluster
    assert r["rc"] == 0, r["stderr"][-2000:]
    spec = load_study(slow_file)
    assert r["killed_with"] < len(parts(r["out"])), "the worker was killed after the study's last part"
    got = rows_by_run(r["out"])
    assert len(got) == spec.runs == 60
    assert {w for w in (row["worker"] for row in got.values())} != set()
    # the same numbers as one run after another in this process (a sample of the runs)
    items = random.Random(1).sample(list(pending_runs(spec, set())), 6)
    serial, failures = run_runs(spec, items, "local")
    assert not failures
    for row in serial:
        assert same(row, got[(row["point"], row["replicate"])]), row["point"]
    summary = (r["out"] / "summary.md").read_text()
    assert "60 of 60 runs in results/ (20 points), 0 failed" in summary
    assert (r["out"] / "plots" / "heatmap-gains_k_f1-latency_camera_ms.png").stat().st_size > 10_000
    assert "Dask dashboard: http://127.0.0.1:" in r["stdout"]


def test_ctrl_c_keeps_what_is_written_and_the_same_command_resumes(slow_on_cluster: dict, slow_file: Path,
                                                                   tmp_path: Path) -> None:
    out = tmp_path / "slow-local"
    proc = spawn_study(str(slow_file), "--out", str(out), "--workers", "2")
    try:
        wait_for(lambda: parts(out) or proc.poll() is not None, 180, "the first part")
        proc.send_signal(signal.SIGINT)
        stdout, stderr = proc.communicate(timeout=120)
    finally:
        if proc.poll() is None:
            proc.kill()
    assert proc.returncode == 130, stderr[-2000:]
    assert "interrupted" in stdout and "the same command resumes" in stdout
    first = rows_by_run(out)
    assert 0 < len(first) < 60
    again = run_cli("study", str(slow_file), "--out", str(out), "--workers", "2")
    assert again.returncode == 0, again.stderr[-2000:]
    made = int(re.search(r"study: (\d+) runs made", again.stdout).group(1))
    assert made == 60 - len(first)
    got = rows_by_run(out)
    assert len(got) == 60
    # identical to the cluster's, worker killed and all (and so across worker counts)
    cl = rows_by_run(slow_on_cluster["out"])
    assert all(same(got[k], cl[k]) for k in cl)
    # finished: the same command runs nothing
    done = run_cli("study", str(slow_file), "--out", str(out), "--workers", "2")
    assert done.returncode == 0 and "0 to run" in done.stdout
    # a study file that differs from the manifest's: one line naming the field
    changed = tmp_path / "slow.toml"
    changed.write_text(SLOW.replace("[0.1, 0.3]", "[0.1, 0.4]"))
    refused = run_cli("study", str(changed), "--out", str(out))
    assert refused.returncode == 2
    assert refused.stderr.count("\n") == 1 and "grid.gains.k_f1 = [0.1, 0.4] (was [0.1, 0.3])" in refused.stderr
    assert len(rows_by_run(out)) == 60  # nothing lost


def test_one_worker_two_and_a_cluster_give_the_same_runs(cluster: dict, fast_file: Path, tmp_path: Path) -> None:
    one = run_cli("study", str(fast_file), "--out", str(tmp_path / "one"), "--workers", "1")
    assert one.returncode == 0, one.stderr[-2000:]
    on_cluster = run_cli("study", str(fast_file), "--out", str(tmp_path / "cl"), "--cluster", cluster["address"])
    assert on_cluster.returncode == 0, on_cluster.stderr[-2000:]
    a, b = rows_by_run(tmp_path / "one"), rows_by_run(tmp_path / "cl")
    spec = load_study(fast_file)
    assert len(a) == len(b) == spec.runs == 24
    assert all(same(a[k], b[k]) for k in a)
    serial, _ = run_runs(spec, list(pending_runs(spec, set())), "local")
    assert all(same(r, a[(r["point"], r["replicate"])]) for r in serial)
    assert (tmp_path / "one" / "plots" / "region_of_attraction.png").exists()
    manifest = json.loads((tmp_path / "one" / "manifest.json").read_text())
    assert manifest["study_text"] == FAST and manifest["runs"] == 24 and manifest["version"]["dask"]

    # a run is `simulate` of that scenario with those values and that seed
    row = next(r for r in a.values() if r["measurement.position_noise_m"] == 0.01)
    from core.study.spec import scenario_for

    sc = scenario_for(spec, spec.scenarios[0], {k: row[k] for k in spec.axis_names}, row["seed"])
    head = (ROOT / "static_config/scenarios/paper_simulation.toml").read_text().split("[[followers]]")[0]
    text = head + "".join(f"\n[[followers]]\nposition = [{float(x)!r}, {float(y)!r}]\nheading_deg = 90.0\n" for x, y in sc.initial_p)
    text += f"\n[gains]\nk_w2 = {row['gains.k_w2']!r}\n\n[measurement]\nposition_noise_m = 0.01\n"
    scen = tmp_path / "point.toml"
    scen.write_text(text)
    assert row["start.offset_m"] > 0
    sim = run_cli("simulate", str(scen), "--seed", str(row["seed"]), "--duration", "6", "--out", str(tmp_path / "p.csv"))
    assert sim.returncode == 0, sim.stderr
    import numpy as np

    csv = np.genfromtxt(tmp_path / "p.csv", delimiter=",", names=True)
    t = csv["t"]
    n = sc.n
    err = np.stack([np.hypot(csv[f"f{i}_x"] - csv[f"f{i}_xd"], csv[f"f{i}_y"] - csv[f"f{i}_yd"]) for i in range(1, n + 1)],
                   axis=1)
    team = np.sqrt(np.mean(err ** 2, axis=1))
    tail = team[t >= t[-1] - 2.0]
    assert row["final_rms_m"] == pytest.approx(float(np.sqrt(np.mean(tail ** 2))), rel=1e-4, abs=2e-6)
    assert row["max_error_m"] == pytest.approx(float(err.max()), rel=1e-4, abs=2e-6)
    assert row["converged"] == bool(np.all(tail <= 0.02))

    # `report DIR` draws the summary and the plots again from the files alone
    for p in (tmp_path / "one" / "plots").iterdir():
        p.unlink()
    (tmp_path / "one" / "summary.md").unlink()
    rep = run_cli("report", str(tmp_path / "one"))
    assert rep.returncode == 0, rep.stderr
    assert (tmp_path / "one" / "summary.md").read_text().count("\n|") == 2 + 12
    assert (tmp_path / "one" / "plots" / "heatmap-gains_k_w2-measurement_position_noise_m.png").exists()


def test_a_run_that_raises_is_a_failure_and_the_study_goes_on(cluster: dict, tmp_path: Path) -> None:
    # a box ahead of the second slot: the start 1 m ahead of it is inside the box, a start that the
    # scenario reader refuses (each axis alone is fine at its extremes: the combination is not)
    scen = (ROOT / "static_config/scenarios/paper_simulation.toml").read_text()
    (tmp_path / "boxed.toml").write_text(scen + "\n[[obstacles]]\ncenter = [0.5, 0.7]\nsize = [0.3, 0.3]\n")
    (tmp_path / "s.toml").write_text('[study]\nscenario = "boxed.toml"\nduration_s = 1.0\nreplicates = 2\n'
                                     '[grid]\n"start.offset_m" = [0.0, 1.0]\n"start.bearing_deg" = [-90.0, 90.0]\n')
    r = run_cli("study", str(tmp_path / "s.toml"), "--out", str(tmp_path / "o"), "--cluster", cluster["address"])
    assert r.returncode == 0, r.stderr[-2000:]
    fails = pq.read_table(tmp_path / "o" / "failures.parquet").to_pylist()
    assert len(fails) == 2 and {f["start.offset_m"] for f in fails} == {1.0} and {f["start.bearing_deg"] for f in fails} == {90.0}
    assert all("clear of the robots" in f["error"] for f in fails)
    assert len(rows_by_run(tmp_path / "o")) == 6
    assert "6 of 8 runs in results/ (3 points), 2 failed" in (tmp_path / "o" / "summary.md").read_text()
    assert "2 failed" in r.stdout


def test_optimize_asks_tells_and_resumes(cluster: dict, tmp_path: Path) -> None:
    (tmp_path / "o.toml").write_text('[study]\nscenario = "paper_simulation"\nduration_s = 8.0\nseed = 4\nreplicates = 2\n'
                                     '[optimize]\nobjective = "settling_s + 10 * overshoot_m"\ntrials = 6\n'
                                     '"gains.k_f1" = {lo = 0.02, hi = 0.8, log = true}\n')
    args = ("study", str(tmp_path / "o.toml"), "--out", str(tmp_path / "o"), "--cluster", cluster["address"])
    r = run_cli(*args)
    assert r.returncode == 0, r.stderr[-2000:]
    assert re.search(r"study: best gains.k_f1 = [0-9.]+ \(trial \d, objective [0-9.]+\)", r.stdout), r.stdout
    got = rows_by_run(tmp_path / "o")
    assert len(got) == 12 and len({k for k, _ in got}) == 6
    assert (tmp_path / "o" / "optuna.journal").stat().st_size > 0
    assert (tmp_path / "o" / "plots" / "optimize_history.png").exists()
    assert "best point" in (tmp_path / "o" / "summary.md").read_text()
    again = run_cli(*args)
    assert again.returncode == 0 and "study: 0 runs made" in again.stdout, again.stdout
    assert len(rows_by_run(tmp_path / "o")) == 12


@pytest.mark.parametrize("body, says", [
    ('[study]\nscenario = "experiment1"\n[grid]\n"gains.k_fx" = [0.1]\n', "gains.k_fx is not a known key"),
    ('[study]\nscenario = "experiment1"\n[grid]\n"gains.k_f1" = [0.1, 1.5]\n', "gains.k_f1 = 1.5: must be a number in (0, 1] m/s"),
    ('[study]\nscenario = "experiment1"\nreplicates = "four"\n', "study.replicates = 'four': must be a whole number"),
    ('[study]\nscenario = "experiment1"\n[grid]\n', "[grid] is empty"),
])
def test_bad_study_files_are_one_line_and_exit_2(tmp_path: Path, body: str, says: str) -> None:
    (tmp_path / "bad.toml").write_text(body)
    r = run_cli("study", str(tmp_path / "bad.toml"), "--out", str(tmp_path / "o"), "--workers", "1")
    assert r.returncode == 2 and r.stderr.count("\n") == 1 and says in r.stderr, r.stderr
    assert not (tmp_path / "o").exists()
