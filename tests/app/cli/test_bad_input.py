"""Every bad input a user can give the command line gets one line naming the input and what
is allowed, exit code 2, no traceback, and changes nothing on disk (table-driven)."""

from __future__ import annotations

import json
from pathlib import Path

import pytest
from mcap.writer import CompressionType, Writer

from app.recording.schema import TICK_TOPIC
from tests.helpers import ROOT, main_cli

SAMPLE = ROOT / "recordings" / "samples" / "experiment2-vision.mcap"


def _mcap_with_ticks(path: Path, *ticks: dict) -> Path:
    with open(path, "wb") as f:
        w = Writer(f, compression=CompressionType.ZSTD)
        w.start()
        sid = w.register_schema("omniformation.Tick", "jsonschema", b"{}")
        cid = w.register_channel(TICK_TOPIC, "json", sid)
        for k, tick in enumerate(ticks):
            w.add_message(cid, log_time=k, publish_time=k, data=json.dumps(tick, separators=(",", ":")).encode())
        w.finish()
    return path


@pytest.fixture(scope="module")
def files(tmp_path_factory: pytest.TempPathFactory) -> dict[str, Path]:
    d = tmp_path_factory.mktemp("bad")
    (d / "folder").mkdir()
    (d / "binary.toml").write_bytes(bytes(range(256)) * 4)
    (d / "random.mp4").write_bytes(bytes((i * 7919) % 256 for i in range(20000)))
    (d / "empty.toml").write_text("")
    (d / "existing.mcap").write_bytes(b"keep")
    text = (ROOT / "static_config/scenarios/experiment1.toml").read_text()
    import re

    (d / "identical.toml").write_text(re.sub(r"slots = \[.*?\]\]", "slots = [[0.5, 0.5], [0.5, 0.5], [0.5, 0.5]]",
                                             text, flags=re.S))
    many = "\n".join(f"[[followers]]\nposition = [{0.3 * (i % 5) - 0.6:.2f}, {-0.5 - 0.3 * (i // 5):.2f}]\nheading_deg = 90\n"
                     for i in range(9))
    slots = ", ".join(f"[{0.3 * (i % 5) - 0.6:.2f}, {0.5 + 0.3 * (i // 5):.2f}]" for i in range(9))
    (d / "nine.toml").write_text(
        'name = "nine"\nduration_s = 5\nrate_hz = 30\n[leader]\nprofile = "constant"\nspeed_mps = 0.05\n'
        f"{many}\n[formation]\nslots = [{slots}]\n")
    (d / "deep.toml").write_text("name = 'deep'\nx = " + "[" * 5000 + "]" * 5000 + "\n")
    _mcap_with_ticks(d / "empty_tick.mcap", {})
    _mcap_with_ticks(d / "wrong_types.mcap", {"tick": 0, "t": 0.0, "p_est": "abc", "a_est": 5})
    return {p.name: p for p in d.iterdir()} | {"dir": d}


CASES = [
    # (arguments, with {name} for the files above; a fragment of the one line expected)
    ("simulate experiment1 --duration 1 --out {folder}", "is a folder; give a file name for the CSV log"),
    ("simulate experiment1 --duration 1 --out /proc/x.csv", "/proc/x.csv"),
    ("simulate experiment1 --duration 1 --record {folder}", "is a folder; give a file name for the recording"),
    ("simulate experiment1 --duration 1 --record {existing.mcap}", "exists; a recording is never written over another"),
    ("simulate experiment1 --duration 1 --plot {dir}/run.xyz", "the figure must be a .png or .pdf or .svg or .jpg file"),
    ("render experiment1 --out {dir}/f.xyz", "the image must be a .png"),
    ("run --record {folder} --port 0", "is a folder; give a file name for the recording"),
    ("run --record {existing.mcap} --port 0", "exists; a recording is never written over another"),
    ("run --scenario {nine.toml} --port 0 --no-record", "9 followers; the live service drives 1..8"),
    ("report {empty_tick.mcap} --out {dir}/rep1", "holds no complete tick"),
    ("report {wrong_types.mcap} --out {dir}/rep2", "tick 0 is not what omniformation records"),
    ("replay {wrong_types.mcap} --port 0", "tick 0 is not what omniformation records"),
    ("report " + str(SAMPLE) + " --out /proc/rep", "/proc/rep: cannot write there"),
    ("report " + str(SAMPLE) + " --out {dir}/rep3 --format <svg>", "--format: invalid choice: '<svg>'"),
    ("rerun " + str(SAMPLE) + " --out {dir}/r.mcap --pipeline-config {binary.toml}", "binary.toml: cannot read"),
    ("rerun " + str(SAMPLE) + " --out {dir}/r.mcap --gains ,,,", "give NAME=NUMBER pairs"),
    ("calibrate --synthetic static_config/camera/synthetic.toml --out {dir}/c.toml --center nan nan",
     "nan is outside [-100000, 100000] px"),
    ("calibrate --synthetic static_config/camera/synthetic.toml --out {folder}", "is a folder; give a file name for the camera file"),
    ("calibrate --synthetic static_config/camera/synthetic.toml --out {dir}/c.toml --bearing-offset nan",
     "nan is outside [-360, 360] deg"),
    ("simulate {identical.toml} --duration 1", "points at least 5 cm apart (slots 1 and 2 are not"),
    # odd numbers and addresses (README: a bad argument is one line and exit code 2)
    ("run --rate 1e-300 --port 0 --no-record", "argument --rate: 1e-300 is outside [1, 200] Hz"),
    ("simulate experiment1 --rate 1e-300", "argument --rate: 1e-300 is outside [1, 1000] Hz"),
    ("simulate experiment1 --duration 1e-300", "--duration 1e-300 s: shorter than one control tick"),
    ("run --host 8.8.8.8 --port 0 --no-record", "cannot serve on 8.8.8.8:0"),
    ("run --scenario {deep.toml} --port 0 --no-record", "deep.toml: arrays or tables nested deeper than 64 levels"),
    ("run --camera {random.mp4} --calibration static_config/camera/synthetic_calibrated.toml --port 0 --no-record",
     "OpenCV cannot read a frame from this file"),
]


@pytest.mark.parametrize(("args", "expected"), CASES, ids=[c[0].split()[0] + ":" + c[1][:30] for c in CASES])
def test_bad_input_is_one_line_and_exit_2(files, args, expected):
    before = {p.name: p.stat().st_mtime_ns for p in files["dir"].iterdir()}
    for name, path in files.items():
        args = args.replace("{" + name + "}", str(path))
    argv = args.split()
    res = main_cli(*argv)
    lines = res.stderr.strip().splitlines()
    assert res.returncode == 2, res.stderr + res.stdout
    assert "Traceback" not in res.stderr
    assert len(lines) == 1 and expected in lines[0], res.stderr
    after = {p.name: p.stat().st_mtime_ns for p in files["dir"].iterdir()}
    assert {k: v for k, v in after.items() if k in before} == before  # nothing given was changed


def test_an_empty_config_runs_the_shipped_synthetic_rig(files):
    """An empty --config means every default, including the shipped rig (not a path next to it)."""
    from app.live.config import load_service_config
    from app.params import MAX_FOLLOWERS

    cfg = load_service_config(files["empty.toml"], MAX_FOLLOWERS)
    assert cfg.rig_path.is_file() and cfg.calibration_path.is_file() and cfg.followers == 3
