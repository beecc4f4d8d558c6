"""The oracle cache is keyed by what the oracle's costs depend on, as data (issue 15): the env's
physics (its compiled MjModel), the env's arguments, the task, the evaluation seeds and lengths,
the planner settings and ``mbtsr.__version__``; not by hashing source files.

Checks: the same inputs give the same key (new env instances included); changing a planner
option, a physical parameter, the task cost or the version changes it; a second agent with the
same settings reads the stored costs without running the oracle (calls counted), one with a
changed planner setting runs it again."""

from __future__ import annotations

import gymnasium as gym
import numpy as np
import pytest

import envs  # noqa: F401  (registers mbtsr/TwoLinkArm-v0)
import mbtsr
from agents.evaluation import cached_costs, oracle_cache_key, physics_fingerprint
from agents.tasks import QuadraticTargetCost, StateMap
from mbtsr.ilqr import ILQROptions

ARM = "mbtsr/TwoLinkArm-v0"
PLANNER = {"horizon": 4, "iterations": 1, "first_plan_iterations": 3, "terminal_weight": 1.0,
           "replan_every": 1}


def _task(q0: float = 1.0) -> dict:
    cost = QuadraticTargetCost(np.diag([q0, 1.0, 0.01, 0.01]), np.diag([0.01, 0.01]), (4, 6))
    return {"cost": cost.to_dict(), "state_map": StateMap().to_dict()}


def _key(env=None, task=None, planner=None, **kw):
    env = gym.make(ARM) if env is None else env
    kw = {"n_episodes": 2, "episode_steps": 5, **kw}
    return oracle_cache_key(env, task or _task(), [np.zeros(2), np.ones(2)], 7,
                            planner=planner or PLANNER, **kw)


def test_same_inputs_same_key_and_each_input_changes_it(monkeypatch):
    base = _key()
    assert _key() == base  # a fresh env instance, the same physics
    assert _key(planner={**PLANNER, "horizon": 5}) != base
    assert _key(optimizer_options=ILQROptions(lambda_init=2.0)) != base
    assert _key(optimizer_options=ILQROptions()) == base  # planning.solver's default
    assert _key(task=_task(2.0)) != base
    assert _key(episode_steps=6) != base
    assert _key(n_episodes=3) != base
    env = gym.make(ARM)
    env.unwrapped.model.dof_damping[0] += 1e-3  # physics only: the env's arguments are the same
    changed = _key(env)
    assert changed["env"] == base["env"] and changed["physics"] != base["physics"]
    monkeypatch.setattr(mbtsr, "__version__", mbtsr.__version__ + ".post1")
    assert _key() != base


def test_physics_fingerprint_follows_the_parameters():
    a, b = gym.make(ARM), gym.make(ARM, params={"link_mass": (2.0, 1.0)})
    assert physics_fingerprint(a) == physics_fingerprint(gym.make(ARM))
    assert physics_fingerprint(a) != physics_fingerprint(b)
    with pytest.raises(ValueError, match="no compiled MuJoCo model"):
        physics_fingerprint(gym.make("Pendulum-v1"))


def test_cached_costs_computes_once_per_key(tmp_path):
    calls = []

    def compute():
        calls.append(1)
        return np.array([1.0, 2.0])

    first = cached_costs(tmp_path, _key(), compute)
    again = cached_costs(tmp_path, _key(), compute)
    np.testing.assert_array_equal(first, again)
    assert len(calls) == 1
    cached_costs(tmp_path, _key(planner={**PLANNER, "iterations": 2}), compute)
    assert len(calls) == 2


def test_agent_oracle_hits_the_cache(tmp_path, monkeypatch):
    import agents.evaluation as evaluation
    import agents.jacprop_agent as jp
    from agents.config import AgentConfig

    runs = []
    real = evaluation.evaluate_policy_costs

    def counted(policy, *args, **kwargs):
        if type(policy).__name__ == "ReplanEvery":  # the oracle (the agent's own is not run)
            runs.append(1)
        return real(policy, *args, **kwargs)

    monkeypatch.setattr(evaluation, "evaluate_policy_costs", counted)
    cfg = AgentConfig.default({"planner.horizon": 4, "planner.ilqr_iterations": 1,
                               "planner.first_plan_iterations": 3, "evaluation.episodes": 1,
                               "evaluation.every": 0,
                               "evaluation.oracle_cache_dir": str(tmp_path)},
                              progress=False, tensorboard=False, checkpoint=False)

    def oracle(cfg):
        return jp.JacPropAgent(gym.make(ARM, episode_steps=4), cfg).compute_oracle()

    first = oracle(cfg)
    assert len(runs) == 1 and len(list(tmp_path.glob("oracle_*.json"))) == 1
    assert oracle(cfg) == first and len(runs) == 1  # read back, not recomputed
    oracle(cfg.replace({"planner.first_plan_iterations": 4}))
    assert len(runs) == 2
