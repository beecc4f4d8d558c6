"""Tests of the excitation signals (mbtsr.excitation)."""

from __future__ import annotations

import math

import numpy as np
import pytest
from hypothesis import given, settings
from hypothesis import strategies as st
from scipy.signal import lfilter

from mbtsr.excitation import (
    filtered_gaussian,
    filtered_gaussian_std,
    multisine,
    multisine_std,
    unit_filtered_gaussian,
)


@pytest.mark.parametrize("T, window", [(1, 1), (5, 100), (50, 52), (400, 100), (300, 5)])
def test_filtered_gaussian_is_a_causal_moving_average_with_zero_initial_state(T, window):
    u = filtered_gaussian(T, 3, window=window, scale=7.0, seed=12)
    white = 7.0 * np.random.default_rng(12).standard_normal((T, 3))
    expected = lfilter(np.ones(window) / window, [1.0], white, axis=0)  # filt(ones(w), [w], e)
    np.testing.assert_allclose(u, expected, rtol=0, atol=1e-12)


@pytest.mark.parametrize("window, scale", [(100, 10.0), (5, 10.0), (20, 3.0)])
def test_filtered_gaussian_steady_state_std_is_scale_over_sqrt_window(window, scale):
    T, m = 200_000, 4
    u = filtered_gaussian(T, m, window=window, scale=scale, seed=0)[window:]
    std = u.std(axis=0).mean()
    expected = filtered_gaussian_std(window, scale)
    assert expected == pytest.approx(scale / math.sqrt(window))
    # sampling error of a variance estimate of an MA(window) process: the autocorrelation
    # rho_k = 1 - k / window gives Var(s^2)/sigma^4 ~ 2 sum_k rho_k^2 / T ~ (4 window / 3) / T;
    # pooled over m channels, std's relative standard error is half the variance's
    rel_se = 0.5 * math.sqrt((4 * window / 3 + 2) / (T * m))
    assert abs(std / expected - 1) < 5 * rel_se
    assert np.all(np.abs(u.mean(axis=0)) < 5 * expected * math.sqrt(2 * window / T))


def test_filtered_gaussian_ramps_up_from_zero_and_the_paper_settings():
    u = filtered_gaussian(300, 2, seed=1)  # the paper's robot input: window 100, scale 10
    white = 10 * np.random.default_rng(1).standard_normal((300, 2))
    # the first window-1 samples average the noise seen so far, divided by the full window
    np.testing.assert_allclose(u[:100], np.cumsum(white, axis=0)[:100] / 100, atol=1e-12)
    assert filtered_gaussian_std(100, 10.0) == pytest.approx(1.0)
    assert filtered_gaussian_std(5, 10.0) == pytest.approx(4.4721, abs=1e-4)


def test_multisine_is_exactly_n_sines_grid_sinusoids_of_the_given_amplitude():
    T, n_sines, amplitude = 4000, 5, 0.7
    u = multisine(T, 2, n_sines=n_sines, amplitude=amplitude, seed=3)
    grid = np.logspace(-3, -1.5, 50)
    t = np.arange(T)[:, None]
    basis = np.hstack([np.sin(2 * np.pi * grid * t), np.cos(2 * np.pi * grid * t)])  # [T, 100]
    coef, *_ = np.linalg.lstsq(basis, u, rcond=None)
    np.testing.assert_allclose(basis @ coef, u, atol=1e-8)  # lies in the span of the grid
    amp = np.hypot(coef[:50], coef[50:])  # [50, 2] amplitude per grid frequency
    for j in range(2):
        active = amp[:, j] > 1e-6
        assert active.sum() == n_sines
        np.testing.assert_allclose(amp[active, j], amplitude, rtol=1e-6)
    assert np.abs(u).max() <= n_sines * amplitude


def test_multisine_std_over_long_windows():
    u = multisine(400_000, 6, n_sines=5, amplitude=1.0, seed=0)
    # distinct frequencies: the time average of sum_i sin^2 -> n_sines / 2; the finite-window
    # error is of order 1 / (T * f_min) = 0.0025
    np.testing.assert_allclose(u.std(axis=0), multisine_std(5, 1.0), rtol=0.02)


def test_same_seed_same_signal_and_generator_seeds_are_accepted():
    for fn in (filtered_gaussian, multisine):
        np.testing.assert_array_equal(fn(50, 2, seed=4), fn(50, 2, seed=4))
        assert not np.array_equal(fn(50, 2, seed=4), fn(50, 2, seed=5))
        np.testing.assert_array_equal(
            fn(50, 2, seed=np.random.default_rng(9)), fn(50, 2, seed=np.random.default_rng(9))
        )


@pytest.mark.parametrize(
    "call, match",
    [
        (lambda: filtered_gaussian(0, 2, seed=0), "T must be"),
        (lambda: filtered_gaussian(10, 0, seed=0), "m must be"),
        (lambda: filtered_gaussian(10, 2, window=0, seed=0), "window"),
        (lambda: filtered_gaussian(10, 2, scale=-1.0, seed=0), "scale"),
        (lambda: filtered_gaussian(10, 2, scale=float("nan"), seed=0), "scale"),
        (lambda: filtered_gaussian(10.5, 2, seed=0), "T must be"),
        (lambda: multisine(10, 2, n_sines=60, seed=0), "n_sines"),
        (lambda: multisine(10, 2, f_max=0.7, seed=0), "f_max"),
        (lambda: multisine(10, 2, f_min=0.0, seed=0), "f_min"),
        (lambda: multisine(10, 2, amplitude=0.0, seed=0), "amplitude"),
    ],
)
def test_bad_arguments_raise_value_error(call, match):
    with pytest.raises(ValueError, match=match):
        call()


@settings(max_examples=40, deadline=None)
@given(
    T=st.integers(1, 300),
    m=st.integers(1, 4),
    window=st.integers(1, 400),
    scale=st.floats(1e-3, 1e3),
    seed=st.integers(0, 2**32 - 1),
)
def test_filtered_gaussian_shapes_finiteness_and_bound(T, m, window, scale, seed):  # noqa: N803
    u = filtered_gaussian(T, m, window=window, scale=scale, seed=seed)
    assert u.shape == (T, m) and u.dtype == np.float64
    assert np.all(np.isfinite(u))
    white = scale * np.random.default_rng(seed).standard_normal((T, m))
    # a moving average never exceeds the largest |sample| of its window
    assert np.all(np.abs(u) <= np.abs(white).max() * (1 + 1e-9))


@settings(max_examples=30, deadline=None)
@given(
    T=st.integers(1, 200),
    m=st.integers(1, 3),
    n_sines=st.integers(1, 10),
    amplitude=st.floats(1e-3, 10.0),
    seed=st.integers(0, 2**32 - 1),
)
def test_multisine_shapes_and_peak_bound(T, m, n_sines, amplitude, seed):  # noqa: N803
    u = multisine(T, m, n_sines=n_sines, amplitude=amplitude, seed=seed)
    assert u.shape == (T, m)
    assert np.all(np.abs(u) <= n_sines * amplitude * (1 + 1e-12))


def test_window_one_is_the_white_noise_itself_and_the_unit_signal_has_unit_std():
    white = np.random.default_rng(11).standard_normal((500, 3))
    np.testing.assert_array_equal(unit_filtered_gaussian(500, 3, window=1, seed=11), white)
    np.testing.assert_array_equal(filtered_gaussian(500, 3, window=1, scale=2.0, seed=11),
                                  2.0 * white)
    u = unit_filtered_gaussian(40000, 2, window=8, seed=3)[8:]  # after the ramp-up
    np.testing.assert_allclose(u.std(0), 1.0, rtol=0.05)
