"""core/ must stay pure: importing it never loads viser, serial or app."""

import subprocess
import sys


def test_importing_core_loads_no_io_packages():
    code = (
        "import sys, core, core.config, core.geometry, core.control.formation, core.control.assignment,"
        " core.control.targets, core.sim.run, core.sim.team, core.sim.profiles;"
        "bad = [m for m in ('viser', 'serial', 'app', 'threading') if m in sys.modules and m != 'threading'];"
        "print(','.join(bad))"
    )
    out = subprocess.run([sys.executable, "-c", code], capture_output=True, text=True, check=True)
    assert out.stdout.strip() == ""
