"""The agent under Stable-Baselines3's conventions (issue 44): ``learn(total_timesteps)``, SB3
callbacks, batch ``predict``, TensorBoard by env step next to an SB3 run, ``load`` of a
registered task without its functions. Real MuJoCo, CasADi, torch and SB3; tiny budgets."""

from __future__ import annotations

import re

import gymnasium as gym
import numpy as np
import pytest
from stable_baselines3 import SAC
from stable_baselines3.common.callbacks import BaseCallback, CallbackList
from tensorboard.backend.event_processing.event_accumulator import EventAccumulator

from agents.experiments.bench_suite import agent_config
from agents.jacprop_agent import JacPropAgent
from agents.tasks import inverted_pendulum, make_task

STEPS = 20  # episode length


def tiny(**changes):
    """The inverted pendulum's smoke settings (bench_suite), 20-step episodes, no evaluation
    unless asked."""
    return agent_config("inverted-pendulum", {"collection.episode_steps": STEPS,
                                              "evaluation.every_steps": 0, **changes}, smoke=True)


def pendulum_agent(config=None) -> JacPropAgent:
    task = inverted_pendulum(max_episode_steps=STEPS)
    return JacPropAgent(task.make_env(), config or tiny(), **task.agent_kwargs())


class Recorder(BaseCallback):
    """Records every call with the agent's step count; ``on_step`` returns False at
    ``stop_at`` (a count of env steps in this learn call)."""

    def __init__(self, events: list, stop_at: int | None = None) -> None:
        super().__init__()
        self.events, self.stop_at = events, stop_at

    def _init_callback(self) -> None:
        self.events.append(("init", self.model.num_timesteps))

    def _on_training_start(self) -> None:
        assert self.locals["self"] is self.model and "total_timesteps" in self.locals
        self.events.append(("training_start", self.num_timesteps))

    def _on_rollout_start(self) -> None:
        self.events.append(("rollout_start", self.model.num_timesteps))

    def _on_step(self) -> bool:
        assert self.locals["new_obs"].shape == (4,)
        self.logger.record("custom/n_calls", self.n_calls)
        self.events.append(("step", self.num_timesteps))
        return self.stop_at is None or self.n_calls < self.stop_at

    def _on_rollout_end(self) -> None:
        self.events.append(("rollout_end", self.locals["row"]["env_steps"]))

    def _on_training_end(self) -> None:
        self.events.append(("training_end", self.model.num_timesteps))


def test_sb3_callbacks_run_in_order_per_env_step_and_stop_learning():
    agent = pendulum_agent()
    events, plain = [], []
    agent.learn(30, callback=[Recorder(events), lambda d: plain.append(d["row"]["env_steps"])],
                progress_bar=False)
    assert agent.env_steps == 30
    # 30 steps: an episode of 20 (unless the pole fell first) and the rest, cut to the budget
    lengths = [t.T for t in agent.trajectories]
    ends = np.cumsum(lengths).tolist()
    expected = [("init", 0), ("training_start", 0)]
    for start, end in zip([0, *ends[:-1]], ends):
        expected += [("rollout_start", start)]
        expected += [("step", s) for s in range(start + 1, end + 1)]
        expected += [("rollout_end", end)]
    expected += [("training_end", 30)]
    assert events == expected
    assert plain == ends  # plain functions still run after every episode

    # on_step returning False ends the rollout after that step and learning after the episode
    events, before = [], len(agent.trajectories)
    agent.learn(100, callback=CallbackList([Recorder(events, stop_at=7)]), progress_bar=False)
    # (the pole may fall first: then an episode ends and the next one runs to the stop)
    assert agent.env_steps == 37 and sum(t.T for t in agent.trajectories[before:]) == 7
    assert [e for e in events if e[0] == "step"][-1] == ("step", 37)
    assert events[-2:] == [("rollout_end", 37), ("training_end", 37)]
    with pytest.raises(TypeError, match="BaseCallback"):
        agent.learn(5, callback=[3])


def test_learn_total_timesteps_stops_at_exactly_n_env_steps(capsys):
    agent = pendulum_agent()
    for n, total in ((13, 13), (25, 38), (1, 39)):
        agent.learn(n, progress_bar=False)
        assert agent.env_steps == total == sum(t.T for t in agent.trajectories)
        assert agent.logger_rows[-1]["env_steps"] == total
    assert "total_timesteps" not in capsys.readouterr().out  # no log_interval: no tables
    before = agent.episodes_done

    def record(d):  # what an SB3 callback may log; exclude= keeps a value off stdout
        d["agent"].logger.record("custom/shown", 1.5)
        d["agent"].logger.record("custom/hidden", 2.5, exclude=("stdout", "log"))

    agent.learn(60, record, 2, progress_bar=False)  # SB3's positions: log_interval third
    out = capsys.readouterr().out
    assert "custom/" in out and "shown" in out and "hidden" not in out
    printed = re.findall(r"\|\s+total_timesteps\s+\|\s+(\d+)", out)
    assert [int(v) for v in printed] == [r["env_steps"] for i, r in enumerate(
        agent.logger_rows) if i >= before and i % 2 == 1]  # every second episode done
    with pytest.raises(ValueError, match="log_interval must be an integer >= 1, got 0"):
        agent.learn(5, log_interval=0)


def test_batch_predict_equals_per_row_predict_with_a_state_per_row():
    agent = pendulum_agent()
    agent.learn(episodes=3, progress_bar=False)  # two excitation episodes, one with the planner
    obs = np.random.default_rng(0).uniform(-0.1, 0.1, (3, 4))
    acts, states = agent.predict(obs)
    assert acts.shape == (3, 1) and len(states) == 3
    rows = [agent.predict(o) for o in obs]
    np.testing.assert_array_equal(acts, np.stack([a for a, _ in rows]))
    # the next call: row-wise warm starts; episode_start cold-starts the flagged row only
    nxt = obs + 0.01
    acts2, _ = agent.predict(nxt, states, episode_start=np.array([False, True, False]))
    np.testing.assert_array_equal(acts2[0], agent.predict(nxt[0], rows[0][1])[0])
    np.testing.assert_array_equal(acts2[1], agent.predict(nxt[1])[0])
    np.testing.assert_array_equal(acts2[2], agent.predict(nxt[2], rows[2][1])[0])
    with pytest.raises(ValueError, match="list of 3 states"):
        agent.predict(obs, states[:2])
    with pytest.raises(ValueError, match="episode_start must be one flag or 3 flags, got 2"):
        agent.predict(obs, states, episode_start=[True, False])
    # deterministic=False: the planned action plus the exploration noise, within the box
    a_det, _ = agent.predict(obs[0], rows[0][1])  # warm-started: a plan a cold start repeats
    noisy = np.stack([agent.predict(obs[0], rows[0][1], deterministic=False)[0]
                      for _ in range(200)])
    low, high = agent.env.action_space.low, agent.env.action_space.high
    assert np.all(noisy >= low) and np.all(noisy <= high)
    std = agent.config.collection.exploration_std * 0.5 * (high - low)
    free = noisy[(noisy > low) & (noisy < high)] - a_det
    assert abs(np.std(free) / std[0] - 1.0) < 0.25  # 200 draws: std within 25 %


def test_the_acting_noise_resumes_its_stream_after_save_and_load(tmp_path):
    """predict(deterministic=False)'s generator is checkpointed: a loaded agent draws the
    noise the saved one would have drawn next."""
    agent = pendulum_agent()
    agent.learn(episodes=2, progress_bar=False)
    obs = np.zeros(4)
    agent.predict(obs, deterministic=False)
    agent.save(tmp_path / "a.pt")
    loaded = JacPropAgent.load(tmp_path / "a.pt", agent.env)
    for _ in range(3):
        np.testing.assert_array_equal(loaded.predict(obs, deterministic=False)[0],
                                      agent.predict(obs, deterministic=False)[0])


def test_load_restores_a_registered_tasks_functions_by_itself(tmp_path):
    agent = pendulum_agent()
    agent.learn(episodes=3, progress_bar=False)
    path = agent.save(tmp_path / "a.pt")
    task = make_task("inverted-pendulum")
    for loaded in (JacPropAgent.load(path), JacPropAgent.load(path, task.make_env(
            max_episode_steps=STEPS))):
        assert loaded.termination_fn is task.termination_fn
        assert loaded.cost_fn is task.cost_fn
        obs = np.array([0.0, 0.05, 0.0, -0.1])
        np.testing.assert_array_equal(loaded.predict(obs)[0], agent.predict(obs)[0])
    resaved = JacPropAgent.load(JacPropAgent.load(path).save(tmp_path / "b.pt"))  # env-less
    assert resaved.termination_fn is task.termination_fn
    loaded.learn(5, progress_bar=False)
    assert loaded.env_steps == agent.env_steps + 5


def test_unregistered_functions_are_named_when_missing_at_load(tmp_path):
    task = inverted_pendulum(max_episode_steps=STEPS)

    def alive(obs):  # not the registry's function: the checkpoint cannot name it
        return task.termination_fn(obs)

    agent = JacPropAgent(task.make_env(), tiny(), cost_fn=task.cost_fn, termination_fn=alive)
    agent.learn(episodes=1, progress_bar=False)
    path = agent.save(tmp_path / "a.pt")
    with pytest.raises(ValueError, match=r"its own cost_fn, termination_fn, .*pass cost_fn=, "
                                         r"termination_fn= to load"):
        JacPropAgent.load(path)
    with pytest.raises(ValueError, match=r"its own termination_fn, .*pass termination_fn="):
        JacPropAgent.load(path, cost_fn=task.cost_fn)
    again = JacPropAgent.load(path, cost_fn=task.cost_fn, termination_fn=alive)
    assert again.termination_fn is alive and again.env_steps == agent.env_steps


def _scalars(folder) -> dict[str, list[tuple[int, float]]]:
    acc = EventAccumulator(str(folder))
    acc.Reload()
    return {t: [(e.step, e.value) for e in acc.Scalars(t)] for t in acc.Tags()["scalars"]}


def test_sb3_sac_and_the_agent_share_one_tensorboard_by_env_step(tmp_path):
    """SB3's SAC and the agent log into one TensorBoard folder; both curves are read back by
    env step under the same tags."""
    env = gym.make("InvertedPendulum-v5", max_episode_steps=STEPS)
    SAC("MlpPolicy", env, learning_starts=50, batch_size=32, policy_kwargs={"net_arch": [16]},
        seed=0, tensorboard_log=str(tmp_path)).learn(120, tb_log_name="sac", log_interval=1)
    cfg = tiny(**{"evaluation.every_steps": 60, "evaluation.episodes": 1}).replace(
        run_dir=str(tmp_path / "jacprop"), tensorboard=True, checkpoint=False)
    agent = pendulum_agent(cfg)
    agent.learn(120, callback=Recorder([]), progress_bar=False)

    sac = _scalars(tmp_path / "sac_1")
    ours = _scalars(tmp_path / "jacprop" / "tb")
    for tag in ("rollout/ep_rew_mean", "rollout/ep_len_mean", "time/fps"):
        assert tag in sac and tag in ours, tag
        assert all(0 < step <= 120 for step, _ in sac[tag] + ours[tag])
    rows = agent.logger_rows
    ends = [r["env_steps"] for r in rows]
    assert [s for s, _ in ours["rollout/ep_rew_mean"]] == ends and ends[-1] == 120
    # SB3's mean over the last 100 episodes of the training return (= -episode cost)
    want = [-np.mean([r["episode_cost"] for r in rows[: i + 1]]) for i in range(len(rows))]
    np.testing.assert_allclose([v for _, v in ours["rollout/ep_rew_mean"]], want, rtol=1e-6)
    lengths = np.diff([0, *ends])
    np.testing.assert_allclose([v for _, v in ours["rollout/ep_len_mean"]],
                               [np.mean(lengths[: i + 1]) for i in range(len(rows))], rtol=1e-6)
    assert ours["time/total_timesteps"] == [(e, float(e)) for e in ends]
    evals = [(r["env_steps"], r["eval_return"]) for r in rows if r["eval_return"] is not None]
    assert evals and [(s, pytest.approx(v)) for s, v in ours["eval/mean_reward"]] == evals
    assert "train/train_loss" in ours and "time/time_training" in ours
    # what the SB3 callback recorded lands at the episode's env step
    assert [s for s, _ in ours["custom/n_calls"]] == ends
    assert [v for _, v in ours["custom/n_calls"]] == [float(e) for e in ends]
