from pathlib import Path

import pytest

from core.config import ConfigError, parse_scenario

GOOD = (Path(__file__).resolve().parents[2] / "static_config" / "scenarios" / "experiment2.toml").read_text()


def test_all_shipped_scenarios_parse():
    folder = Path(__file__).resolve().parents[2] / "static_config" / "scenarios"
    names = {p.stem for p in folder.glob("*.toml")}
    assert {"paper_simulation", "experiment1", "experiment2", "experiment3"} <= names
    for p in folder.glob("*.toml"):
        s = parse_scenario(p.read_text(), p.name)
        assert s.name == p.stem
        assert s.slots.shape[0] >= s.n
    assert parse_scenario(GOOD, "x").disturbances[0].follower == 1  # 1-based in the file


@pytest.mark.parametrize(
    ("old", "new", "message"),
    [
        ("rate_hz = 30.0", "rate_hz = 0.0", r"f.toml: rate_hz = 0.0: must be a number in \[1, 1000\] Hz"),
        ("rate_hz = 30.0", "rate_hz = \"fast\"", r"rate_hz = 'fast': must be a number"),
        ("speed_mps = 0.06", "speed_mps = 9.0", r"leader.speed_mps = 9.0: must be a number in \[-0.3, 0.3\] m/s"),
        ('profile = "constant"', 'profile = "zigzag"', r"leader.profile = 'zigzag': must be one of constant, eq39, segments"),
        ("heading_deg = 85.0", "heading_deg = 1e9", r"followers\[1\].heading_deg = 1000000000.0: must be a number in \[-360, 360\] deg"),
        ("position = [-0.70, 0.00]", "position = [-0.70]", r"followers\[1\].position = \[-0.7\]: must be \[x, y\]"),
        ("follower = 2", "follower = 3", r"disturbances\[1\].follower = 3: must be a whole number from 1 to 2"),
        ("end_s = 62.0", "end_s = 50.0", r"disturbances\[1\].end_s = 50.0: must be > start_s \(58\)"),
        ("[measurement]", "[measurement]\nposition_noise = 0.1", r"measurement.position_noise is not a known key"),
        ("slots = [[0.0, 0.70], [0.0, -0.70]]", "slots = [[0.0, 0.70]]", r"formation.slots = .*: must be at least as many points as followers \(2\)"),
        ("wheel_noise_mps = 0.005", "wheel_noise_mps = -1", r"dynamics.wheel_noise_mps = -1: must be a number in \[0, 0.5\] m/s"),
        ("[formation]", "[gains]\nk_f1 = 0.0\n[formation]", r"gains.k_f1 = 0.0: must be a number in \(0, 1\] m/s"),
        ('name = "experiment2"', "", r"f.toml: name is missing"),
        ("[leader]", "[leader\n", r"f.toml: not valid TOML"),
    ],
)
def test_bad_values_name_file_key_value_and_allowed(old, new, message):
    assert old in GOOD
    with pytest.raises(ConfigError, match=message) as info:
        parse_scenario(GOOD.replace(old, new, 1), "f.toml")
    assert "\n" not in str(info.value)
