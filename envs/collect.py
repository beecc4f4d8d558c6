"""Collect open-loop excitation trajectories from a Gymnasium env.

``collect_trajectories`` drives the env open-loop with an excitation signal (:mod:`mbtsr.excitation`
or your own) and records ``Trajectory(x [T+1, n], u [T, m])``; same ``seed``, bit-identical
trajectories. The manual: docs/environments.md, "Data collection".
"""

from __future__ import annotations

import math
from collections.abc import Callable, Mapping

import gymnasium as gym
import numpy as np

from mbtsr.episode import run_episode
from mbtsr.excitation import filtered_gaussian, multisine
from mbtsr.trajectory import Trajectory
from mbtsr.validation import as_array, check_int, check_positive

__all__ = ["collect_trajectories", "default_input_kwargs", "rollout_open_loop"]

InputFn = Callable[..., np.ndarray]
#: the built-in signals with the signature of an ``input`` callable, ``(T, m, rng, **kwargs)``
_BUILTIN: dict[str, InputFn] = {
    name: (lambda T, m, rng, _f=f, **kw: _f(T, m, seed=rng, **kw))  # noqa: N803
    for name, f in (("filtered_gaussian", filtered_gaussian), ("multisine", multisine))}


def default_input_kwargs(env: gym.Env, input: str) -> dict:  # noqa: A002 - the public name
    """Default excitation settings for ``env``: the env's ``excitation_kwargs[input]``, else
    the built-in signal scaled to the env's ``excitation_std`` (docs/environments.md, "Data
    collection"), else ``{}`` (the signal's own defaults)."""
    base = env.unwrapped
    own = getattr(base, "excitation_kwargs", None)
    if isinstance(own, Mapping) and input in own:
        return dict(own[input])
    std = getattr(base, "excitation_std", None)
    if std is None:
        return {}
    if input == "filtered_gaussian":
        return {"window": 100, "scale": float(std) * math.sqrt(100)}
    if input == "multisine":
        return {"n_sines": 5, "amplitude": float(std) / math.sqrt(5 / 2)}
    return {}


def rollout_open_loop(
    env: gym.Env,
    u: np.ndarray,
    *,
    seed: int | None = None,
    reset_options: Mapping | None = None,
    abort: Callable[[np.ndarray], bool] | None = None,
) -> tuple[np.ndarray, np.ndarray, dict] | None:
    """Reset ``env`` and apply ``u: [T, m]`` (clipped into the action space) open loop, through
    the one rollout loop :func:`mbtsr.episode.run_episode`.

    :param abort: called with each new state; a true result stops the rollout early.
    :return: ``(x [T+1, n], u_applied [T, m], reset_info)``, or ``None`` if aborted.
    :raises ValueError: if the env terminates or truncates before ``T`` steps.
    """
    u = as_array("u", u, (None, int(np.prod(env.action_space.shape))))
    T = u.shape[0]
    rec = run_episode(
        env, lambda x, t: u[t], seed=seed, max_steps=T, stop=abort,
        observe=lambda obs, info: np.array(info.get("state", obs), dtype=np.float64).ravel(),
        options=dict(reset_options) if reset_options else None,
    )
    if rec.stopped:
        return None
    if rec.info.get("unstable"):
        raise ValueError(f"the simulation became unstable during the open-loop rollout: "
                         f"{rec.info.get('instability', '')}")
    if rec.T < T:
        raise ValueError(f"the env ended the episode after {rec.T} steps but T={T} were "
                         "requested; make the env with a longer episode (e.g. episode_steps=T)")
    x = rec.states if rec.states is not None else rec.obs
    return np.asarray(x, dtype=np.float64).reshape(T + 1, -1), rec.actions, rec.info0


def collect_trajectories(
    env: gym.Env,
    n_traj: int,
    T: int,  # noqa: N803 - the paper's symbol
    *,
    input: str | InputFn = "filtered_gaussian",  # noqa: A002 - the public name
    input_kwargs: Mapping | None = None,
    seed: int = 0,
    reject_abs_q: float | None = None,
    max_attempts: int | None = None,
    reset_options: Mapping | None = None,
) -> list[Trajectory]:
    """Collect ``n_traj`` open-loop excitation trajectories of ``T`` steps.

    :param env: a Gymnasium env (made with ``gymnasium.make`` or bare); episodes must last at
        least ``T`` steps (for the arm: ``episode_steps >= T``).
    :param n_traj: number of trajectories to return (>= 1).
    :param T: transitions per trajectory (>= 1).
    :param input: ``"filtered_gaussian"``, ``"multisine"`` or a callable
        ``input(T, m, rng, **input_kwargs) -> [T, m]`` with ``rng`` a ``numpy.random.Generator``.
    :param input_kwargs: keyword arguments of the input; ``None`` uses
        :func:`default_input_kwargs` (scaled to the env's ``excitation_std``).
    :param seed: master seed; same seed, same trajectories (bit for bit).
    :param reject_abs_q: if set, redraw trajectories in which any joint angle (the first
        ``model.nq`` state entries of a MuJoCo env) reaches ``|q| >= reject_abs_q`` (the paper:
        ``0.9 * pi``).
    :param max_attempts: give up (``RuntimeError``) after this many rollouts; default
        ``20 * n_traj``.
    :param reset_options: passed to ``env.reset(options=...)`` (e.g. ``{"state": x0}``).
    :return: list of :class:`~mbtsr.trajectory.Trajectory` with ``dt`` set from the env and
        ``meta = {"reset_seed", "input_seed", "attempt", "target"?, "input"}``.
    """
    check_int("n_traj", n_traj, 1)
    check_int("T", T, 1)
    if not isinstance(env.action_space, gym.spaces.Box) or len(env.action_space.shape) != 1:
        raise ValueError(f"env.action_space must be a 1-D Box, got {env.action_space}")
    base = env.unwrapped
    episode_steps = getattr(base, "episode_steps", None)
    if episode_steps is not None and episode_steps < T:
        raise ValueError(
            f"T={T} exceeds the env's episode_steps={episode_steps}; make the env with "
            f"episode_steps >= {T}"
        )
    m = env.action_space.shape[0]
    if isinstance(input, str) and input in _BUILTIN:
        kwargs = default_input_kwargs(env, input) if input_kwargs is None else dict(input_kwargs)
        signal, input_name = _BUILTIN[input], input
    elif callable(input):
        kwargs, signal = dict(input_kwargs or {}), input
        input_name = getattr(input, "__name__", "callable")
    else:
        raise ValueError(f"input must be one of {sorted(_BUILTIN)} or a callable, got {input!r}")

    abort = None
    if reject_abs_q is not None:
        limit = check_positive("reject_abs_q", reject_abs_q)
        model = getattr(base, "model", None)
        if model is None or not hasattr(model, "nq"):
            raise ValueError(
                "reject_abs_q needs a MuJoCo env (joint angles = first model.nq states)"
            )
        nq = int(model.nq)

        def abort(x: np.ndarray) -> bool:
            return bool(np.any(np.abs(x[:nq]) >= limit))

    max_attempts = 20 * n_traj if max_attempts is None else int(max_attempts)
    if max_attempts < n_traj:
        raise ValueError(f"max_attempts must be >= n_traj={n_traj}, got {max_attempts}")
    dt = getattr(base, "dt", None)
    master = np.random.default_rng(seed)
    trajs: list[Trajectory] = []
    for attempt in range(max_attempts):
        reset_seed, input_seed = (int(s) for s in master.integers(0, 2**31 - 1, size=2))
        u = np.asarray(signal(T, m, np.random.default_rng(input_seed), **kwargs), dtype=np.float64)
        if u.shape != (T, m):
            raise ValueError(f"input must return shape ({T}, {m}), got {u.shape}")
        if not np.all(np.isfinite(u)):
            raise ValueError("input returned non-finite values")
        result = rollout_open_loop(
            env, u, seed=reset_seed, reset_options=reset_options, abort=abort
        )
        if result is None:
            continue
        x, u_applied, info = result
        meta = {
            "reset_seed": reset_seed,
            "input_seed": input_seed,
            "attempt": attempt,
            "input": input_name,
            "seed": seed,
        }
        if "target" in info:
            meta["target"] = np.asarray(info["target"]).tolist()
        trajs.append(Trajectory(x, u_applied, dt=None if dt is None else float(dt), meta=meta))
        if len(trajs) == n_traj:
            return trajs
    raise RuntimeError(
        f"only {len(trajs)} of {n_traj} trajectories stayed within |q| < {reject_abs_q} in "
        f"{max_attempts} attempts; lower the input scale or raise max_attempts"
    )
