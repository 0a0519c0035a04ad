"""The leader bench (``make bench``, fleet line): its fleet file is one `arena` accepts (its teams
fit one fleet's marker hues, and FLEET_TEAMS is within what a fleet holds), and how it counts."""

import math

import pytest

from app.cli.bench.fleet import (FLEET_TEAMS, HELD_HZ, STEAL_LIMIT, WINDOWS_PER_COUNT, LeaderCount, Window,
                                 bench_fleet_file, leader_count, leader_line)
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


def _w(count: int, hz: float, steal: float = 0.0) -> Window:
    return Window(count, hz, 15.0, 20.0, steal)


def test_a_count_whose_window_falls_below_is_measured_again_and_fails_on_two_windows_the_host_did_not_stall():
    """leader_count: (held, held before the first window that fell below, go on). A count that fell
    below 29.7 Hz is measured again (go on at the same count); it holds if a later window does. It
    fails at its second window that fell below with the hypervisor's steal at most STEAL_LIMIT (or
    not said: NaN), or at its WINDOWS_PER_COUNT-th window whatever the steal."""
    assert leader_count([_w(1, 30.0), _w(2, 29.9)]) == (2, 2, True)
    assert leader_count([_w(1, 30.0), _w(2, 29.69)]) == (1, 1, True)  # once: measure again
    assert leader_count([_w(1, 30.0), _w(2, 29.69), _w(2, 29.8), _w(3, 29.9)]) == (3, 1, True)
    assert leader_count([_w(1, 30.0), _w(2, 29.69), _w(2, 29.8), _w(3, 28.0), _w(3, 29.0)]) == (2, 1, False)
    assert leader_count([_w(1, 0.0), _w(1, 0.0)]) == (0, 0, False)  # none held at all
    assert leader_count([]) == (0, 0, True)
    # stalls of the host's: not counted, measured again, up to WINDOWS_PER_COUNT windows
    stolen = STEAL_LIMIT + 0.1
    assert leader_count([_w(1, 30.0), _w(2, 29.0, stolen), _w(2, 29.0)]) == (1, 1, True)
    assert leader_count([_w(1, 30.0), _w(2, 29.0, stolen), _w(2, 29.0), _w(2, 29.8)]) == (2, 1, True)
    assert leader_count([_w(1, 30.0), _w(2, 29.0, stolen), _w(2, 29.0), _w(2, 29.0, STEAL_LIMIT)]) == (1, 1, False)
    assert leader_count([_w(1, 30.0), _w(2, 29.0), _w(2, 29.0, math.nan)]) == (1, 1, False)  # steal not said
    assert leader_count([_w(1, 30.0)] + [_w(2, 29.0, stolen)] * (WINDOWS_PER_COUNT - 1)) == (1, 1, True)
    assert leader_count([_w(1, 30.0)] + [_w(2, 29.0, stolen)] * WINDOWS_PER_COUNT) == (1, 1, False)
    assert _w(1, HELD_HZ).held and not _w(1, HELD_HZ - 0.01).held
    count = LeaderCount(2, 1, (_w(1, 30.0), _w(2, 29.0), _w(2, 29.9)))
    assert count.at(2).slowest_hz == 29.9  # the last window of that count


def test_the_bench_line_names_both_counts_every_window_and_the_steal_where_a_window_fell_below():
    count = LeaderCount(2, 1, (_w(1, 30.0), _w(2, 29.5), _w(2, 29.9), _w(3, 29.0), Window(3, 28.5, 16.0, 30.0, 6.25)))
    line = leader_line("run now", count)
    assert "holds 2 at 30 Hz" in line and "1 before the first window that fell below" in line
    assert "1: 30.00, 2: 29.50, 2: 29.90, 3: 29.00, 3: 28.50 Hz" in line
    assert "with 2 running, each leader (its process and its page) took 15.0 % of one CPU" in line
    assert "took 0.0, 0.0, 6.2 % of its CPUs (steal)" in line
    assert "it may hold more" not in line
    every = leader_line("run now", LeaderCount(2, 2, (_w(1, 30.0), _w(2, 29.9))))
    assert "it may hold more" in every and "steal" not in every


def test_a_count_stopped_on_the_hosts_stalls_alone_says_it_was_not_measured():
    stolen = STEAL_LIMIT + 1.0
    count = LeaderCount(1, 1, (_w(1, 30.0),) + (_w(2, 29.0, stolen),) * WINDOWS_PER_COUNT)
    assert count.host_bound
    assert "NOT MEASURED" in leader_line("run now", count) and "holds 1 at 30 Hz" in leader_line("run now", count)
    mixed = LeaderCount(1, 1, (_w(1, 30.0), _w(2, 29.0, stolen), _w(2, 29.0), _w(2, 29.0)))
    assert not mixed.host_bound and "NOT MEASURED" not in leader_line("run now", mixed)
    assert not LeaderCount(2, 2, (_w(1, 30.0), _w(2, 29.9))).host_bound
