import numpy as np
from hypothesis import given, settings
from hypothesis import strategies as st
from numpy.testing import assert_allclose

from core.control.targets import SlotMotion, step_slots

coord = st.floats(-2.0, 2.0)


@settings(max_examples=25, deadline=None)
@given(coord, coord, coord, coord, st.floats(0.02, 0.3), st.floats(0.02, 0.5))
def test_slot_ramp_respects_speed_and_acceleration_and_arrives(x0, y0, x1, y1, vmax, amax):
    dt = 0.02
    motion = SlotMotion.at_rest([[x0, y0]])
    target = np.array([[x1, y1]])
    prev_v = motion.v_d.copy()
    travel_s = np.hypot(x1 - x0, y1 - y0) / vmax + 2 * vmax / amax + 1.0
    for _ in range(int(travel_s / dt)):
        motion = step_slots(motion, target, dt, vmax, amax)
        speed = np.hypot(*motion.v_d[0])
        assert speed <= vmax + 1e-9
        assert np.hypot(*(motion.v_d[0] - prev_v[0])) <= amax * dt + 1e-9
        prev_v = motion.v_d.copy()
    assert_allclose(motion.p_d, target, atol=1e-3)
    assert np.hypot(*motion.v_d[0]) < 2 * amax * dt


def test_desired_position_moves_continuously():
    motion = SlotMotion.at_rest([[0.0, 0.0]])
    jumps = []
    for _ in range(200):
        new = step_slots(motion, [[1.0, 0.0]], 0.05)
        jumps.append(np.hypot(*(new.p_d[0] - motion.p_d[0])))
        motion = new
    assert max(jumps) <= 0.10 * 0.05 + 1e-12
