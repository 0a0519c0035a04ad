"""The house has no upward arrows and no sideways doors: what each folder of app/ may import
(every import statement, at any depth, type-only ones included), no function of app/ or core/
longer than a screenful or two (120 lines) and no module longer than 700.

The order: cli -> services -> dashboard / recording / fleet / ros2 -> live -> backends ->
contracts -> core. Dashboard, recording and fleet import none of one another: what two of them
share lives below them (the state publisher beside TickState, the parameter events beside
Params, the figures in app/figures.py). app/ros2 (the service as a ROS 2 node) sits beside the
fleet: like the fleet's bridge it reads what the loop publishes and writes the store, so it
imports no loop, page, recorder, service or command line; it may use the fleet's endpoint rules
and keys (app.fleet.bridge.check_endpoint, app.fleet.security), and nothing below it imports it."""

from __future__ import annotations

import ast
import re
from pathlib import Path

from tests.helpers import ROOT

# folder -> the app folders it must not import (no allow-list: a file that needs one moves its need down)
SIDEWAYS = {"dashboard", "recording", "fleet"}
FORBIDDEN = {
    # the loop types against app.contracts alone: the services hand it its world (app.backends.world)
    "live": {"backends", "dashboard", "fleet", "ros2", "services", "cli", "recording"},
    "backends": {"live", "dashboard", "fleet", "ros2", "services", "recording", "cli"},
    **{row: (SIDEWAYS - {row}) | {"ros2", "services", "cli"} for row in SIDEWAYS},
    "ros2": {"live", "dashboard", "recording", "services", "cli"},
    "services": {"cli"},
}
FORBIDDEN["recording"] |= {"live"}  # a recording is read and written without the loop
MAX_FUNCTION_LINES = 120


def _app_imports(path: Path) -> set[str]:
    out = set()
    for node in ast.walk(ast.parse(path.read_text(encoding="utf-8"))):
        names = [node.module] if isinstance(node, ast.ImportFrom) and node.level == 0 and node.module else \
            [a.name for a in node.names] if isinstance(node, ast.Import) else []
        out |= {n.split(".")[1] for n in names if n.startswith("app.") and n.count(".") >= 1}
    return out


def _module_names(root: Path) -> dict[str, Path]:
    """Every module of app/ and core/ by its dotted name (a package by its own, for __init__.py)."""
    found = {}
    for pkg in ("app", "core"):
        for f in sorted((root / pkg).rglob("*.py")):
            parts = f.relative_to(root).with_suffix("").parts
            found[".".join(parts[:-1] if parts[-1] == "__init__" else parts)] = f
    return found


def _imported_modules(name: str, path: Path, modules: dict[str, Path]) -> set[str]:
    """The modules of app/ and core/ that ``name`` imports: every import statement, at any depth
    (inside functions, methods and ``if`` blocks too: an import inside a function runs when it is
    called, so a circle through one is a circle all the same), relative ones resolved, ``from
    package import submodule`` taken as the submodule. Imports under ``if TYPE_CHECKING:`` never
    run, but they are counted too: a module that names another's type depends on it, and a
    type-only import is where a circle hides until someone needs the name at run time."""
    package = name.split(".") if path.name == "__init__.py" else name.split(".")[:-1]
    out = set()
    for node in ast.walk(ast.parse(path.read_text(encoding="utf-8"))):
        if isinstance(node, ast.Import):
            out |= {a.name for a in node.names if a.name in modules}
        elif isinstance(node, ast.ImportFrom):
            base = ".".join(package[:len(package) - node.level + 1] + ([node.module] if node.module else [])) \
                if node.level else (node.module or "")
            for a in node.names:
                whole = f"{base}.{a.name}"
                if whole in modules:
                    out.add(whole)
                elif base in modules:
                    out.add(base)
    out.discard(name)
    return out


def import_circles(root: Path = ROOT) -> list[list[str]]:
    """The import circles among the modules of ``root``'s app/ and core/: each group of modules that
    reach one another through imports (a strongly connected component of the import graph, Tarjan's)."""
    modules = _module_names(root)
    graph = {m: sorted(_imported_modules(m, f, modules)) for m, f in modules.items()}
    index: dict[str, int] = {}
    low: dict[str, int] = {}
    stack: list[str] = []
    circles: list[list[str]] = []

    def visit(v: str) -> None:
        index[v] = low[v] = len(index)
        stack.append(v)
        for w in graph[v]:
            if w not in index:
                visit(w)
                low[v] = min(low[v], low[w])
            elif w in stack:
                low[v] = min(low[v], index[w])
        if low[v] == index[v]:
            group = []
            while True:
                w = stack.pop()
                group.append(w)
                if w == v:
                    break
            if len(group) > 1:
                circles.append(sorted(group))

    for v in sorted(graph):
        if v not in index:
            visit(v)
    return circles


def test_no_module_of_app_or_core_imports_itself_in_a_circle():
    """No circle of imports, counting those inside functions and type-only ones (a circle is
    broken by moving what both sides share down a layer, never by an import inside a function)."""
    circles = import_circles()
    assert not circles, "import circles: " + "; ".join(" <-> ".join(group) for group in circles)


def test_the_circle_finder_finds_a_circle_through_an_import_inside_a_function(tmp_path: Path) -> None:
    """The finder itself: two modules that import each other, one of them only inside a function
    and the other only for types, are one circle; the module that imports one of them is not in it."""
    (tmp_path / "app").mkdir()
    (tmp_path / "core").mkdir()
    (tmp_path / "app" / "__init__.py").write_text("")
    (tmp_path / "core" / "__init__.py").write_text("")
    (tmp_path / "app" / "one.py").write_text("def f():\n    from app.two import g\n    return g\n")
    (tmp_path / "app" / "two.py").write_text("from typing import TYPE_CHECKING\nif TYPE_CHECKING:\n"
                                             "    from . import one\ng = 1\n")
    (tmp_path / "app" / "three.py").write_text("import app.one\n")
    assert import_circles(tmp_path) == [["app.one", "app.two"]]


def test_no_folder_of_app_imports_one_above_it():
    broken = []
    for folder, banned in FORBIDDEN.items():
        files = sorted((ROOT / "app" / folder).rglob("*.py"))
        assert files, folder
        for f in files:
            if bad := _app_imports(f) & banned:
                broken.append(f"{f.relative_to(ROOT)} imports app.{', app.'.join(sorted(bad))}")
    assert not broken, broken


def test_the_loop_builds_no_backend_itself():
    """The loop is handed its world (app.contracts.World, app.backends.world.Backends, by the
    services): it names no backend's class to make one."""
    text = (ROOT / "app" / "live" / "loop.py").read_text(encoding="utf-8")
    for made_elsewhere in ("SimTeam(", "VisionFeedback(", "TruthFeedback(", "ArenaFeedback(", "spread_start("):
        assert made_elsewhere not in text, made_elsewhere


def test_the_command_line_builds_no_part_itself():
    """app/cli/*.py parses and checks arguments, prints and calls services: it opens no bus, page,
    link, recorder, bridge or node itself (the composition roots are app/services'; bench/ measures
    the parts one by one and is left out: it is a folder, not a module of app/cli/*.py)."""
    parts = re.compile(r"\b(Service|FleetBridge|Adopter|ArenaTeam|Arena|FleetView|FleetRecorder|Recorder|Ros2Bridge"
                       r"|Ros2Node|Ros2Base|EmulatedBase|FoxgloveLive|FoxgloveFleet|HardwareTeam|SerialLink)\(|"
                       r"\b(open_session|open_bus|serve_gated|make_link|open_ros2_session)\(")
    built = [f"{f.relative_to(ROOT)}:{k + 1}" for f in sorted((ROOT / "app" / "cli").glob("*.py"))
             for k, line in enumerate(f.read_text(encoding="utf-8").splitlines()) if parts.search(line.split("#")[0])]
    assert not built, built


def test_every_benchmark_is_in_the_bench_package():
    """`omniformation bench`'s families are modules of app/cli/bench/, none a loose app/cli/bench_*.py."""
    assert not sorted((ROOT / "app" / "cli").glob("bench_*.py"))


def test_the_tests_import_no_private_name_of_the_project():
    """A test uses what a module offers (a name without a leading underscore), so a module's
    private parts can change without a test importing them; third-party private names are not
    the project's to rename and are left out."""
    private = []
    for f in sorted((ROOT / "tests").rglob("*.py")):
        for node in ast.walk(ast.parse(f.read_text(encoding="utf-8"))):
            if isinstance(node, ast.ImportFrom) and node.module and node.module.split(".")[0] in {"app", "core", "tests"}:
                private += [f"{f.relative_to(ROOT)}:{node.lineno} {node.module}.{a.name}"
                            for a in node.names if a.name.startswith("_")]
    assert not private, private


def test_the_modules_beside_the_contracts_import_no_folder():
    for name in ("contracts", "params", "tick", "keys", "files", "memory", "wire", "figures"):
        imported = _app_imports(ROOT / "app" / f"{name}.py")
        assert imported <= {"contracts", "params", "tick", "keys", "files", "memory"}, (name, imported)


def test_no_function_is_longer_than_120_lines():
    long = []
    for folder in ("app", "core"):
        for f in sorted((ROOT / folder).rglob("*.py")):
            for node in ast.walk(ast.parse(f.read_text(encoding="utf-8"))):
                if isinstance(node, (ast.FunctionDef, ast.AsyncFunctionDef)):
                    n = (node.end_lineno or node.lineno) - node.lineno + 1
                    if n > MAX_FUNCTION_LINES:
                        long.append(f"{f.relative_to(ROOT)}:{node.lineno} {node.name} ({n} lines)")
    assert not long, long


MAX_MODULE_LINES = 700


def test_no_module_is_longer_than_700_lines():
    """A module that grows past this does more than one job: split it by job (as bench/ and report/statistics)."""
    long = [f"{f.relative_to(ROOT)} ({n} lines)" for folder in ("app", "core") for f in sorted((ROOT / folder).rglob("*.py"))
            if (n := len(f.read_text(encoding="utf-8").splitlines())) > MAX_MODULE_LINES]
    assert not long, long


def test_only_one_module_reaches_into_viser_s_private_parts():
    """viser's private modules and attributes (``viser._messages``, ``._impl``, ``._websock_…``)
    are reached from app/dashboard/viser_private.py alone: a viser upgrade is checked in one file."""
    private = re.compile(r"\bviser\._[a-z]|\._impl\b|\._websock_|\._gui_input_handle|\._live_connections")
    found = [f"{f.relative_to(ROOT)}:{k + 1}" for folder in ("app", "core") for f in sorted((ROOT / folder).rglob("*.py"))
             if f.name != "viser_private.py"
             for k, line in enumerate(f.read_text(encoding="utf-8").splitlines())
             if private.search(line.split("#")[0])]
    assert not found, found


def test_the_tests_mirror_the_package():
    """tests/app/<folder>/ tests app/<folder>/, tests/core/<folder>/ tests core/<folder>/: every
    folder of tests/app and tests/core is a folder of the package, and a test file that sits at the
    top of tests/app (or tests/core) tests a module at the top of app/ (or core/) or the house itself."""
    strays = []
    for pkg in ("app", "core"):
        for folder in sorted(p for p in (ROOT / "tests" / pkg).rglob("*") if p.is_dir() and p.name != "__pycache__"):
            rel = folder.relative_to(ROOT / "tests" / pkg)
            if not (ROOT / pkg / rel / "__init__.py").is_file():
                strays.append(f"tests/{pkg}/{rel} has no package app/core folder {pkg}/{rel}")
    assert not strays, strays
    flat = sorted(f.name for f in (ROOT / "tests" / "app").glob("test_*.py"))
    assert flat == ["test_console.py", "test_layers.py", "test_memory.py", "test_parameter_table.py", "test_params.py", "test_processes.py",
                    "test_realtime.py"], flat
