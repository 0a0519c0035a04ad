"""The study bench's scaling model: what docs/studies.md's table of 8, 64 and 512 workers is made by."""

from __future__ import annotations

import pytest

from app.cli.bench.study import scaling_model


def test_workers_add_up_until_the_client_writing_parts_is_the_limit() -> None:
    # vision-like runs of 0.5 s in batches of 1 s: two runs a batch, 10 ms per task, 20 ms per part
    one = scaling_model(0.5, 0.01, 0.02, 1.0, 1)
    assert one == pytest.approx(2 / 1.01)
    assert scaling_model(0.5, 0.01, 0.02, 1.0, 8) == pytest.approx(8 * one)
    central = 2 / (0.02 + 1e-3)  # the client writes one part per batch, the scheduler handles it
    assert scaling_model(0.5, 0.01, 0.02, 1.0, 512) == pytest.approx(central)
    # truth-like runs of 2 ms: 500 runs a batch; more workers never slow the study down
    rates = [scaling_model(0.002, 0.01, 0.02, 1.0, n) for n in (1, 8, 64, 512)]
    assert rates == sorted(rates) and rates[0] == pytest.approx(500 / 1.01)
