"""Every door of the fleet bus closed (docs/fleet-protocol.md), each tried by a hostile party
written from the document: a name that only looks like loopback, payloads built to break a
parser, key folders that hold more than their identity's keys, a page certificate used
beyond the page's role."""

from __future__ import annotations

import json
import os
import shutil
import subprocess
import sys
import uuid
from collections.abc import Iterator
from pathlib import Path

import pytest

from tests.helpers import ROOT

FLEET = "three_teams"
BASE = f"omniformation/{FLEET}"


# -- H: a name is judged by the addresses it resolves to -------------------------------------------
@pytest.fixture
def netns() -> Iterator[tuple[str, str]]:
    """A network namespace of this test's own, joined to this one by a veth pair: its address
    (10.231.x.2) is on this machine and is not loopback. ``ip netns exec`` gives a process in it
    the namespace's own hosts file (/etc/netns/NAME/hosts) in place of /etc/hosts: the names
    below resolve through the real resolver, for that process only."""
    if shutil.which("ip") is None or os.geteuid() != 0:
        pytest.skip("network namespaces need `ip` and root")
    tag = uuid.uuid4().hex[:6]
    name, here, there = f"omf{tag}", f"vo{tag}", f"vi{tag}"
    subnet = f"10.231.{int(tag[:2], 16)}"
    made = subprocess.run(["ip", "netns", "add", name], capture_output=True, text=True)
    if made.returncode != 0:
        pytest.skip(f"network namespaces unavailable: {made.stderr.strip()}")
    etc = Path("/etc/netns") / name
    try:
        for cmd in (["ip", "link", "add", here, "type", "veth", "peer", "name", there],
                    ["ip", "link", "set", there, "netns", name],
                    ["ip", "addr", "add", f"{subnet}.1/24", "dev", here], ["ip", "link", "set", here, "up"],
                    ["ip", "-n", name, "addr", "add", f"{subnet}.2/24", "dev", there],
                    ["ip", "-n", name, "link", "set", there, "up"], ["ip", "-n", name, "link", "set", "lo", "up"]):
            subprocess.run(cmd, check=True, capture_output=True)
        etc.mkdir(parents=True)
        (etc / "hosts").write_text(f"127.0.0.1 localhost home.lan both.lan\n{subnet}.2 127.lan 127.0.0.1.evil both.lan\n")
        yield name, f"{subnet}.2"
    finally:
        subprocess.run(["ip", "link", "del", here], capture_output=True)
        subprocess.run(["ip", "netns", "del", name], capture_output=True)
        shutil.rmtree(etc, ignore_errors=True)


RUN_IN_NETNS = """
import json, sys
from tests.helpers import main_cli
out = []
for args in json.loads(sys.argv[1]):
    r = main_cli(*args)
    out.append([r.returncode, r.stderr])
print(json.dumps(out))
"""


def test_an_open_endpoint_is_loopback_by_every_address_its_name_resolves_to(netns):
    """docs/fleet-protocol.md, "Joining": a name is resolved and every address must be loopback."""
    name, address = netns
    cases = [
        (["arena", FLEET, "--zenoh-listen", "tcp/127.lan:17447", "--minutes", "0.005"], 2, f"127.lan is {address}"),
        (["fleet", "--fleet", FLEET, "--zenoh-connect", "tcp/127.0.0.1.evil:17447", "--port", "0"], 2,
         f"127.0.0.1.evil is {address}"),
        (["arena", FLEET, "--zenoh-listen", "udp/both.lan:17447", "--minutes", "0.005"], 2, f"both.lan is {address}"),
        (["arena", FLEET, "--zenoh-listen", "tcp/nowhere.invalid:17447", "--minutes", "0.005"], 2,
         "nowhere.invalid' does not resolve"),
        # a name that is 127.0.0.1 only passes: the line is about what comes after it
        (["run", "--fleet", FLEET, "--leader-id", "L1", "--zenoh-connect", "tcp/home.lan:17447", "--scenario",
          "no_such_scenario"], 2, "scenario 'no_such_scenario' not found"),
    ]
    r = subprocess.run(["ip", "netns", "exec", name, sys.executable, "-c", RUN_IN_NETNS,
                        json.dumps([c[0] for c in cases])], cwd=ROOT, capture_output=True, text=True, timeout=60)
    assert r.returncode == 0, r.stderr
    for (args, code, words), (rc, err) in zip(cases, json.loads(r.stdout.strip().splitlines()[-1]), strict=True):
        lines = err.strip().splitlines()
        assert rc == code and len(lines) == 1 and words in lines[0], (args, rc, err)
        refused_endpoint = "not loopback" in lines[0] or "does not resolve" in lines[0]
        assert refused_endpoint == ("no_such_scenario" not in args), (args, err)
