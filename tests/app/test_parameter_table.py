"""One parameter table (docs/parameters.md): every control on the operator's page and on the
fleet page offers exactly its row's range, which the parameter store takes whole; the bus,
ROS and the viewer may set what the table says and nothing else; the defaults are the table's;
the docs' table is the code's."""

from __future__ import annotations

import dataclasses
import re
from types import SimpleNamespace

import pytest
import viser

from app import wire
from app.dashboard.controls import Controls
from app.dashboard.gate import quietly
from app.fleet.bridge import SETTABLE
from app.params import Params, ParamsStore
from app.dashboard.fleet_view import LeaderPanel
from core.bounds import BUS, OPERATOR, PARAMETERS, ROS, SCENARIO, VIEWER, markdown_table, settable_by
from core.control.safety import SafetySettings
from core.types import Gains
from tests.helpers import ROOT


@pytest.fixture
def server():
    srv = quietly(lambda: viser.ViserServer(host="127.0.0.1", port=0, verbose=False))
    yield srv
    quietly(srv.stop)


def _expected(name: str) -> tuple[float, float, float]:
    """The range the docs give a control: the bound on the step's grid."""
    row = PARAMETERS[name]
    b, step = row.bound, row.step
    return (b.lo if b.lo_inclusive else b.lo + step), b.hi, step


def _page_controls(c: Controls) -> list[tuple[str, object]]:
    """Every number a person enters on the operator's page, with the row it sets."""
    pairs = [("n_followers", c.n_slider), ("leader_speed_mps", c.speed), ("leader_turn_deg_s", c.turn),
             ("goal", c.goal_x), ("goal", c.goal_y), ("min_scale", c.min_scale),
             ("safety_distance_m", c.safety_distance), *c.gains.items()]
    return pairs + [("slot", h) for pair in c.slot_inputs for h in pair]


def _takes(store: ParamsStore, name: str, value: float) -> bool:
    """Whether the store takes ``value`` for row ``name`` unchanged (no notice, no refusal)."""
    change = {"goal": {"goal": (value, 0.0)}, "slot": {"slot": (0, value, 0.0)}}.get(name, {name: value})
    try:
        _, notices = store.update("test", **change)
    except ValueError:
        return False
    return not notices


def _check(store: ParamsStore, name: str, handle) -> None:
    lo, hi, step = _expected(name)
    assert (handle.min, handle.max, handle.step) == pytest.approx((lo, hi, step)), name
    # its ends are values the store takes as they are; a step past either end is not
    assert _takes(store, name, handle.min) and _takes(store, name, handle.max), name
    assert not _takes(store, name, handle.max + step), name
    below = handle.min - step if PARAMETERS[name].bound.lo_inclusive else PARAMETERS[name].bound.lo
    assert not _takes(store, name, below), name


def test_every_control_on_the_page_offers_its_rows_range_and_the_store_takes_it(server):
    store = ParamsStore()
    controls = Controls(server, ParamsStore())
    pairs = _page_controls(controls)
    # no number control on the page is left out of the table's hands
    numbers = [h for h in server.gui._gui_input_handle_from_uuid.values()
               if isinstance(h, (viser.GuiSliderHandle, viser.GuiNumberHandle))]
    assert {id(h) for h in numbers} == {id(h) for _, h in pairs}
    for name, handle in pairs:
        assert OPERATOR in PARAMETERS[name].setters, name
        _check(store, name, handle)
    assert sorted(controls.gains) == sorted(n for n in settable_by(OPERATOR) if PARAMETERS[n].kind == "gain")


def test_every_control_on_the_fleet_page_offers_its_rows_range(server):
    sent = []
    view = SimpleNamespace(server=server, send=lambda leader, changes: sent.append((leader, changes)))
    panel = LeaderPanel(view, "L1", order=10)
    store = ParamsStore()
    for name, handle in (("k_f1", panel.k_f1), ("k_w2", panel.k_w2), ("leader_speed_mps", panel.speed)):
        assert BUS in PARAMETERS[name].setters, name  # what the fleet page sends goes over the bus
        _check(store, name, handle)
    # k_f1's range is one, wherever it is set: the page's, the fleet page's, the bus's, a scenario's
    assert (panel.k_f1.min, panel.k_f1.max) == (0.01, 1.0)


def test_the_bus_ros_and_the_viewer_set_what_the_table_says():
    assert set(SETTABLE) == {n for n, r in PARAMETERS.items() if BUS in r.setters}
    assert settable_by(VIEWER) == ("stop",)  # a view-only client can only stop (docs/page-access.md)
    assert set(settable_by(ROS)) == {"stop", "goal", "leader_mode"}  # /omniformation/stop and /goal
    for name in SETTABLE:  # every value the bus may carry has a type the bus's reader knows
        row = PARAMETERS[name]
        value = {"flag": True, "choice": "stop", "point": [0.5, 0.5], "slots": [[0.5, -0.3]]}.get(row.kind, 0.1)
        wire.setting(name, value)
    store = ParamsStore()
    before = store.get()
    with pytest.raises(ValueError, match=r"k_f1: cannot be set from the ros \(allowed: leader_mode, goal, stop\)"):
        store.update_from(ROS, "ros2:/omniformation/goal", goal=(1.0, 1.0), k_f1=0.2)
    with pytest.raises(ValueError, match="n_followers: cannot be set from the bus"):
        store.update_from(BUS, "fleet:page", n_followers=3)
    assert store.get() is before  # a refused change changes nothing, not even its allowed part
    p, _ = store.update_from(ROS, "ros2:/omniformation/stop", stop=True)
    assert p.stop


def test_the_defaults_are_the_tables():
    p, g = Params(), Gains()
    for name, row in PARAMETERS.items():
        if row.kind == "gain":
            assert getattr(g, name) == row.default, name
        elif row.kind == "slots":
            assert p.slots.tolist() == [list(r) for r in row.default]
        elif row.kind != "slot":
            assert getattr(p, name) == row.default, name
    assert SafetySettings().min_distance_m == PARAMETERS["safety_distance_m"].default
    for row in PARAMETERS.values():  # every number's default is within its own bound
        if row.kind in ("gain", "number", "count"):
            assert row.bound.lo <= row.default <= row.bound.hi, row.name
    assert {f.name for f in dataclasses.fields(Gains)} == {n for n, r in PARAMETERS.items() if r.kind == "gain"}
    assert all(SCENARIO in r.setters for r in PARAMETERS.values() if r.kind == "gain")


def test_the_docs_table_is_the_codes():
    text = (ROOT / "docs" / "parameters.md").read_text(encoding="utf-8")
    m = re.search(r"<!-- generated: core.bounds.markdown_table\(\) -->\n(.*)<!-- end of the generated table -->",
                  text, re.S)
    assert m is not None and m.group(1) == markdown_table(), "docs/parameters.md: paste core.bounds.markdown_table()"
    assert all(f"| `{name}` |" in m.group(1) for name in PARAMETERS)
