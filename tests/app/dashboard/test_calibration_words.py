"""The calibration page's words: a sector named as the guide names bearings (0-360°), and
"1 marker", not "1 markers"."""

from app.dashboard.calibration_panel import guide_deg, count_markers


def test_sectors_are_named_as_the_guide_names_bearings():
    assert [guide_deg(b) for b in (-180.0, -90.0, 0.0, 45.0, 90.0, 179.9)] == [180.0, 270.0, 0.0, 45.0, 90.0, 179.9]
    assert guide_deg(-1e-12) == 0.0  # not 360


def test_one_marker_is_one_marker():
    assert [count_markers(n) for n in (0, 1, 2)] == ["0 markers", "1 marker", "2 markers"]


def test_before_the_fit_the_page_says_how_many_each_bearing_has_and_needs():
    from app.dashboard.calibration_panel import DEGREE, CalibrationPanel

    panel = CalibrationPanel.__new__(CalibrationPanel)  # the wording alone (no page needed)
    panel.rows = [(0.0, 0.5, 1.0, 2.0), (0.0, 0.8, 1.0, 2.0), (270.0, 0.5, 1.0, 2.0)]
    need = DEGREE + 2
    assert panel._per_bearing() == f"so far 0°: 2/{need}, 270°: 1/{need}"
    panel.rows = []
    assert panel._per_bearing() == "none captured yet"
