"""core/ must stay pure: importing it never loads viser, serial or app."""

import subprocess
import sys


def test_importing_core_loads_no_io_packages():
    code = (
        "import sys, core, core.config, core.geometry, core.control.formation, core.control.assignment,"
        " core.control.targets, core.sim.run, core.sim.team, core.sim.profiles,"
        " core.camera.model, core.camera.render, core.camera.gamma, core.camera.config, core.camera.synthetic,"
        " core.vision.blobs, core.vision.pipeline, core.vision.heading, core.vision.tracking, core.vision.background,"
        " core.sim.vision_run;"
        "bad = [m for m in ('viser', 'serial', 'app', 'threading') if m in sys.modules and m != 'threading'];"
        "print(','.join(bad))"
    )
    out = subprocess.run([sys.executable, "-c", code], capture_output=True, text=True, check=True)
    assert out.stdout.strip() == ""


def test_core_source_uses_no_clock_threads_or_global_rng():
    import re
    from pathlib import Path

    core = Path(__file__).resolve().parents[1] / "core"
    banned = re.compile(
        r"\bimport (time|threading|serial|viser|random)\b|\bfrom (time|threading|serial|viser|random) import"
        r"|np\.random\.(seed|rand|randn|randint|normal|uniform|choice|shuffle|random)\(|cv2\.(randn|randu|setRNGSeed)\("
    )
    hits = [f"{p.relative_to(core)}:{i}: {line.strip()}"
            for p in core.rglob("*.py") for i, line in enumerate(p.read_text().splitlines(), 1) if banned.search(line)]
    assert hits == []
