"""The transfer table's bootstrap interval of a ratio of means (benchmarks/sim2sim.py)."""

import numpy as np
import pytest

from benchmarks.sim2sim import ratio_interval


def test_constant_samples_give_the_exact_ratio():
    assert ratio_interval(np.full(5, 3.0), np.full(7, 1.5)) == (2.0, 2.0)


def test_interval_holds_the_point_ratio_and_narrows_with_episodes():
    rng = np.random.default_rng(1)
    few = ratio_interval(rng.exponential(20.0, 32), rng.exponential(20.0, 32))
    many = ratio_interval(rng.exponential(20.0, 2048), rng.exponential(20.0, 2048))
    assert few[0] < 1.0 < few[1] and many[0] < 1.0 < many[1]
    assert many[1] - many[0] < 0.25 * (few[1] - few[0])


def test_heavy_tail_of_32_episodes_spans_a_factor_of_two():
    # Circle-like costs: mostly 0, a few escapes of ~260 steps each; same law on both sides.
    rng = np.random.default_rng(0)
    sample = lambda: np.where(rng.random(32) < 0.1, 260.0, 0.0)
    lo, hi = ratio_interval(sample(), sample())
    assert hi / lo > 2.0


def test_zero_denominator_resamples_end_at_inf():
    lo, hi = ratio_interval(np.ones(4), np.array([0.0, 0.0, 0.0, 1.0]))
    assert hi == np.inf and lo > 0


def test_empty_sample_is_an_error():
    with pytest.raises(ValueError, match="at least one episode"):
        ratio_interval(np.array([]), np.ones(3))
