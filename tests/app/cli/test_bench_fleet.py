"""The leader bench's fleet file (``make bench``, fleet line) is one `arena` accepts: its teams
fit one fleet's marker hues, and FLEET_TEAMS is within what a fleet holds."""

import pytest

from app.cli.bench.fleet import FLEET_TEAMS, bench_fleet_file
from core.camera.config import MIN_HUE_SEPARATION_DEG
from core.config import ConfigError
from core.fleet import parse_fleet


def test_the_bench_fleet_of_fleet_teams_teams_parses_as_the_arena_parses_it():
    fleet = parse_fleet(bench_fleet_file(FLEET_TEAMS, "bench0"), "bench0.toml")
    assert fleet.name == "bench0" and fleet.rate_hz == 30.0
    assert [ld.id for ld in fleet.leaders] == [f"L{k + 1}" for k in range(FLEET_TEAMS)]
    assert all(ld.followers == 3 and ld.mode == "straight" for ld in fleet.leaders)
    hues = [h for ld in fleet.leaders for h in ld.hues_deg]
    assert len(set(hues)) == 3 * FLEET_TEAMS


def test_one_team_more_than_a_fleets_hues_hold_is_refused():
    most = int(360 // MIN_HUE_SEPARATION_DEG) // 3  # teams of 3, every robot its own hue
    assert FLEET_TEAMS <= most
    parse_fleet(bench_fleet_file(most), "bench.toml")
    with pytest.raises(ConfigError, match="cannot carry hues"):
        parse_fleet(bench_fleet_file(most + 1), "bench.toml")
