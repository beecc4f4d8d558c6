"""Shared by the SB3 tests: small training settings, scripted resets, and SB3's own return of a
trained model (the independent computation the benchmarks' evaluation is checked against)."""

from __future__ import annotations

import gymnasium as gym
import numpy as np
from stable_baselines3.common.evaluation import evaluate_policy
from stable_baselines3.common.monitor import Monitor
from stable_baselines3.common.vec_env import DummyVecEnv, VecNormalize

#: (algo, budget, eval_every, hyperparams): a few hundred steps of SAC (raw observations) and PPO
#: (VecNormalize), enough to move the policy away from its initialisation
SMALL_RUNS = [
    ("sac", 200, 100, {"learning_starts": 50, "batch_size": 32}),
    ("ppo", 128, 64, {"n_steps": 64, "batch_size": 32, "n_epochs": 2, "normalize": True}),
]


class ScriptedResets(gym.Wrapper):
    """Reset ``i`` uses ``seed + i`` (and ``targets[i]`` when given), whatever the caller asks
    for, so that SB3's ``evaluate_policy``, which resets on its own, plays the benchmark's
    episodes."""

    def __init__(self, env, seed, targets=None):
        super().__init__(env)
        self.targets, self.seed0, self.i = targets, seed, 0

    def reset(self, *, seed=None, options=None):
        if self.targets is None:
            self.i += 1
            return self.env.reset(seed=self.seed0 + self.i - 1)
        k = self.i % len(self.targets)
        self.i += 1
        return self.env.reset(seed=self.seed0 + k, options={"target": self.targets[k]})


def sb3_returns(model, env: gym.Env, n_episodes: int, normalize: bool):
    """SB3's ``evaluate_policy`` returns and lengths of the deterministic ``model`` on ``env``
    (with the model's own observation normalization when it trained with ``VecNormalize``)."""
    venv = DummyVecEnv([lambda: Monitor(env)])
    train_norm = model.get_vec_normalize_env()
    assert (train_norm is not None) == normalize
    if normalize:
        venv = VecNormalize(venv, training=False, norm_reward=False)
        venv.obs_rms = train_norm.obs_rms
    returns, lengths = evaluate_policy(model, venv, n_eval_episodes=n_episodes,
                                       deterministic=True, return_episode_rewards=True)
    return np.asarray(returns), lengths
