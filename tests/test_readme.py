"""The README's Python code blocks run, in a smoke mode, so that they cannot rot.

Design: the blocks run unchanged (``exec``, in a temporary working folder). The test, not the
README, makes them small: it wraps :class:`agents.JacPropAgent` so that every agent's config gets
tiny budgets on top of the README's own settings (:data:`SMOKE`) and every ``learn`` call runs
at most :data:`MAX_EPISODES` episodes. Everything else (envs, costs, the registry task, the
learned reward, save, predict, summary) is the real code path. The bash blocks are commands
that CI runs elsewhere (the test suite, ``--smoke`` of the benchmark commands).
"""

from __future__ import annotations

import warnings
from pathlib import Path

import pytest

from agents import AgentConfig, JacPropAgent
from agents.experiments.readme_examples import readme_blocks

BLOCKS = readme_blocks()

#: tiny budgets laid over each README config (bench_suite's SMOKE_OVERRIDES' sizes)
SMOKE = {
    "training.steps": 3, "planner.horizon": 5, "planner.first_plan_iterations": 2,
    "planner.ilqr_iterations": 1, "planner.cem.samples": 16, "planner.cem.elites": 4,
    "planner.cem.iterations": 1, "planner.proposal.samples": 8, "planner.proposal.elites": 2,
    "planner.proposal.iterations": 1, "model.ensemble_size": 2, "model.hidden_width": 8,
    "reward.steps": 5, "reward.members": 2, "reward.hidden": 8,
    "collection.episode_steps": 10, "collection.n_excitation_episodes": 1,
    "evaluation.episodes": 1, "progress": False, "tensorboard": False,
}
MAX_EPISODES = 2


def _smoke(config: AgentConfig) -> AgentConfig:
    kind = config.planner.kind
    keep = {k: v for k, v in SMOKE.items()
            if not (k.startswith("planner.cem.") and kind != "cem")
            and not (k.startswith("planner.proposal.") and kind != "cem-ilqr")
            and not (k == "planner.ilqr_iterations" and kind == "cem")}
    if config.evaluation.solved_return is None:  # no oracle in the smoke: a return criterion
        keep["evaluation.solved_return"] = 0.0
    return config.replace(keep)


@pytest.fixture
def smoke_agent(monkeypatch: pytest.MonkeyPatch, tmp_path: Path) -> None:
    init, learn = JacPropAgent.__init__, JacPropAgent.learn

    def small_init(self, env, config=None, *args, **kwargs):
        init(self, env, _smoke(AgentConfig() if config is None else config), *args, **kwargs)

    def small_learn(self, total_timesteps=None, callback=None, log_interval=None, *,
                    progress_bar=None, episodes=None):
        return learn(self, total_timesteps, callback, log_interval, progress_bar=progress_bar,
                     episodes=MAX_EPISODES if episodes is None else min(episodes, MAX_EPISODES))

    monkeypatch.setattr(JacPropAgent, "__init__", small_init)
    monkeypatch.setattr(JacPropAgent, "learn", small_learn)
    monkeypatch.chdir(tmp_path)


def test_the_readme_has_python_examples():
    assert len(BLOCKS) >= 3
    assert any('JacPropAgent(gym.make("' in b and "cost_fn" not in b for b in BLOCKS)


@pytest.mark.parametrize("i", range(len(BLOCKS)))
@pytest.mark.usefixtures("smoke_agent")
def test_readme_block_runs_in_smoke_mode(i):
    namespace: dict = {"__name__": f"readme_block_{i}"}
    with warnings.catch_warnings():
        warnings.simplefilter("ignore", RuntimeWarning)  # logged LTV fallbacks of tiny data
        exec(compile(BLOCKS[i], f"README.md[python block {i}]", "exec"), namespace)
    agents = [v for v in namespace.values() if isinstance(v, JacPropAgent)]
    assert agents, "every README example builds an agent"
    for agent in agents:
        assert agent.episodes_done == MAX_EPISODES and agent.spec.episode_steps == 10
