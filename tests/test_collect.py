"""Tests of envs.collect.collect_trajectories."""

from __future__ import annotations

import math

import gymnasium as gym
import numpy as np
import pytest

import envs  # noqa: F401  (registration)
from envs.collect import collect_trajectories, default_input_kwargs
from envs.linear_system import LinearSystemEnv
from envs.two_link_arm import TwoLinkArmEnv
from mbtsr.dynamics import rollout
from mbtsr.trajectory import Trajectory


def test_shapes_dt_meta_and_records_replay_through_the_true_model():
    env = TwoLinkArmEnv(episode_steps=60)
    trajs = collect_trajectories(env, 3, 60, seed=1)
    assert len(trajs) == 3
    model = env.dynamics_model()
    for traj in trajs:
        assert isinstance(traj, Trajectory)
        assert traj.x.shape == (61, 4) and traj.u.shape == (60, 2)
        assert traj.dt == pytest.approx(0.02)
        assert {"reset_seed", "input_seed", "attempt", "target", "input"} <= set(traj.meta)
        # the recorded u is exactly what was applied: replaying it reproduces x bit for bit
        np.testing.assert_array_equal(rollout(model, traj.x[0], traj.u), traj.x)
        # and the env's own reset with the recorded seed gives the recorded start and target
        obs, info = env.reset(seed=traj.meta["reset_seed"])
        np.testing.assert_array_equal(info["state"], traj.x[0])
        np.testing.assert_array_equal(info["target"], traj.meta["target"])


def test_same_seed_bit_identical_across_env_instances_other_seed_differs():
    def run(seed: int) -> list[Trajectory]:
        env = gym.make("mbtsr/TwoLinkArm-v0", episode_steps=40)
        return collect_trajectories(env, 2, 40, input="multisine", seed=seed)

    first, again, other = run(5), run(5), run(6)
    for a, b in zip(first, again):
        np.testing.assert_array_equal(a.x, b.x)
        np.testing.assert_array_equal(a.u, b.u)
    assert not np.array_equal(first[0].u, other[0].u)


def test_default_input_is_scaled_to_the_presets_excitation_std():
    for preset, std in (("default", 0.15), ("paper", 1 / 3)):
        env = TwoLinkArmEnv(preset=preset)
        assert env.excitation_std == pytest.approx(std)
        assert default_input_kwargs(env, "filtered_gaussian") == pytest.approx(
            {"window": 100, "scale": 10 * std}
        )
        assert default_input_kwargs(env, "multisine")["amplitude"] == pytest.approx(
            std / math.sqrt(2.5)
        )
    # the paper preset's input is the paper's torque: std 1 N m = (1/3) * torque limit 3 N m
    env = TwoLinkArmEnv(preset="paper", episode_steps=300)
    trajs = collect_trajectories(env, 8, 300, seed=0)
    torque = np.concatenate([t.u[100:] for t in trajs]) * env.torque_limit
    # 8 x 200 strongly correlated samples per joint (~16 independent windows): +-40 %
    assert 0.6 < torque.std() < 1.4
    assert np.mean(np.abs(torque) >= env.torque_limit) < 0.01  # saturates rarely


def test_actions_are_clipped_into_the_action_space_and_recorded_clipped():
    env = TwoLinkArmEnv(episode_steps=10)

    def too_large(T, m, rng, level):  # noqa: N803
        return np.full((T, m), level) * rng.choice([-1.0, 1.0], size=(T, m))

    traj = collect_trajectories(env, 1, 10, input=too_large, input_kwargs={"level": 3.0}, seed=0)
    assert traj[0].u.shape == (10, 2)
    np.testing.assert_array_equal(np.abs(traj[0].u), 1.0)


def test_rejection_keeps_only_trajectories_inside_the_joint_limit():
    env = TwoLinkArmEnv(episode_steps=150)
    limit = 0.7  # about half of the default-input rollouts of 150 steps exceed it
    trajs = collect_trajectories(env, 4, 150, seed=2, reject_abs_q=limit)
    assert all(np.abs(t.x[:, :2]).max() < limit for t in trajs)
    assert trajs[-1].meta["attempt"] >= 4  # some rollouts were rejected and redrawn
    unfiltered = collect_trajectories(env, 4, 150, seed=2)
    assert max(np.abs(t.x[:, :2]).max() for t in unfiltered) >= limit
    with pytest.raises(RuntimeError, match="attempts"):
        collect_trajectories(env, 2, 150, seed=0, reject_abs_q=1e-4, max_attempts=5)


def test_linear_system_collection_uses_the_papers_input():
    env = LinearSystemEnv()
    assert default_input_kwargs(env, "filtered_gaussian") == {"window": 5, "scale": 10.0}
    trajs = collect_trajectories(env, 4, 200, seed=0)
    u = np.concatenate([t.u[5:] for t in trajs])
    assert u.std() == pytest.approx(10 / math.sqrt(5), rel=0.1)  # 7800 samples, 5-tap MA
    for t in trajs:
        np.testing.assert_allclose(t.x[1:], t.x[:-1] @ env.A.T + t.u @ env.B.T, atol=1e-12)
    with pytest.raises(ValueError, match="MuJoCo"):
        collect_trajectories(env, 1, 10, reject_abs_q=1.0)


@pytest.mark.parametrize(
    "kwargs, match",
    [
        ({"n_traj": 0}, "n_traj"),
        ({"T": 0}, "T must be"),
        ({"T": 101}, "episode_steps"),
        ({"input": "chirp"}, "input must be one of"),
        ({"input": 3}, "input must be"),
        ({"reject_abs_q": -1.0}, "reject_abs_q"),
        ({"input": lambda T, m, rng: np.zeros((T + 1, m))}, "shape"),
        ({"input": lambda T, m, rng: np.full((T, m), np.nan)}, "non-finite"),
    ],
)
def test_bad_arguments_raise_value_error(kwargs, match):
    env = TwoLinkArmEnv()
    args = {"n_traj": 1, "T": 20, **kwargs}
    with pytest.raises(ValueError, match=match):
        collect_trajectories(env, args.pop("n_traj"), args.pop("T"), **args)
