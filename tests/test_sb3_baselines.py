"""SB3 baselines on the two-link arm's targets (issue 7).

- the callback's evaluation cost is minus the return SB3's own ``evaluate_policy`` measures on
  the same targets and resets (raw observations for SAC, ``VecNormalize`` for PPO);
- a cost threshold stops training at the first solved evaluation; bad arguments are refused.
(The suite's SAC rows, on every task's own return: tests/test_bench_suite_sb3.py.)
"""

from __future__ import annotations

import json
from pathlib import Path

import gymnasium as gym
import numpy as np
import pytest
import torch
from helpers_sb3 import SMALL_RUNS, ScriptedResets, sb3_returns

import envs  # noqa: F401  (registers mbtsr/TwoLinkArm-v0)
from agents.sb3_baselines import default_hyperparams, train_sb3

REPO = Path(__file__).resolve().parents[1]
ARM = "mbtsr/TwoLinkArm-v0"
TARGETS = [[0.4, -0.3], [-0.8, 0.5], [1.0, 0.2]]
EVAL_SEED = 1000


@pytest.fixture(autouse=True)
def _one_thread():
    threads = torch.get_num_threads()
    torch.set_num_threads(1)
    yield
    torch.set_num_threads(threads)


# ---------------------------------------------------------------------------------------------
# the callback's cost is minus SB3's episode return
# ---------------------------------------------------------------------------------------------


@pytest.mark.parametrize("algo, budget, every, hyperparams", SMALL_RUNS)
def test_callback_cost_is_minus_sb3_return(algo, budget, every, hyperparams):
    rec = train_sb3(algo, ARM, budget, seed=3, eval_every=every, eval_targets=TARGETS,
                    threshold=None, hyperparams=hyperparams, eval_seed=EVAL_SEED,
                    return_model=True)
    model = rec.pop("model")
    json.dumps(rec)  # the record is JSON-serializable
    assert [s for s, _ in rec["curve"]] == list(range(0, budget + 1, every))
    assert rec["env_steps"] == budget and not rec["solved"] and rec["steps_to_solve"] is None

    returns, lengths = sb3_returns(model, ScriptedResets(gym.make(ARM), EVAL_SEED, TARGETS),
                                   len(TARGETS), bool(hyperparams.get("normalize")))
    assert lengths == [100] * len(TARGETS)
    # the final curve point is the final policy; rewards pass through float32 in the VecEnv
    assert rec["curve"][-1][1] == pytest.approx(-np.mean(returns), rel=1e-5)


def test_stops_at_first_solved_evaluation():
    # the untrained policy's cost on these targets, then a threshold just above it: solved at 0
    probe = train_sb3("td3", ARM, 1, seed=0, eval_every=1, eval_targets=TARGETS[:1],
                      threshold=None, hyperparams={"learning_starts": 10}, eval_seed=EVAL_SEED)
    cost0 = probe["curve"][0][1]
    rec = train_sb3("td3", ARM, 10_000, seed=0, eval_every=50, eval_targets=TARGETS[:1],
                    threshold=cost0 * 1.0001, hyperparams={"learning_starts": 10},
                    eval_seed=EVAL_SEED)
    assert rec["solved"] and rec["steps_to_solve"] == 0
    assert rec["env_steps"] <= 1  # stopped at the first on_step after the solved evaluation
    assert rec["curve"] == [[0, pytest.approx(cost0, rel=1e-12)]]
    assert 0 <= rec["wall_seconds_to_solve"] <= rec["wall_seconds_to_solve_incl_eval"]


@pytest.mark.parametrize(
    "kwargs, msg",
    [
        ({"algo": "a2c"}, "algo"),
        ({"budget_steps": 0}, "budget_steps"),
        ({"eval_every": 1.5}, "eval_every"),
        ({"seed": -1}, "seed"),
        ({"eval_targets": [[0.1, np.nan]]}, "eval_targets"),
        ({"eval_targets": [0.1, 0.2]}, "eval_targets"),
        ({"threshold": -1.0}, "threshold"),
        ({"threshold": np.inf}, "threshold"),
        ({"hyperparams": {"no_such_kwarg": 1}}, "hyperparams"),
        ({"hyperparams": {"action_noise_std": 0.1}, "algo": "ppo"}, "action_noise_std"),
    ],
)
def test_bad_arguments(kwargs, msg):
    args = {"algo": "sac", "env_id": ARM, "budget_steps": 10, "seed": 0, "eval_every": 5,
            "eval_targets": TARGETS, "threshold": 1.0}
    args.update(kwargs)
    with pytest.raises(ValueError, match=msg):
        train_sb3(**args)


def test_default_hyperparams_are_documented_choices():
    assert default_hyperparams("sac") == {}
    assert default_hyperparams("td3") == {"action_noise_std": 0.1}
    assert default_hyperparams("ppo") == {"normalize": True}
