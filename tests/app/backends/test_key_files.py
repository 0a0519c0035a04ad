"""The key folder against hostile input, on real files (docs/safety.md, "Key files and counters";
docs/follower-protocol.md, "Keys and provisioning", "Counters that only grow", "Rotating the
key"): names that would collide with the folder's own layout, key and counter files that are not
regular files or are too big or too deep, counters that are corrupt or cannot go up, and a
rotation interrupted half way. Each is one line on stderr, exit 2, and nothing written."""

from __future__ import annotations

import pytest

from tests.helpers import main_cli


def _files(d) -> list[str]:
    return sorted(str(p.relative_to(d)) for p in d.rglob("*")) if d.exists() else []


def _one_line(r) -> str:
    lines = r.stderr.strip().splitlines()
    assert r.returncode == 2 and len(lines) == 1 and "Traceback" not in r.stderr, (r.returncode, r.stderr)
    return lines[0]


@pytest.mark.parametrize("leaders, words", [
    ("ca,L1", "a name the key folder uses itself"),  # would write over the CA's ca.key and ca.pem
    ("L1,radio", "a name the key folder uses itself"),  # would get the radio folder as its bundle
    ("L1,next", "a name the key folder uses itself"),
    ("CA,L1", "a name the key folder uses itself"),  # "CA" is "ca" on a case-blind file system
    ("L1,Robots", "a name the key folder uses itself"),
    ("L1,l1", "twice"),
    ("1L", "a letter first"),
    ("L1,-L2", "a letter first"),
    ("_x", "a letter first"),
    ("L1,../L2", "a letter first"),
    ("L 1", "1 to 32 characters"),
    ("L1,L2." , "a letter first"),
    ("L" * 33, "1 to 32 characters"),
    ("L\u00e9", "a letter first"),
])
def test_identity_names_that_collide_or_are_not_names_are_refused_and_nothing_is_written(tmp_path, leaders, words):
    d = tmp_path / "keys"
    r = main_cli("fleet-keys", str(d), "--fleet", "lab", "--leaders", leaders)
    line = _one_line(r)
    assert words in line and "--leaders" in line, line
    assert _files(d) == []


def test_too_many_leaders_for_the_radio_are_refused_before_any_file_is_written(tmp_path):
    d = tmp_path / "keys"
    r = main_cli("fleet-keys", str(d), "--fleet", "lab", "--leaders", ",".join(f"L{k}" for k in range(1, 18)))
    assert "at most 16" in _one_line(r) and _files(d) == []


def test_good_names_still_make_keys(tmp_path):
    d = tmp_path / "keys"
    r = main_cli("fleet-keys", str(d), "--fleet", "lab", "--leaders", "L1,leader_2,Rover-3,x" + "y" * 31)
    assert r.returncode == 0, r.stderr
    assert (d / "ca" / "ca.key").is_file() and (d / "leader_2" / "leader_2.radio").is_file()
