"""The link registry (app.backends.links): one place maps a link spec's scheme to its parser and
factory; the command line only looks a spec up there, and refuses an unknown scheme in one line
naming the schemes the option takes."""

from __future__ import annotations

import ast

import pytest

from app.backends.links import FOLLOWERS, LEADER, LINK_TYPES, Wiring, make, parse_link, schemes_for
from core.link.spec import SCHEMES
from tests.helpers import ROOT, main_cli


@pytest.mark.parametrize(("args", "line"), [
    (("--link", "tcp:9"), "--link 'tcp:9': must be 'sim', 'none' or 'serial:PATH'"),
    (("--link", "ros2:/cmd_vel"), "--link 'ros2:/cmd_vel': must be 'sim', 'none' or 'serial:PATH'"),
    (("--link", "serial:"), "--link 'serial:': must be 'sim', 'none' or 'serial:PATH'"),
    (("--leader", "udp:/x"), "--leader 'udp:/x': must be 'serial:PATH' or 'ros2:/TOPIC'"),
    (("--leader", "sim"), "--leader 'sim': must be 'serial:PATH' or 'ros2:/TOPIC'"),
])
def test_the_command_line_refuses_an_unknown_link_scheme_in_one_line_naming_the_schemes(args, line):
    out = main_cli("run", "--port", "0", "--no-record", *args)
    assert out.returncode == 2, out.stderr
    assert out.stderr.strip().splitlines() == [f"omniformation: error: {line}"]


def test_each_option_takes_the_schemes_the_registry_says():
    assert schemes_for(FOLLOWERS) == ("sim", "none", "serial")
    assert schemes_for(LEADER) == ("serial", "ros2")
    for name, kind in LINK_TYPES.items():  # every scheme's parser is core.link.spec's, under its own name
        assert kind.scheme is SCHEMES[name] and kind.options


def test_a_spec_is_parsed_into_its_scheme_and_value():
    assert parse_link("sim", FOLLOWERS).scheme == "sim" and parse_link("none", FOLLOWERS).ports == ()
    two = parse_link("serial:/dev/ttyUSB0, socket://127.0.0.1:9", FOLLOWERS)
    assert two.scheme == "serial" and two.ports == ("/dev/ttyUSB0", "socket://127.0.0.1:9")
    assert parse_link("ros2:/cmd_vel:stamped", LEADER).topic == ("/cmd_vel", True)
    assert parse_link("ros2:/base/cmd_vel", LEADER).topic == ("/base/cmd_vel", False)
    with pytest.raises(ValueError, match=r"^--link 'serial:/dev/a,,/dev/b': an empty port name in the list$"):
        parse_link("serial:/dev/a,,/dev/b", FOLLOWERS)
    with pytest.raises(ValueError, match=r"^--leader 'ros2:cmd_vel': must be ros2:/TOPIC or ros2:/TOPIC:stamped \("):
        parse_link("ros2:cmd_vel", LEADER)


def test_the_factory_makes_nothing_for_the_simulated_team_and_a_serial_link_for_a_port(tmp_path):
    """sim and none open nothing; serial: opens the port it names (a missing one is said as the
    serial link says it)."""
    assert make(parse_link("sim", FOLLOWERS), FOLLOWERS, Wiring(n=3)) is None
    assert make(parse_link("none", FOLLOWERS), FOLLOWERS, Wiring(n=3)) is None
    with pytest.raises(ValueError, match="2 ports for 3 followers"):
        make(parse_link("serial:/dev/a,/dev/b", FOLLOWERS), FOLLOWERS, Wiring(n=3))


def test_the_command_line_parses_no_link_spec_itself():
    """app/cli looks a spec up in the registry: it imports no scheme's parser or factory."""
    private = {"app.backends.serial_link", "app.backends.ros2", "core.link.spec"}
    found = []
    for f in sorted((ROOT / "app" / "cli").glob("*.py")):
        for node in ast.walk(ast.parse(f.read_text(encoding="utf-8"))):
            if isinstance(node, ast.ImportFrom) and node.module in private:
                names = {a.name for a in node.names} - {"same_device"}  # a device check, not a spec's
                if names:
                    found.append(f"{f.relative_to(ROOT)}:{node.lineno} {node.module} {sorted(names)}")
    assert not found, found
