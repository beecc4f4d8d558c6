"""AgentConfig composes the library's own configs (EnsembleConfig, TrainConfig,
RegularizationConfig) in one place; the agent uses exactly those."""

from __future__ import annotations

import gymnasium as gym
import pytest

import envs  # noqa: F401  (registers mbtsr/TwoLinkArm-v0)
from agents.config import AgentConfig
from agents.jacprop_agent import JacPropAgent
from mbtsr.ensemble import EnsembleConfig, MemberSpec
from mbtsr.training import RegularizationConfig, TrainConfig


@pytest.mark.parametrize("reg, expect", [
    ("sampled", {"sampled_weight": 0.7}),
    ("exact", {"exact_weight": 0.05}),
    ("smooth", {"smooth_weight": 0.05}),
    ("none", {}),
])
def test_regularization_config_per_method(reg, expect):
    cfg = AgentConfig(regularization=reg, jacprop_weight=0.7, jacobian_penalty=0.05,
                      perturbation_sigma=0.2, n_perturbed_copies=3)
    assert cfg.regularization_config() == RegularizationConfig(sigma=0.2, n_copies=3, **expect)


def test_train_and_ensemble_configs():
    cfg = AgentConfig(epochs_per_episode=7, lr=1e-3, batch_size=0, weight_decay=1e-4, seed=5,
                      ensemble_size=3, hidden_width=9, hidden_layers=2,
                      activations=("tanh", "elu"), formulation="f")
    assert cfg.train_config(seed=11) == TrainConfig(epochs=7, lr=1e-3, batch="trajectory",
                                                    weight_decay=1e-4, seed=11, progress=False)
    assert cfg.replace(batch_size=64).train_config().batch == 64
    ens = cfg.ensemble_config(4, 2)
    assert ens == EnsembleConfig(
        state_dim=4, action_dim=2, formulation="f", normalize=True, seed=5,
        members=(MemberSpec("tanh", 9, 2), MemberSpec("elu", 9, 2), MemberSpec("tanh", 9, 2)))


def test_the_agent_uses_the_composed_configs():
    cfg = AgentConfig(regularization="exact", ensemble_size=2, progress=False, tensorboard=False,
                      checkpoint=False, eval_every=0)
    agent = JacPropAgent(gym.make("mbtsr/TwoLinkArm-v0"), cfg)
    assert agent.ensemble_config == cfg.ensemble_config(4, 2)
    assert agent._train_configs(3) == (cfg.train_config(3), cfg.regularization_config())
