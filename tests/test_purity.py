"""core/ must stay pure: importing it never loads viser, serial, zenoh or app, and its source
uses no clock, threads or global random state."""

import re
import subprocess
import sys

from tests.helpers import ROOT

CORE = ROOT / "core"
IO_PACKAGES = ("viser", "serial", "zenoh", "app")


def core_modules() -> list[str]:
    """Every module under core/, from the tree (a new module is checked without being listed)."""
    names = []
    for path in sorted(CORE.rglob("*.py")):
        parts = path.relative_to(ROOT).with_suffix("").parts
        names.append(".".join(parts[:-1] if parts[-1] == "__init__" else parts))
    return names


def test_the_module_list_comes_from_the_tree():
    names = core_modules()
    assert "core.link.protocol" in names and "core.camera.render.kernels" in names and "core.jit" in names
    assert len(names) == len(set(names)) == len(list(CORE.rglob("*.py")))


def test_importing_core_loads_no_io_packages():
    code = (
        f"import sys, importlib\nfor m in {core_modules()!r}: importlib.import_module(m)\n"
        f"print(','.join(m for m in {IO_PACKAGES!r} if m in sys.modules))"
    )
    out = subprocess.run([sys.executable, "-c", code], capture_output=True, text=True, check=True, cwd=ROOT)
    assert out.stdout.strip() == ""


def test_core_source_uses_no_clock_threads_or_global_rng():
    banned = re.compile(
        r"\bimport (time|threading|serial|viser|zenoh|random)\b|\bfrom (time|threading|serial|viser|zenoh|random) import"
        r"|np\.random\.(seed|rand|randn|randint|normal|uniform|choice|shuffle|random)\(|cv2\.(randn|randu|setRNGSeed)\("
    )
    hits = [f"{p.relative_to(CORE)}:{i}: {line.strip()}"
            for p in CORE.rglob("*.py") for i, line in enumerate(p.read_text().splitlines(), 1) if banned.search(line)]
    assert hits == []
