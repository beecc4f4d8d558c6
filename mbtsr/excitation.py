"""Excitation input signals for system identification (pure numpy): :func:`filtered_gaussian`
and :func:`multisine`, time-major ``[T, m]``, bit for bit the same for the same keyword
``seed`` (docs/environments.md, "Excitation signals").
"""

from __future__ import annotations

import math

import numpy as np

from mbtsr.validation import check_int, check_positive

__all__ = ["filtered_gaussian", "multisine", "filtered_gaussian_std", "multisine_std",
           "unit_filtered_gaussian"]

SeedLike = int | np.random.SeedSequence | np.random.Generator


def filtered_gaussian_std(window: int, scale: float) -> float:
    """Steady-state std of :func:`filtered_gaussian`: ``scale / sqrt(window)``."""
    return scale / math.sqrt(window)


def filtered_gaussian(
    T: int,  # noqa: N803 - the paper's symbol
    m: int,
    *,
    window: int = 100,
    scale: float = 10.0,
    seed: SeedLike,
) -> np.ndarray:
    """Low-pass filtered Gaussian input: ``u[t] = (1 / window) sum_{k<window} e[t - k]``,
    ``e ~ scale * N(0, I_m)``, zero initial filter state; stationary std
    :func:`filtered_gaussian_std` after ``window - 1`` samples.

    :param T: number of samples (>= 1).
    :param m: number of input channels (>= 1).
    :param window: moving-average length in samples (>= 1).
    :param scale: std of the white noise before averaging (> 0).
    :param seed: int, ``SeedSequence`` or ``Generator``.
    :return: ``u: [T, m]``.
    """
    T, m = check_int("T", T, 1), check_int("m", m, 1)  # noqa: N806
    window = check_int("window", window, 1)
    scale = check_positive("scale", scale)
    rng = np.random.default_rng(seed)
    white = scale * rng.standard_normal((T, m))
    if window == 1:
        return white  # the moving average of one sample is the sample itself (exactly)
    # causal moving average with zero initial state: differences of a cumulative sum
    csum = np.cumsum(np.vstack([np.zeros((1, m)), white]), axis=0)  # csum[k] = sum_{i<k} e[i]
    start = np.maximum(np.arange(T) + 1 - window, 0)
    return (csum[1:] - csum[start]) / window


def unit_filtered_gaussian(T: int, m: int, *, window: int, seed: SeedLike) -> np.ndarray:  # noqa: N803
    """:func:`filtered_gaussian` scaled to a unit stationary std (``window=1``: white N(0, 1)).

    :return: ``u: [T, m]``.
    """
    return (filtered_gaussian(T, m, window=window, scale=1.0, seed=seed)
            / filtered_gaussian_std(window, 1.0))


def multisine_std(n_sines: int, amplitude: float) -> float:
    """Std of :func:`multisine` over long windows: ``amplitude * sqrt(n_sines / 2)``."""
    return amplitude * math.sqrt(n_sines / 2)


def multisine(
    T: int,  # noqa: N803 - the paper's symbol
    m: int,
    *,
    n_sines: int = 5,
    f_min: float = 1e-3,
    f_max: float = 10**-1.5,
    n_grid: int = 50,
    amplitude: float = 1.0,
    seed: SeedLike,
) -> np.ndarray:
    """``u[t, j] = amplitude * sum_i sin(2 pi f_ij t + phi_ij)``, per channel ``n_sines``
    frequencies drawn without replacement from a log-spaced grid and phases ``U[0, 2 pi)``;
    std :func:`multisine_std`, peak at most ``n_sines * amplitude``.

    :param T: number of samples (>= 1).
    :param m: number of input channels (>= 1).
    :param n_sines: sinusoids per channel, ``1 <= n_sines <= n_grid``.
    :param f_min: lowest grid frequency, cycles/sample (> 0).
    :param f_max: highest grid frequency, cycles/sample, ``f_min <= f_max <= 0.5`` (Nyquist).
    :param n_grid: number of grid frequencies.
    :param amplitude: amplitude of each sinusoid (> 0).
    :param seed: int, ``SeedSequence`` or ``Generator``.
    :return: ``u: [T, m]``.
    """
    T, m = check_int("T", T, 1), check_int("m", m, 1)  # noqa: N806
    n_grid = check_int("n_grid", n_grid, 1)
    n_sines = check_int("n_sines", n_sines, 1)
    if n_sines > n_grid:
        raise ValueError(f"n_sines must be <= n_grid={n_grid}, got {n_sines}")
    f_min, f_max = check_positive("f_min", f_min), check_positive("f_max", f_max)
    if not f_min <= f_max <= 0.5:
        raise ValueError(f"need 0 < f_min <= f_max <= 0.5, got f_min={f_min}, f_max={f_max}")
    amplitude = check_positive("amplitude", amplitude)
    rng = np.random.default_rng(seed)
    grid = np.logspace(math.log10(f_min), math.log10(f_max), n_grid)
    freqs = np.stack([rng.choice(grid, size=n_sines, replace=False) for _ in range(m)])  # [m, k]
    phases = rng.uniform(0.0, 2 * math.pi, size=(m, n_sines))
    t = np.arange(T, dtype=np.float64)[:, None, None]  # [T, 1, 1]
    return amplitude * np.sin(2 * math.pi * freqs[None] * t + phases[None]).sum(axis=2)
