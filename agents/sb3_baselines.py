"""Stable-Baselines3 model-free baselines (SAC, TD3, PPO) on exactly the agent's task, for the
suite's SAC rows (``scripts/bench_suite.py --sb3 sac``): the same env id and keyword arguments
(hence episode length and reward), the same evaluation episodes through the same function
(:func:`agents.evaluation.evaluate_policy_cost`, deterministic policy) every ``eval_every`` env
steps (:class:`CostEvalCallback`). Hyperparameters: :func:`default_hyperparams`. Wall time is
counted without the evaluations (the total including them is reported beside it).
"""

from __future__ import annotations

import functools
import time
from collections.abc import Callable, Sequence
from typing import Any

import gymnasium as gym
import numpy as np
from stable_baselines3 import PPO, SAC, TD3
from stable_baselines3.common.base_class import BaseAlgorithm
from stable_baselines3.common.callbacks import BaseCallback
from stable_baselines3.common.monitor import Monitor
from stable_baselines3.common.noise import NormalActionNoise
from stable_baselines3.common.vec_env import DummyVecEnv, VecEnv, VecNormalize

from mbtsr.validation import as_array, check_int, check_positive

__all__ = [
    "ALGOS",
    "CostEvalCallback",
    "default_hyperparams",
    "make_sb3_model",
    "train_sb3",
]

ALGOS: dict[str, type[BaseAlgorithm]] = {"sac": SAC, "td3": TD3, "ppo": PPO}


def default_hyperparams(algo: str) -> dict[str, Any]:
    """The hyperparameters the benchmark uses for ``algo`` (JSON-serializable): SB3's defaults
    with the rl-baselines3-zoo MuJoCo changes that are not about the budget: TD3 explores with
    Gaussian action noise of std 0.1 (``action_noise_std``; SB3's TD3 has none) and PPO
    normalizes observations and rewards (``normalize``: ``VecNormalize``). The zoo's
    ``learning_starts=10000`` (SAC, TD3) is not used: it would put a floor of 10,000 random steps
    under "steps to solve" that says nothing about learning and flatter the model-based agent.
    """
    _check_algo(algo)
    return {"td3": {"action_noise_std": 0.1}, "ppo": {"normalize": True}}.get(algo, {})


def make_sb3_model(
    algo: str,
    env: gym.Env | VecEnv,
    seed: int,
    hyperparams: dict[str, Any] | None = None,
) -> BaseAlgorithm:
    """Build an SB3 model with an ``MlpPolicy`` on ``env`` (CPU, seeded).

    :param hyperparams: keyword arguments of the SB3 class, plus two keys of this module:
        ``action_noise_std`` (sac/td3) adds ``NormalActionNoise`` with that std on every action
        dimension; ``normalize`` is consumed by :func:`train_sb3` and ignored here.
        ``None``: :func:`default_hyperparams`.
    """
    _check_algo(algo)
    kwargs = dict(default_hyperparams(algo) if hyperparams is None else hyperparams)
    kwargs.pop("normalize", None)
    noise_std = kwargs.pop("action_noise_std", None)
    if noise_std is not None:
        if algo == "ppo":
            raise ValueError("hyperparams: action_noise_std is for sac/td3, not ppo")
        check_positive("hyperparams['action_noise_std']", noise_std)
        m = env.action_space.shape[0]
        kwargs["action_noise"] = NormalActionNoise(np.zeros(m), float(noise_std) * np.ones(m))
    try:
        return ALGOS[algo](
            "MlpPolicy", env, seed=int(seed), device="cpu", verbose=0, **kwargs,
        )
    except TypeError as err:
        raise ValueError(f"hyperparams for {algo} are not accepted by SB3: {err}") from None


class CostEvalCallback(BaseCallback):
    """Evaluate the deterministic policy every ``eval_every`` env steps, at the start of a
    rollout (after the gradient updates on all data so far), at step 0 and at the end: the mean
    episode cost ``score(act)`` of ``act``, the policy on a raw observation (a
    ``VecNormalize``-d policy sees its running statistics' normalization).

    After training: ``curve`` ``[(env_steps, eval_cost), ...]``; ``train_wall``, wall seconds
    since ``t_start`` without the evaluations, per curve point; ``eval_seconds`` in total.

    :param score: ``score(act: obs [d] -> action) -> float``, the cost on the evaluation
        episodes (:func:`agents.evaluation.evaluate_policy_cost`).
    :param eval_every: evaluation period in env steps.
    :param t_start: ``time.perf_counter()`` value that wall times are measured from.
    """

    def __init__(self, score: Callable[[Callable], float], eval_every: int,
                 t_start: float) -> None:
        super().__init__()
        self.score, self.eval_every, self.t_start = score, int(eval_every), t_start
        self.curve: list[tuple[int, float]] = []
        self.train_wall: list[float] = []
        self.eval_seconds = 0.0
        self._next_eval = 0

    def policy_action(self, obs: np.ndarray) -> np.ndarray:
        """The deterministic action of the current policy for one raw observation ``obs: [d]``
        (normalized first if the training env is a ``VecNormalize``)."""
        vec_normalize = self.model.get_vec_normalize_env()
        if vec_normalize is not None:
            obs = vec_normalize.normalize_obs(np.asarray(obs))
        action, _ = self.model.predict(obs, deterministic=True)
        return action

    def evaluate_now(self) -> None:
        """Evaluate at the current step (once per step)."""
        if self.curve and self.curve[-1][0] == self.num_timesteps:
            return
        t0 = time.perf_counter()
        train_wall = t0 - self.t_start - self.eval_seconds
        cost = self.score(self.policy_action)
        self.eval_seconds += time.perf_counter() - t0
        self.curve.append((int(self.num_timesteps), cost))
        self.train_wall.append(train_wall)

    def _on_training_start(self) -> None:
        self._maybe_evaluate()

    def _on_rollout_start(self) -> None:
        self.num_timesteps = self.model.num_timesteps
        self._maybe_evaluate()

    def _maybe_evaluate(self) -> None:
        if self.num_timesteps >= self._next_eval:
            self.evaluate_now()
            while self._next_eval <= self.num_timesteps:
                self._next_eval += self.eval_every

    def _on_step(self) -> bool:
        return True

    def _on_training_end(self) -> None:
        self.num_timesteps = self.model.num_timesteps
        self.evaluate_now()


def train_sb3(
    algo: str,
    env_id: str,
    budget_steps: int,
    seed: int,
    eval_every: int,
    eval_targets: np.ndarray | Sequence[Sequence[float]] | None,
    hyperparams: dict[str, Any] | None = None,
    *,
    env_kwargs: dict[str, Any] | None = None,
    eval_seed: int = 0,
    return_model: bool = False,
    n_eval_episodes: int | None = None,
    eval_max_steps: int | None = None,
) -> dict[str, Any]:
    """Train an SB3 agent on ``env_id`` for ``budget_steps``, evaluated along the way; return
    its record.

    :param algo: ``"sac"``, ``"td3"`` or ``"ppo"``.
    :param env_id: registered Gymnasium id, e.g. ``"mbtsr/TwoLinkArm-v0"``.
    :param budget_steps: env steps (PPO rounds up to whole rollouts of ``n_steps``).
    :param seed: seed of the SB3 model and of the training env's resets.
    :param eval_every: evaluation period in env steps.
    :param eval_targets: ``[k, 2]`` fixed evaluation targets (the agent's), or ``None`` for an
        env without targets: then ``n_eval_episodes`` episodes, scored by the env's own return.
    :param hyperparams: SB3 keyword arguments (see :func:`make_sb3_model`); ``None``: the
        documented :func:`default_hyperparams`.
    :param env_kwargs: keyword arguments of ``gym.make`` (e.g. ``{"preset": "default"}``), used
        for both the training and the evaluation env.
    :param eval_seed: evaluation episode ``i`` resets with ``eval_seed + i``.
    :param return_model: also return the trained model under ``"model"`` (not serializable;
        for tests and notebooks).
    :param n_eval_episodes: evaluation episodes when ``eval_targets`` is ``None`` (>= 1).
    :param eval_max_steps: cap on the steps of an evaluation episode (``None``: the env's own
        limit).
    :return: a JSON-serializable dict: ``curve`` ``[[env_steps, eval_cost], ...]`` (the cost is
        minus the mean return), ``curve_train_wall`` (seconds, excl. evaluation, per curve
        point), ``env_steps`` (total), ``train_wall_seconds`` / ``eval_wall_seconds`` /
        ``total_wall_seconds``, ``hyperparams`` and the arguments.
    """
    from agents.evaluation import evaluate_policy_cost

    _check_algo(algo)
    budget_steps = check_int("budget_steps", budget_steps, 1)
    eval_every = check_int("eval_every", eval_every, 1)
    seed = check_int("seed", seed, 0)
    eval_seed = check_int("eval_seed", eval_seed, 0)
    if eval_max_steps is not None:
        eval_max_steps = check_int("eval_max_steps", eval_max_steps, 1)
    if eval_targets is None:
        if n_eval_episodes is None:
            raise ValueError("give eval_targets or n_eval_episodes")
        n_eval_episodes = check_int("n_eval_episodes", n_eval_episodes, 1)
        targets = None
    else:
        if n_eval_episodes is not None:
            raise ValueError("n_eval_episodes is for eval_targets=None; with targets there is "
                             "one episode per target")
        targets = as_array("eval_targets", eval_targets, (None, None))
        if targets.shape[0] < 1:
            raise ValueError("eval_targets must hold at least one target, got shape [0, *]")
        n_eval_episodes = int(targets.shape[0])
    if hyperparams is not None and not isinstance(hyperparams, dict):
        raise ValueError(f"hyperparams must be a dict or None, got {type(hyperparams).__name__}")
    hp = dict(default_hyperparams(algo) if hyperparams is None else hyperparams)
    env_kwargs = dict(env_kwargs or {})

    t_start = time.perf_counter()
    # one Monitor-ed env in a DummyVecEnv (faster than subprocesses on 2 cores), normalized
    # (observations and rewards) with hyperparams["normalize"]
    train_env: VecEnv = DummyVecEnv([lambda: Monitor(gym.make(env_id, **env_kwargs))])
    if hp.get("normalize", False):
        train_env = VecNormalize(train_env, norm_obs=True, norm_reward=True,
                                 gamma=float(hp.get("gamma", 0.99)))
    eval_env = gym.make(env_id, **env_kwargs)
    try:
        model = make_sb3_model(algo, train_env, seed, hp)
        callback = CostEvalCallback(functools.partial(
            evaluate_policy_cost, env=eval_env, targets=targets, seed=eval_seed,
            n_episodes=n_eval_episodes, max_steps=eval_max_steps), eval_every, t_start)
        model.learn(total_timesteps=budget_steps, callback=callback)
        total = time.perf_counter() - t_start
    finally:
        train_env.close()
        eval_env.close()
    record = {
        "algo": algo,
        "env_id": env_id,
        "env_kwargs": env_kwargs,
        "seed": seed,
        "budget_steps": budget_steps,
        "eval_every": eval_every,
        "eval_seed": eval_seed,
        "n_eval_targets": 0 if targets is None else n_eval_episodes,
        "n_eval_episodes": n_eval_episodes,
        "hyperparams": hp,
        "curve": [[s, c] for s, c in callback.curve],
        "curve_train_wall": callback.train_wall,
        "env_steps": int(model.num_timesteps),
        "train_wall_seconds": total - callback.eval_seconds,
        "eval_wall_seconds": callback.eval_seconds,
        "total_wall_seconds": total,
    }
    if return_model:
        record["model"] = model
    return record


def _check_algo(algo: str) -> None:
    if algo not in ALGOS:
        raise ValueError(f"algo must be one of {sorted(ALGOS)}, got {algo!r}")
