"""Any Gymnasium env with no other argument (issue 44): a registry task by the env's id, else a
reward learned from the env's rewards; the CI smoke over every MuJoCo v5 env Gymnasium ships
and its classic-control envs with Box actions."""

from __future__ import annotations

import casadi as ca
import gymnasium as gym
import numpy as np
import pytest
import torch

from agents import AgentConfig, JacPropAgent
from agents.task_setup import LearnedTask
from agents.tasks import inverted_double_pendulum, inverted_pendulum, reacher
from mbtsr.reward import LearnedRewardCost

#: tiny model, planner, training and reward budgets (bench_suite's SMOKE_OVERRIDES and a reward)
SMOKE = {
    "training.steps": 3, "planner.horizon": 5, "planner.first_plan_iterations": 2,
    "planner.ilqr_iterations": 1, "planner.proposal.samples": 8, "planner.proposal.elites": 2,
    "planner.proposal.iterations": 1, "model.ensemble_size": 2, "model.hidden_width": 8,
    "reward.steps": 5, "reward.members": 2, "reward.hidden": 8,
    "collection.episode_steps": 10, "collection.n_excitation_episodes": 1,
    "evaluation.every": 0, "progress": False, "tensorboard": False, "checkpoint": False,
    "jacobian_error": False,
}

#: the documented settings an env needs (docs/troubleshooting.md, "A large observation"): the
#: LTV labels of a 348-dimensional state would not fit in memory
NEEDS = {"Humanoid-v5": {"regularization": "smooth"},
         "HumanoidStandup-v5": {"regularization": "smooth"}}

MUJOCO_V5 = sorted(
    k for k, v in gym.envs.registry.items()
    if k.endswith("-v5") and isinstance(v.entry_point, str)
    and v.entry_point.startswith("gymnasium.envs.mujoco"))


def _config(env_id: str = "", **extra: object) -> AgentConfig:
    return AgentConfig.default({**SMOKE, **NEEDS.get(env_id, {}), **extra})


def test_the_smoke_covers_every_mujoco_v5_env():
    assert len(MUJOCO_V5) >= 11 and {"Reacher-v5", "Humanoid-v5", "Ant-v5"} <= set(MUJOCO_V5)


@pytest.mark.parametrize("env_id", [*MUJOCO_V5, "Pendulum-v1", "MountainCarContinuous-v0"])
def test_any_env_learns_with_no_other_argument(env_id):
    agent = JacPropAgent(gym.make(env_id), _config(env_id))
    agent.learn(episodes=2)
    rows = agent.logger_rows
    assert [r["episode"] for r in rows] == [0, 1] and rows[1]["phase"] == "mpc"
    for r in rows:
        assert np.isfinite(r["episode_cost"]) and np.isfinite(r["model_cost"])
    action, _ = agent.predict(agent.env.reset(seed=3)[0])
    assert np.all(np.isfinite(action)) and agent.env.action_space.contains(
        action.astype(agent.env.action_space.dtype))
    if agent.task.source == "learned":  # the reward saw every transition so far
        assert agent.task_cost.model.fits == 2
        assert sum(len(t.meta["rewards"]) for t in agent.trajectories) == agent.env_steps


def test_a_registry_env_by_its_id_uses_the_registrys_task():
    agent = JacPropAgent(gym.make("Reacher-v5"))  # no other argument
    task = reacher()
    assert agent.task.source == "registry" and agent.task.registry == "reacher"
    assert agent.cost_fn is task.cost_fn and agent.terminal_cost_fn is task.terminal_cost_fn
    rng = np.random.default_rng(0)
    obs, act = rng.normal(size=(6, 10)), rng.uniform(-1, 1, (6, 2))
    expected = [float(task.cost_fn(ca.DM(o), ca.DM(a))) for o, a in zip(obs, act)]
    np.testing.assert_allclose(agent.task_cost.on_observations(obs, act), expected, rtol=1e-12)
    # the planner's terminal cost is the task's, at the planner's terminal weight
    s, p = ca.DM(obs[0]), ca.DM(obs[0])
    w = agent.config.planner.terminal_weight
    np.testing.assert_allclose(float(agent.planner_cost.terminal(s, p)),
                               w * float(task.terminal_cost_fn(ca.DM(obs[0]))), rtol=1e-12)


def test_the_registrys_termination_and_a_users_functions():
    agent = JacPropAgent(gym.make("InvertedPendulum-v5"), _config())
    assert agent.termination_fn is inverted_pendulum().termination_fn

    def cost(obs, a):
        return ca.sumsqr(obs) + ca.sumsqr(a)

    def never(obs):
        return np.zeros(np.shape(obs)[:-1], bool)

    mine = JacPropAgent(gym.make("InvertedPendulum-v5"), _config(), cost_fn=cost,
                        termination_fn=never)
    assert mine.task.source == "given" and mine.cost_fn is cost
    assert mine.termination_fn is never


def test_the_horizon_rule_shortens_the_plan_of_a_task_that_terminates():
    """``planner.horizon``/``terminal_weight`` ``None``: 15 and 100 for a written cost with a
    termination function (the registry's or a user's), 30 and 1 otherwise; a value given is
    kept. The planner built, and its terminal cost, use the resolved values."""
    def never(obs):
        return np.zeros(np.shape(obs)[:-1], bool)

    def cost(obs, a):
        return ca.sumsqr(obs) + ca.sumsqr(a)

    cfg = AgentConfig(progress=False, tensorboard=False, checkpoint=False)
    made = {"registry IP": JacPropAgent(gym.make("InvertedPendulum-v5"), cfg),
            "user's termination": JacPropAgent(gym.make("Swimmer-v5"), cfg, cost_fn=cost,
                                               termination_fn=never),
            "Reacher": JacPropAgent(gym.make("Reacher-v5"), cfg),
            "user's cost only": JacPropAgent(gym.make("Swimmer-v5"), cfg, cost_fn=cost)}
    got = {k: (a.config.planner.horizon, a.config.planner.terminal_weight,
               a.actor.policy.horizon) for k, a in made.items()}
    assert got == {"registry IP": (15, 100.0, 15), "user's termination": (15, 100.0, 15),
                   "Reacher": (30, 1.0, 30), "user's cost only": (30, 1.0, 30)}
    x = np.linspace(0.1, 0.8, 8)
    np.testing.assert_allclose(  # the terminal cost: 100 x the stage cost at zero action
        float(made["user's termination"].planner_cost.terminal(ca.DM(x), ca.DM(x))),
        100.0 * float(cost(ca.DM(x), ca.DM.zeros(2))), rtol=1e-12)
    given = cfg.replace({"planner.horizon": 20, "planner.terminal_weight": 0.0})
    agent = JacPropAgent(gym.make("InvertedPendulum-v5"), given)
    assert (agent.config.planner.horizon, agent.config.planner.terminal_weight) == (20, 0.0)
    assert agent.evaluator.config.planner == agent.config.planner  # the oracle plans alike
    # a learned reward keeps 30 and 1, termination or not (docs/notes/horizon_rule.md)
    learned = JacPropAgent(gym.make("InvertedPendulum-v5"), cfg, cost_fn="learned")
    assert learned.termination_fn is not None and learned.actor.policy.horizon == 30
    assert (learned.config.planner.horizon, learned.config.planner.terminal_weight) == (30, 1.0)
    long_replan = cfg.replace({"planner.replan_every": 20})  # fits 30, not 15
    assert long_replan.planner.for_task(None, None).horizon == 30
    with pytest.raises(ValueError, match="replan_every=20 exceeds the horizon rule's 15 steps"):
        JacPropAgent(gym.make("InvertedPendulum-v5"), long_replan)


def test_an_unknown_env_learns_its_reward_and_plans_on_it():
    """Pendulum-v1: after a few episodes the learned cost ranks held-out steps as the env's
    rewards do, and the planner's cost is that learned reward."""
    cfg = _config(**{"collection.episode_steps": 100, "collection.n_excitation_episodes": 3,
                     "collection.excitation_scale": 1.0, "reward.steps": 500,
                     "reward.members": 3, "reward.hidden": 32})
    agent = JacPropAgent(gym.make("Pendulum-v1"), cfg)
    assert agent.task.source == "learned" and agent.cost_fn is None
    before = agent.planner_cost
    assert isinstance(before, LearnedRewardCost)
    assert np.all(before.reward.predict(np.ones((4, 3)), np.ones((4, 1))) == 0)  # no data: 0
    agent.learn(episodes=3)
    cost = agent.planner_cost
    assert isinstance(cost, LearnedRewardCost) and cost is not before
    assert agent.actor.policy.mpc.cost is cost
    # held-out: an episode of random actions from another start
    env = gym.make("Pendulum-v1")
    obs, _ = env.reset(seed=12345)
    rng = np.random.default_rng(7)
    O, A, R = [], [], []
    for _ in range(200):
        a = rng.uniform(-2, 2, 1)
        O.append(obs)
        A.append(a)
        obs, r, *_ = env.step(a.astype(np.float32))
        R.append(r)
    learned = agent.task_cost.on_observations(np.array(O), np.array(A))
    corr = np.corrcoef(learned, -np.array(R))[0, 1]
    assert corr > 0.9, corr
    # the planner's stage cost is -r_hat of the reward model
    X, U = np.array(O)[:5], np.array(A)[:5]
    stage = cost.stage_values(X[None], U[None], params=np.array(O[0]))
    np.testing.assert_allclose(np.ravel(stage), learned[:5], rtol=1e-10)


def test_a_learned_reward_resumes_bit_identically(tmp_path):
    def fresh() -> JacPropAgent:
        return JacPropAgent(gym.make("Pendulum-v1"), _config())

    whole = fresh().learn(episodes=3)
    part = fresh().learn(episodes=2)
    part.save(tmp_path / "a.pt")
    resumed = JacPropAgent.load(tmp_path / "a.pt", gym.make("Pendulum-v1")).learn(episodes=1)
    assert [r["episode_cost"] for r in resumed.logger_rows] == [
        r["episode_cost"] for r in whole.logger_rows]
    for k, v in whole.task_cost.model.state_dict()["params"].items():
        assert torch.equal(v, resumed.task_cost.model.state_dict()["params"][k]), k
    # without an env: acts on the saved learned reward
    actor = JacPropAgent.load(tmp_path / "a.pt")
    assert isinstance(actor.task_cost, LearnedTask) and actor.task_cost.model.fits == 2
    obs = np.array([1.0, 0.0, 0.0])
    np.testing.assert_array_equal(actor.predict(obs)[0], part.predict(obs)[0])


def test_without_a_written_cost_the_evaluation_has_no_oracle():
    agent = JacPropAgent(gym.make("Swimmer-v5"),
                         _config(**{"evaluation.every": 1, "evaluation.episodes": 1}))
    agent.learn(episodes=1)
    row = agent.logger_rows[-1]
    assert row["oracle_cost"] is None and row["cost_ratio"] is None
    assert np.isfinite(row["eval_cost"]) and agent.compute_oracle() is None


def test_model_env_of_a_learned_reward_agent_rewards_with_the_learned_reward():
    from agents.model_env import ModelEnv

    agent = JacPropAgent(gym.make("Pendulum-v1"), _config()).learn(episodes=2)
    menv = ModelEnv.from_agent(agent)
    obs, _ = menv.reset(seed=0)
    a = np.array([0.5], dtype=np.float32)
    _, r, *_ = menv.step(a)
    expected = agent.task_cost.frozen().predict(agent.state_map.state(obs), a.astype(float))
    assert r == pytest.approx(float(expected), rel=1e-9)


def test_a_constant_input_of_the_first_fit_is_not_rescaled():
    """An input that was constant in the first data (a contact force at rest) keeps unit scale:
    a small value later moves the learned reward little (a 1e-6 std floor made 1e-3 a
    thousand standard deviations)."""
    from mbtsr.reward import RewardConfig, RewardModel

    rng = np.random.default_rng(0)
    S = np.column_stack([rng.normal(size=400), np.zeros(400)])
    A = rng.normal(size=(400, 1))
    r = -S[:, 0] ** 2 - 0.1 * A[:, 0] ** 2
    model = RewardModel(2, 1, RewardConfig(steps=300, seed=0))
    model.fit(S, A, r)
    frozen = model.freeze()
    x = np.column_stack([rng.normal(size=50), np.zeros(50)])
    u = rng.normal(size=(50, 1))
    moved = x + np.array([0.0, 1e-3])
    assert np.max(np.abs(frozen.predict(moved, u) - frozen.predict(x, u))) < 0.01 * r.std()


def test_a_registry_agent_loads_without_its_functions(tmp_path):
    """The registry task's name is saved: load needs neither the cost nor the state maps.
    InvertedDoublePendulum's first episode turns its two sine/cosine pairs into angles (a model
    state of 7 numbers, not the 9 observations), which the checkpoint keeps."""
    agent = JacPropAgent(gym.make("InvertedDoublePendulum-v5"), _config())
    assert agent.state_dim == 9
    agent.learn(episodes=1)
    assert agent.state_dim == 7 and agent.state_map.angles == ((1, 3), (2, 4))
    assert agent.trajectories[0].n == 7 and agent.model.config.state_dim == 7
    agent.save(tmp_path / "idp.pt")
    for env in (gym.make("InvertedDoublePendulum-v5"), None):
        loaded = JacPropAgent.load(tmp_path / "idp.pt", env)
        assert loaded.task.source == "registry" and loaded.state_dim == 7
        assert loaded.termination_fn is agent.termination_fn
        obs = agent.env.reset(seed=1)[0]
        np.testing.assert_array_equal(loaded.predict(obs)[0], agent.predict(obs)[0])
    # a state map of the user's own is kept as it is
    own = JacPropAgent(gym.make("InvertedDoublePendulum-v5"), _config(),
                       cost_fn=inverted_double_pendulum().cost_fn, state_fn=lambda o: o,
                       obs_fn=lambda s, o: s).learn(episodes=1)
    assert own.state_dim == 9 and own.trajectories[0].n == 9


class _UprightPendulum(gym.Env):
    """A pendulum kept near upright, observed as ``[sin th, cos th, w]``; terminates at
    ``|th| > 0.5``; ``dynamics_model()`` is the true model on the observation."""

    observation_space = gym.spaces.Box(-np.inf, np.inf, (3,), np.float64)
    action_space = gym.spaces.Box(-1.0, 1.0, (1,), np.float64)

    @staticmethod
    def next_obs(x: np.ndarray, u: np.ndarray) -> np.ndarray:
        th, w = np.arctan2(x[..., 0], x[..., 1]), x[..., 2] + 0.05 * (
            9.81 * x[..., 0] + 2.0 * np.clip(u[..., 0], -1, 1))
        return np.stack([np.sin(th + 0.05 * w), np.cos(th + 0.05 * w), w], -1)

    def reset(self, *, seed=None, options=None):
        super().reset(seed=seed)
        th, self.w = self.np_random.uniform(-0.1, 0.1, 2)
        self.x = np.array([np.sin(th), np.cos(th), self.w])
        return self.x.copy(), {}

    def step(self, a):
        self.x = self.next_obs(self.x, np.asarray(a, float))
        th = np.arctan2(self.x[0], self.x[1])
        return self.x.copy(), -(th**2), bool(abs(th) > 0.5), False, {}

    def dynamics_model(self):
        return _ObservationModel()


class _ObservationModel:
    """:class:`_UprightPendulum`'s true model; Jacobians by central differences."""

    state_dim, action_dim = 3, 1

    def step(self, x, u, t=None):
        return _UprightPendulum.next_obs(np.asarray(x, float), np.asarray(u, float))

    def jacobians(self, x, u, t=0):
        x, u, e = np.atleast_2d(x).astype(float), np.atleast_2d(u).astype(float), 1e-6
        def d(z, n, f):
            return np.stack([(f(z + e * np.eye(n)[i]) - f(z - e * np.eye(n)[i])) / (2 * e)
                             for i in range(n)], -1)
        return (d(x, 3, lambda z: self.step(z, u)), d(u, 1, lambda z: self.step(x, z)))


def test_found_angles_leave_the_oracle_on_the_env_s_own_model():
    """The oracle plans on the env's ``dynamics_model()``, whose state is the observation: the
    angles the agent finds after its first episode change its own model only."""
    gym.register("mbtsr-test/UprightPendulum-v0", entry_point=_UprightPendulum,
                 max_episode_steps=40)
    def cost(o, a):
        return 10 * (1 - o[1]) + 0.01 * o[2] ** 2 + 0.01 * a[0] ** 2

    cfg = _config(**{"evaluation.every": 1, "collection.episode_steps": 40})
    agent = JacPropAgent(gym.make("mbtsr-test/UprightPendulum-v0"), cfg, cost_fn=cost)
    before = agent.compute_oracle()
    agent.learn(episodes=2)  # evaluated after each episode, oracle included
    assert agent.state_dim == 2 and agent.state_map.angles == ((0, 1),)
    assert agent.oracle_mean == before
    fresh = JacPropAgent(gym.make("mbtsr-test/UprightPendulum-v0"), cfg, cost_fn=cost)
    assert fresh.learn(episodes=1).state_dim == 2 and fresh.compute_oracle() == before
