"""The health banner's rules, as docs/page-access.md states them: each cause raises one alarm while
it lasts, recorded by each listener, and the banner keeps it until someone acknowledges it."""

from __future__ import annotations

import dataclasses

import numpy as np
import pytest

from app.dashboard.gate import page_head
from app.dashboard.health import Health
from app.tick import TickState
from core.types import Gains


def tick(t: float, **changes: object) -> TickState:
    n = 2
    s = TickState(tick=int(t * 30), t=t, leader=np.zeros(3), leader_twist=(0.0, 0.0), followers_world=np.zeros((n, 3)),
                  p_est=np.zeros((n, 2)), a_est=np.zeros(n), tracked=np.ones(n, bool), p_true=np.zeros((n, 2)),
                  a_true=np.zeros(n), p_d=np.zeros((n, 2)), slot_targets=np.zeros((n, 2)), assignment=np.arange(n),
                  commands=np.zeros((n, 2)), a_err=np.zeros(n), v_lyap=np.zeros(n), gains=Gains(), params_version=0,
                  stopped=False, paused=False, link_state="serial /dev/x: ok", rate_hz=30.0, latency_ms=20.0)
    return dataclasses.replace(s, **changes)  # type: ignore[arg-type]


def test_each_cause_is_one_alarm_while_it_lasts_and_stays_until_acknowledged() -> None:
    dropped = [0]
    health = Health(30.0, dropped=lambda: dropped[0])
    heard: list[str] = []
    health.listeners.append(lambda _t, text: heard.append(text))
    for k in range(60):  # 28 Hz (below 95 % of 30) for 1.9 s: not yet
        health.check(tick(k / 30, rate_hz=28.0))
    assert heard == []
    for k in range(60, 70):  # past 2 s: one alarm, however many ticks it lasts
        health.check(tick(k / 30, rate_hz=28.0))
    assert len(heard) == 1 and "28.0 Hz" in heard[0]
    health.check(tick(2.4, rate_hz=29.0))  # 29 Hz is above 95 %: the cause ends, the banner keeps it
    assert len(health.alarms) == 1
    health.check(tick(2.5, latency_ms=40.0))  # longer than one period (33 ms), on 3 of the last 30 ticks
    health.check(tick(2.55, latency_ms=40.0))
    health.check(tick(2.6, latency_ms=40.0))
    dropped[0] = 11
    health.check(tick(2.7))
    health.check(tick(2.8, link_detail="F1 rtt 2.0 ms, watchdog; F2 rtt 2.1 ms"))
    health.check(tick(2.9, link_state="link lost (no reply for 1.0 s)"))
    assert [h.split(":")[0].split(" ")[0] for h in heard] == ["loop", "frame", "11", "a", "link"], heard
    assert "F1" in heard[3] and "F2" not in heard[3]
    assert len(health.alarms) == 5
    health.acknowledge()
    assert health.alarms == []
    health.check(tick(3.0, link_state="link lost (no reply for 1.1 s)"))  # the same cause, still on: not again
    assert len(heard) == 5 and health.alarms == []
    health.check(tick(3.1))
    health.check(tick(3.2, link_state="link lost (again)"))  # it came back: a new alarm
    assert len(heard) == 6 and len(health.alarms) == 1


def test_a_tick_by_tick_alarm_must_hold_on_3_of_30_ticks_and_is_one_line_with_its_count() -> None:
    """Frame to command over one period on two ticks of any 30 is no alarm (a busy machine's odd
    tick); on three it is, once while it lasts, and the banner's line for it counts the times in the
    last minute and gives the last value, rewritten in place (never a line more per occurrence)."""
    health = Health(30.0, dropped=lambda: 0)
    heard: list[str] = []
    health.listeners.append(lambda _t, text: heard.append(text))
    for k in range(300):  # ten seconds, a late tick every 20 (two in any 30): no alarm
        health.check(tick(k / 30, latency_ms=90.0 if k % 20 == 0 else 20.0))
    assert heard == [] and health.alarms == []
    for k in range(300, 306):  # three late ticks in a row: one alarm
        health.check(tick(k / 30, latency_ms=94.0 if k < 303 else 20.0))
    assert heard == ["frame to command 94 ms, longer than one period (33 ms)"]
    # the line counts every late tick of the last minute (the 15 that raised nothing, and these 3)
    assert health.alarms == ["frame to command over one period (33 ms): 18 times in the last minute, last 94 ms"]
    for k in range(306, 312):  # late again within the window: still the same alarm, its line updated
        health.check(tick(k / 30, latency_ms=70.0 if k < 308 else 20.0))
    assert len(heard) == 1
    assert health.alarms == ["frame to command over one period (33 ms): 20 times in the last minute, last 70 ms"]
    health.check(tick(100.0))  # a minute on: the line's count forgets what is older
    assert health.alarms == ["frame to command over one period (33 ms): 0 times in the last minute, last 70 ms"]
    health.acknowledge()
    health.check(tick(100.1))
    assert health.alarms == []


def test_the_page_says_what_it_is_and_only_what_it_may_be() -> None:
    assert b'kind: "replay"' in page_head("replay") and b"omni-stopbar" in page_head("replay")
    with pytest.raises(ValueError, match="must be one of live, replay, fleet"):
        page_head("<script>")
