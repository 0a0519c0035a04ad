"""`render`, `calibrate`, `locate` as a user runs them, and the accuracy they reach (README, "Camera")."""

import json
import math

import cv2
import numpy as np
import pytest

from app.files import SYNTHETIC_CALIBRATED, SYNTHETIC_CAMERA, load_camera
from core.camera.synthetic import renderer_for
from core.vision.blobs import find_blobs, hue_distance_deg
from tests.helpers import main_cli, run_cli


@pytest.fixture(scope="module")
def calibrated(tmp_path_factory):
    out = tmp_path_factory.mktemp("cal") / "camera.toml"
    table = out.parent / "table.csv"
    res = run_cli("calibrate", "--synthetic", str(SYNTHETIC_CAMERA), "--out", str(out), "--save-table", str(table))
    assert res.returncode == 0, res.stderr
    assert "8 sectors, degree 3" in res.stdout and "residual RMS" in res.stdout
    return out, table


def test_committed_calibration_is_what_calibrate_makes(calibrated):
    """The same file, every line, every key; the numbers equal to 1e-7 of each other (the least
    squares' last digits differ between CPUs: the linear algebra takes other SIMD paths)."""
    import re

    out, _ = calibrated
    made, committed = out.read_text(), SYNTHETIC_CALIBRATED.read_text()
    number = re.compile(r"-?\d+\.\d+(?:[eE][-+]?\d+)?|-?\d+[eE][-+]?\d+")
    assert number.sub("#", made) == number.sub("#", committed)
    xs, ys = [float(v) for v in number.findall(made)], [float(v) for v in number.findall(committed)]
    assert len(xs) == len(ys) and xs
    worst = max(abs(x - y) / max(abs(x), abs(y), 1e-12) for x, y in zip(xs, ys))
    assert worst <= 1e-7, worst


def test_a_real_table_fits_the_same_way(calibrated, tmp_path):
    _, table = calibrated
    res = run_cli("calibrate", str(table), "--out", str(tmp_path / "c.toml"), "--sectors", "4")
    assert res.returncode == 0, res.stderr
    assert "4 sectors" in res.stdout
    cam = load_camera(tmp_path / "c.toml")
    assert cam.gamma is not None and cam.gamma.n_sectors == 4


def _placements(rng, n, lo=0.3, hi=1.5, gap=0.4):
    pts = []
    while len(pts) < n:
        d, b = rng.uniform(lo, hi), rng.uniform(-math.pi, math.pi)
        p = np.array([-d * math.sin(b), d * math.cos(b)])
        if all(np.linalg.norm(p - q) > gap for q in pts):
            pts.append(p)
    return np.array(pts)


def test_locate_accuracy_on_random_placements(calibrated, tmp_path):
    """Median <= 1.5 cm, 95th percentile <= 3 cm, 0.3..1.5 m, default flaws, noise and clutter."""
    out, _ = calibrated
    cam = load_camera(out)
    rig = load_camera(SYNTHETIC_CAMERA)
    renderer = renderer_for(rig)
    gamma = cam.gamma
    area = cam.working_area.mask(640, 480, (gamma.cx, gamma.cy))
    rng = np.random.default_rng(2024)
    errors, missed = [], 0
    for k in range(50):
        truth = _placements(rng, 6)
        poses = np.column_stack([truth, rng.uniform(-math.pi, math.pi, 6)])
        leader = np.array([rng.uniform(-20, 20), rng.uniform(-20, 20), rng.uniform(-math.pi, math.pi)])
        frame = renderer.render(leader, poses, 0.9 * k, rng)
        if k < 3:  # through the command, as a user would
            path = tmp_path / f"frame{k}.png"
            cv2.imwrite(str(path), frame)
            res = run_cli("locate", str(path), "--camera", str(out))
            assert res.returncode == 0, res.stderr
            blobs = [json.loads(line) for line in res.stdout.splitlines()]
            assert set(blobs[0]) == {"hue_deg", "pixel", "area_px", "x", "y"}
            found = [(b["hue_deg"], np.array([b["x"], b["y"]])) for b in blobs]
        else:
            found = [(b.hue_deg, gamma.pixel_to_leader(np.array(b.u), np.array(b.v))) for b in find_blobs(frame, area, cam.detect)]
        for i in range(6):
            hue = rig.render.hues_deg[i]
            cands = [xy for h, xy in found if hue_distance_deg(h, hue) < 15]
            if not cands:
                missed += 1  # hidden behind a box of the clutter
                continue
            errors.append(min(np.linalg.norm(xy - truth[i]) for xy in cands))
    e = np.array(errors) * 100
    print(f"locate: {len(e)} markers, median {np.median(e):.2f} cm, p95 {np.percentile(e, 95):.2f} cm, max {e.max():.2f} cm")
    assert missed <= 0.03 * 300
    assert np.median(e) <= 1.5
    assert np.percentile(e, 95) <= 3.0


def test_grey_clutter_is_never_reported(calibrated, tmp_path):
    out, _ = calibrated
    cam = load_camera(out)
    renderer = renderer_for(load_camera(SYNTHETIC_CAMERA), distractor=False)
    area = cam.working_area.mask(640, 480, (cam.gamma.cx, cam.gamma.cy))
    rng = np.random.default_rng(5)
    boxes_in_view = 0
    for k in range(40):
        leader = np.array([rng.uniform(-8, 8), rng.uniform(-8, 8), rng.uniform(-math.pi, math.pi)])
        boxes = renderer.boxes(leader, np.zeros((0, 3)))
        boxes_in_view += int(np.sum(np.hypot(boxes.x, boxes.y) < 2.0))
        frame = renderer.render(leader, np.zeros((0, 3)), 0.5 * k, rng)
        assert find_blobs(frame, area, cam.detect) == []
    assert boxes_in_view >= 20  # the boxes really were in the working area
    path = tmp_path / "grey.png"
    cv2.imwrite(str(path), frame)
    res = run_cli("locate", str(path), "--camera", str(out))
    assert res.returncode == 0 and res.stdout == ""


def test_render_writes_a_frame_of_a_scenario(tmp_path):
    out = tmp_path / "f.png"
    res = run_cli("render", "experiment1", "--t", "12.5", "--out", str(out))
    assert res.returncode == 0, res.stderr
    img = cv2.imread(str(out))
    assert img.shape == (480, 640, 3)


@pytest.mark.parametrize(
    "args, message",
    [
        (["render", "experiment1", "--t", "500", "--out", "X/f.png"], "lasts 90 s"),
        (["render", "experiment1", "--t", "-1", "--out", "f.png"], "argument --t: -1 is outside [0, 86400] s"),
        (["render", "nosuch", "--out", "f.png"], "scenario 'nosuch' not found"),
        (["calibrate", "--out", "c.toml"], "give either TABLE.csv or --synthetic"),
        (["calibrate", "BAD_TABLE", "--out", "OUT/c.toml"], "missing column 'v'"),
        (["calibrate", "BAD_TABLE", "--out", "c.toml", "--degree", "9"], "argument --degree: 9 is outside 1..7"),
        (["locate", "NOT_IMAGE", "--camera", str(SYNTHETIC_CALIBRATED)], "not an image OpenCV can read"),
        (["locate", "NOT_IMAGE", "--camera", str(SYNTHETIC_CAMERA)], "has no [gamma] section"),
    ],
)
def test_bad_input_is_one_line_and_exit_2(tmp_path, args, message):
    (tmp_path / "OUT").mkdir()
    (tmp_path / "bad.csv").write_text("bearing_deg,metres,u\n0,1,2\n")
    (tmp_path / "notes.png").write_text("not a picture")
    args = [a.replace("BAD_TABLE", str(tmp_path / "bad.csv")).replace("NOT_IMAGE", str(tmp_path / "notes.png"))
            .replace("OUT/", str(tmp_path / "OUT") + "/").replace("X/", str(tmp_path) + "/") for a in args]
    res = main_cli(*args)
    assert res.returncode == 2, res.stdout + res.stderr
    assert message in res.stderr and len(res.stderr.strip().splitlines()) == 1, res.stderr


def _synthetic_table(model, path):
    """A table of the synthetic mirror model as a person measures it (4 bearings x 15 distances)."""
    from app.files import write_table
    from core.camera.gamma import MatchingTable
    from core.camera.model import bearing_range_to_xy

    rng = np.random.default_rng(5)
    rows = []
    for b in (0.0, 90.0, 180.0, 270.0):
        for d in [round(0.4 + 0.1 * i, 2) for i in range(15)]:
            xy = bearing_range_to_xy(np.array(math.radians(b)), np.array(d))
            u, v = model.project(np.array([float(xy[0]), float(xy[1]), 0.102]))
            rows.append((b, d, u + rng.normal(0, 0.3), v + rng.normal(0, 0.3)))
    a = np.array(rows)
    table = MatchingTable(a[:, 0], a[:, 1], a[:, 2], a[:, 3])
    write_table(table, path)
    return table


@pytest.mark.parametrize("flip", [False, True])
def test_a_turned_or_mirrored_camera_calibrates_into_a_file_locate_and_run_accept(tmp_path, flip):
    """Every rotation (in 13 deg steps, and the odd 89.4) and both mirrorings: calibrate reads
    them from the table and writes a file that loads and places the markers right."""
    from core.camera.config import parse_camera
    from core.camera.model import CameraModel, bearing_range_to_xy

    for turn in [*range(0, 360, 13), 89.4, 359.0]:
        model = CameraModel(bearing_offset_deg=float(turn), flip=flip, tilt_deg=1.0)
        table = _synthetic_table(model, tmp_path / f"t{turn}.csv")
        out = tmp_path / f"c{turn}.toml"
        res = main_cli("calibrate", str(tmp_path / f"t{turn}.csv"), "--out", str(out))
        assert res.returncode == 0, (turn, res.stderr)
        assert "the markers show the camera" in res.stdout or abs(turn) < 1 and not flip, (turn, res.stdout)
        gamma = parse_camera(out.read_text(), out.name).gamma  # what locate and run load
        assert gamma is not None and gamma.flip == flip
        xy = bearing_range_to_xy(np.radians(table.bearing_deg), table.metres)
        err = np.linalg.norm(gamma.pixel_to_leader(table.u, table.v) - xy, axis=1)
        assert err.max() < 0.03, (turn, err.max())
    # a turn given that the table contradicts is refused with the option to use
    res = main_cli("calibrate", str(tmp_path / "t91.csv"), "--out",
                   str(tmp_path / "x.toml"), "--bearing-offset", "0")
    assert res.returncode == 2 and "use --bearing-offset 91" in res.stderr, res.stderr
    assert not (tmp_path / "x.toml").exists()
    # an existing camera file is never replaced without --overwrite
    first = tmp_path / "c0.toml"
    before = first.read_text()
    res = main_cli("calibrate", str(tmp_path / "t0.csv"), "--out", str(first))
    assert res.returncode == 2 and "--overwrite" in res.stderr and first.read_text() == before
    assert main_cli("calibrate", str(tmp_path / "t0.csv"), "--out", str(first), "--overwrite").returncode == 0


def test_calibrate_reports_the_held_out_error_and_warns_on_gaps(tmp_path):
    from app.files import write_table
    from core.camera.model import CameraModel

    table = _synthetic_table(CameraModel(tilt_deg=2.0), tmp_path / "full.csv")
    res = main_cli("calibrate", str(tmp_path / "full.csv"), "--out", str(tmp_path / "full.toml"))
    assert res.returncode == 0 and "held-out error" in res.stdout and "warning" not in res.stdout, res.stdout
    assert "held-out error median" in (tmp_path / "full.toml").read_text()
    keep = (table.bearing_deg != 90.0) & ((table.metres < 0.75) | (table.metres > 1.45) | (table.bearing_deg != 0.0))
    from core.camera.gamma import MatchingTable

    write_table(MatchingTable(*(np.asarray(c)[keep] for c in (table.bearing_deg, table.metres, table.u, table.v))),
                tmp_path / "gappy.csv")
    res = main_cli("calibrate", str(tmp_path / "gappy.csv"), "--out", str(tmp_path / "gappy.toml"))
    assert res.returncode == 0, res.stderr
    assert "warning: no bearing between 0 and 180 deg" in res.stdout, res.stdout
    assert "warning: bearing 0 deg: no marker between 0.7 and 1.5 m" in res.stdout, res.stdout
