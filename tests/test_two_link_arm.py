"""Tests of mbtsr/TwoLinkArm-v0, its Jacobians and its analytic CasADi twin.

Tolerances (see docs/environments.md):
- ``linearize`` vs an independent central difference of ``env.step`` (eps 1e-6): 1e-7 of the
  Jacobian's largest entry. Both are centred differences of a function that is smooth except on
  MuJoCo's friction-zone boundaries; truncation error ~eps^2 and rounding ~1e-16/eps per substep,
  chained over 10 substeps, measured <= 3e-9, so 1e-7 leaves a 30x margin.
- analytic twin vs MuJoCo where both joints keep ``|qd| >= 0.2`` rad/s in every substep (MuJoCo's
  friction is exactly ``-fc sign(qd)`` there, ``tanh(qd/0.01)`` equals ``sign`` to 1e-8): states
  1e-10 (measured ~2e-15), Jacobians 1e-7 of the largest entry (measured ~2e-9, the FD error).
- near zero velocity the friction models differ (MuJoCo: soft stiction, twin: tanh); the
  velocity error is bounded by ``dt * ||(M + h D)^-1||_2 * 2 ||fc||`` (friction differs by at most
  2 fc for the whole step), the position error by ``dt`` times that.
"""

from __future__ import annotations

import math
import pickle

import gymnasium as gym
import mujoco
import numpy as np
import pytest
from gymnasium.utils.env_checker import check_env
from hypothesis import given, settings
from hypothesis import strategies as st
from hypothesis.extra.numpy import arrays

import envs  # noqa: F401  (registration, MUJOCO_GL)
from envs.two_link_arm import ASSET_PATH, TwoLinkArmEnv, build_model, fingertip_position
from envs.two_link_arm_model import PRESETS, TwoLinkArmCasadi, arm_params
from mbtsr.dynamics import DynamicsModel

PRESET_NAMES = ["default", "paper"]


@pytest.fixture(scope="module", params=PRESET_NAMES)
def arm(request) -> TwoLinkArmEnv:
    env = TwoLinkArmEnv(preset=request.param)
    env.reset(seed=0)
    return env


def full_mass_matrix(env: TwoLinkArmEnv, q: np.ndarray) -> np.ndarray:
    data = mujoco.MjData(env.model)
    data.qpos[:] = q
    mujoco.mj_forward(env.model, data)
    mass = np.zeros((2, 2))
    mujoco.mj_fullM(env.model, data, mass)
    return mass


def env_step_from(env: TwoLinkArmEnv, x: np.ndarray, u: np.ndarray) -> np.ndarray:
    env.reset(options={"state": x})
    return env.step(u)[4]["state"]


def stacked(a_jac: np.ndarray, b_jac: np.ndarray) -> np.ndarray:
    return np.concatenate([a_jac, b_jac], axis=-1)


# --- Gymnasium / SB3 API --------------------------------------------------------------------


@pytest.mark.parametrize("preset", PRESET_NAMES)
def test_gymnasium_and_sb3_env_checkers_pass(preset):
    from stable_baselines3.common.env_checker import check_env as sb3_check_env

    check_env(TwoLinkArmEnv(preset=preset), skip_render_check=True)
    sb3_check_env(TwoLinkArmEnv(preset=preset), warn=True)
    env = gym.make("mbtsr/TwoLinkArm-v0", preset=preset)
    check_env(env.unwrapped, skip_render_check=True)
    assert env.observation_space.shape == (6,)
    assert env.action_space.shape == (2,)
    np.testing.assert_array_equal(env.action_space.low, [-1, -1])
    np.testing.assert_array_equal(env.action_space.high, [1, 1])


def test_same_seed_gives_bit_identical_trajectory_and_other_seed_differs():
    def run(seed: int) -> tuple[np.ndarray, np.ndarray]:
        env = gym.make("mbtsr/TwoLinkArm-v0")
        obs, _ = env.reset(seed=seed)
        actions = np.random.default_rng(seed).uniform(-1, 1, (50, 2)).astype(np.float32)
        observations, rewards = [obs], []
        for a in actions:
            obs, reward, *_ = env.step(a)
            observations.append(obs)
            rewards.append(reward)
        return np.array(observations), np.array(rewards)

    obs_a, rew_a = run(7)
    obs_b, rew_b = run(7)
    np.testing.assert_array_equal(obs_a, obs_b)
    np.testing.assert_array_equal(rew_a, rew_b)
    assert not np.array_equal(run(8)[0], obs_a)


def test_episode_truncates_at_episode_steps_without_termination():
    env = TwoLinkArmEnv(episode_steps=7)
    env.reset(seed=0)
    flags = [env.step(np.zeros(2))[2:4] for _ in range(7)]
    assert [f[0] for f in flags] == [False] * 7
    assert [f[1] for f in flags] == [False] * 6 + [True]


def test_reward_is_the_documented_quadratic_cost_of_the_next_state_and_clipped_action():
    env = TwoLinkArmEnv()
    _, info = env.reset(seed=3, options={"target": [0.4, -0.3]})
    np.testing.assert_array_equal(info["target"], [0.4, -0.3])
    np.testing.assert_array_equal(env.cost_Q, np.diag([1.0, 1.0, 0.01, 0.01]))
    np.testing.assert_array_equal(env.cost_R, np.diag([0.01, 0.01]))
    obs, reward, _, _, info = env.step(np.array([2.0, -0.5]))  # 2.0 is clipped to 1.0
    err = info["state"] - np.array([0.4, -0.3, 0.0, 0.0])
    applied = np.array([1.0, -0.5])
    expected = -(err @ env.cost_Q @ err + applied @ env.cost_R @ applied)
    assert reward == pytest.approx(expected, rel=1e-12)
    np.testing.assert_array_equal(obs, np.concatenate([info["state"], [0.4, -0.3]]))
    np.testing.assert_array_equal(env.data.ctrl, applied)


def test_reset_draws_targets_within_limits_and_options_override_exactly():
    env = TwoLinkArmEnv()
    targets = np.array([env.reset(seed=s)[1]["target"] for s in range(200)])
    assert np.all(np.abs(targets) <= env.target_limit)
    assert targets.std() > 0.5  # U(-pi/2, pi/2) has std 0.91
    _, plain = env.reset(seed=11)
    obs, info = env.reset(seed=11, options={"target": [0.1, 0.2]})
    np.testing.assert_array_equal(info["state"], plain["state"])  # start state unchanged
    np.testing.assert_array_equal(obs[4:], [0.1, 0.2])
    x0 = np.array([0.3, -0.2, 0.5, -0.1])
    _, info = env.reset(seed=11, options={"state": x0})
    np.testing.assert_array_equal(info["state"], x0)
    np.testing.assert_array_equal(info["target"], plain["target"])
    assert np.all(np.abs(plain["state"]) <= env.init_noise)


def test_q_zero_hangs_down_is_at_rest_and_positive_angles_swing_to_plus_x(arm):
    _, info = arm.reset(options={"state": np.zeros(4)})
    for _ in range(20):
        _, _, _, _, info = arm.step(np.zeros(2))
    np.testing.assert_array_equal(info["state"], np.zeros(4))
    data = mujoco.MjData(arm.model)
    for q in ([0.0, 0.0], [0.7, 0.0], [0.3, 1.1], [-2.0, 0.5]):
        data.qpos[:] = q
        mujoco.mj_forward(arm.model, data)
        tip = data.site("fingertip").xpos
        np.testing.assert_allclose(tip, fingertip_position(np.array(q), arm.params), atol=1e-12)
    assert fingertip_position(np.array([0.7, 0.0]), arm.params)[0] > 0


def test_xml_asset_numbers_are_the_default_preset():
    raw = mujoco.MjModel.from_xml_path(str(ASSET_PATH))
    built = build_model(PRESETS["default"])
    for name in (
        "body_mass",
        "body_ipos",
        "body_inertia",
        "body_pos",
        "dof_damping",
        "dof_frictionloss",
        "dof_armature",
        "dof_solref",
        "actuator_gear",
        "actuator_ctrlrange",
    ):
        np.testing.assert_allclose(getattr(built, name), getattr(raw, name), err_msg=name)
    assert raw.opt.timestep == built.opt.timestep == 0.002
    np.testing.assert_array_equal(raw.opt.gravity, built.opt.gravity)
    assert raw.opt.integrator == mujoco.mjtIntegrator.mjINT_EULER


def test_paper_preset_matches_the_original_robot_without_the_inertia_typo():
    env = TwoLinkArmEnv(preset="paper")
    assert env.dt == pytest.approx(0.02)
    np.testing.assert_array_equal(env.model.dof_damping, [2.0, 2.0])
    np.testing.assert_array_equal(env.model.dof_frictionloss, [0.1, 0.1])
    np.testing.assert_allclose(env.model.opt.gravity, [0, 0, -1.82])
    m1 = m2 = 0.2
    l1 = l2 = 1.0
    for q2 in np.linspace(-3, 3, 7):
        c2 = math.cos(q2)
        expected = np.array(
            [
                [
                    (m1 + m2) * l1**2 + m2 * l2**2 + 2 * m2 * l1 * l2 * c2,
                    m2 * l2**2 + m2 * l1 * l2 * c2,
                ],
                [m2 * l2**2 + m2 * l1 * l2 * c2, m2 * l2**2],
            ]
        )
        # point masses: MuJoCo needs a positive body inertia, the preset uses 1e-9 kg m^2
        np.testing.assert_allclose(full_mass_matrix(env, [0.3, q2]), expected, atol=3e-9)
    # gravity torque at rest, closed form of the original code
    data = mujoco.MjData(env.model)
    q = np.array([0.4, -1.3])
    data.qpos[:] = q
    mujoco.mj_forward(env.model, data)
    g = 1.82
    s12 = math.sin(q.sum())
    gravity = [g * l2 * m2 * s12 + (m1 + m2) * l1 * g * math.sin(q[0]), g * l2 * m2 * s12]
    np.testing.assert_allclose(data.qfrc_bias, gravity, rtol=1e-12)


def test_analytic_mass_matrix_equals_mujoco(arm):
    import casadi as ca

    from envs.two_link_arm_model import mass_matrix

    q = ca.SX.sym("q", 2)
    mass_fn = ca.Function("M", [q], [mass_matrix(q, arm.params)])
    for qv in np.random.default_rng(0).uniform(-3, 3, (5, 2)):
        np.testing.assert_allclose(np.array(mass_fn(qv)), full_mass_matrix(arm, qv), rtol=1e-12)


# --- exact Jacobians ------------------------------------------------------------------------


def random_states(rng: np.random.Generator, n: int, speed: tuple[float, float]) -> np.ndarray:
    q = rng.uniform(-2.5, 2.5, (n, 2))
    qd = rng.uniform(*speed, (n, 2)) * rng.choice([-1.0, 1.0], (n, 2))
    return np.column_stack([q, qd])


def central_difference_of_env_step(env: TwoLinkArmEnv, x, u, eps=1e-6):
    a_fd = np.column_stack(
        [
            (env_step_from(env, x + eps * e, u) - env_step_from(env, x - eps * e, u)) / (2 * eps)
            for e in np.eye(4)
        ]
    )
    b_fd = np.column_stack(
        [
            (env_step_from(env, x, u + eps * e) - env_step_from(env, x, u - eps * e)) / (2 * eps)
            for e in np.eye(2)
        ]
    )
    return a_fd, b_fd


def test_linearize_matches_central_difference_of_env_step_incl_near_zero_velocity(arm):
    rng = np.random.default_rng(42)
    states = np.vstack(
        [
            random_states(rng, 4, (0.3, 3.0)),  # moving
            random_states(rng, 3, (0.0, 0.01)),  # near zero velocity: friction in stiction zone
            np.array([[0.4, -0.6, 0.0, 0.0], [0.0, 0.0, 0.0, 0.0]]),  # exactly at rest
        ]
    )
    actions = rng.uniform(-0.95, 0.95, (len(states), 2))
    for x, u in zip(states, actions):
        a_jac, b_jac = arm.linearize(x, u)
        a_fd, b_fd = central_difference_of_env_step(arm, x, u)
        scale = np.abs(stacked(a_fd, b_fd)).max()
        np.testing.assert_allclose(
            stacked(a_jac, b_jac), stacked(a_fd, b_fd), rtol=0, atol=1e-7 * scale, err_msg=str(x)
        )


def test_linearize_leaves_the_env_state_untouched_and_trajectory_form_agrees(arm):
    arm.reset(seed=5)
    for _ in range(3):
        arm.step(np.array([0.3, -0.4]))
    before = (arm.data.qpos.copy(), arm.data.qvel.copy(), arm.data.ctrl.copy(), arm.data.time)
    xs = random_states(np.random.default_rng(1), 6, (0.0, 2.0))
    us = np.random.default_rng(2).uniform(-1, 1, (6, 2))
    a_traj, b_traj = arm.linearize_trajectory(xs, us)
    np.testing.assert_array_equal(arm.data.qpos, before[0])
    np.testing.assert_array_equal(arm.data.qvel, before[1])
    np.testing.assert_array_equal(arm.data.ctrl, before[2])
    assert arm.data.time == before[3]
    assert a_traj.shape == (6, 4, 4) and b_traj.shape == (6, 4, 2)
    for k in range(6):
        a_one, b_one = arm.linearize(xs[k], us[k])
        np.testing.assert_array_equal(a_traj[k], a_one)
        np.testing.assert_array_equal(b_traj[k], b_one)


def test_dynamics_model_reproduces_env_steps_bit_for_bit_and_batches(arm):
    model = arm.dynamics_model()
    assert isinstance(model, DynamicsModel)
    assert (model.state_dim, model.action_dim) == (4, 2)
    rng = np.random.default_rng(3)
    xs = random_states(rng, 6, (0.0, 3.0)).reshape(2, 3, 4)
    us = rng.uniform(-1, 1, (2, 3, 2))
    nxt = model.step(xs, us)
    assert nxt.shape == (2, 3, 4)
    for i in range(2):
        for j in range(3):
            np.testing.assert_array_equal(nxt[i, j], env_step_from(arm, xs[i, j], us[i, j]))
    a_jac, b_jac = model.jacobians(xs[0], us[0])
    a_env, b_env = arm.linearize_trajectory(xs[0], us[0])
    np.testing.assert_array_equal(a_jac, a_env)
    np.testing.assert_array_equal(b_jac, b_env)


# --- the analytic CasADi twin ---------------------------------------------------------------


def min_speed_over_substeps(env: TwoLinkArmEnv, x: np.ndarray, u: np.ndarray) -> float:
    data = mujoco.MjData(env.model)
    data.qpos[:], data.qvel[:], data.ctrl[:] = x[:2], x[2:], u
    speed = np.inf
    for _ in range(env.frame_skip):
        speed = min(speed, float(np.abs(data.qvel).min()))
        mujoco.mj_step(env.model, data)
    return min(speed, float(np.abs(data.qvel).min()))


def test_analytic_twin_matches_mujoco_away_from_zero_velocity(arm):
    twin = arm.analytic_model()
    true = arm.dynamics_model()
    rng = np.random.default_rng(7)
    xs = random_states(rng, 60, (0.5, 4.0))
    us = rng.uniform(-1, 1, (60, 2))
    away = np.array([min_speed_over_substeps(arm, x, u) >= 0.2 for x, u in zip(xs, us)])
    assert away.mean() > 0.5  # the premise holds for most draws
    xs, us = xs[away], us[away]
    np.testing.assert_allclose(twin.step(xs, us), true.step(xs, us), rtol=0, atol=1e-10)
    j_twin = stacked(*twin.jacobians(xs, us))
    j_true = stacked(*true.jacobians(xs, us))
    scale = np.abs(j_true).max(axis=(1, 2), keepdims=True)
    assert np.all(np.abs(j_twin - j_true) <= 1e-7 * scale)
    # the continuous model equals MuJoCo's acceleration (friction saturated at these speeds)
    data = mujoco.MjData(arm.model)
    for x, u in zip(xs[:5], us[:5]):
        data.qpos[:], data.qvel[:], data.ctrl[:] = x[:2], x[2:], u
        mujoco.mj_forward(arm.model, data)
        xdot = np.array(twin.casadi_continuous(x, u)).ravel()
        np.testing.assert_allclose(xdot, np.concatenate([x[2:], data.qacc]), rtol=1e-9, atol=1e-9)


def test_analytic_twin_near_zero_velocity_stays_within_the_friction_bound(arm):
    twin = arm.analytic_model()
    true = arm.dynamics_model()
    p = arm.params
    rng = np.random.default_rng(8)
    xs = random_states(rng, 40, (0.0, 0.02))
    us = rng.uniform(-1, 1, (40, 2))
    err = np.abs(twin.step(xs, us) - true.step(xs, us))
    for x, e in zip(xs, err):
        inertia = full_mass_matrix(arm, x[:2]) + p.timestep * np.diag(p.damping)
        bound = (
            p.dt * np.linalg.norm(np.linalg.inv(inertia), 2) * 2 * np.linalg.norm(p.frictionloss)
        )
        assert e[2:].max() <= bound
        assert e[:2].max() <= p.dt * bound
    assert err.max() > 1e-6  # the friction models really differ here (the test is not vacuous)


def test_analytic_continuous_dynamics_equal_the_original_codes_equations_with_tanh_friction():
    """Paper preset against the original code's inverse model (typo fixed), written out here:
    tau = M qdd + c + g + v qd + k tanh(100 qd), i.e. v_s = 0.01 rad/s."""
    twin = TwoLinkArmCasadi(arm_params("paper"))
    m1 = m2 = 0.2
    l1 = l2 = 1.0
    g, v, k = 1.82, 2.0, 0.1
    rng = np.random.default_rng(4)
    for x, a in zip(random_states(rng, 20, (0.0, 0.05)), rng.uniform(-1, 1, (20, 2))):
        q1, q2, qd1, qd2 = x
        c2, s2 = math.cos(q2), math.sin(q2)
        s1, s12 = math.sin(q1), math.sin(q1 + q2)
        mass = np.array(
            [
                [
                    (m1 + m2) * l1**2 + m2 * l2**2 + 2 * m2 * l1 * l2 * c2,
                    m2 * l2**2 + m2 * l1 * l2 * c2,
                ],
                [m2 * l2**2 + m2 * l1 * l2 * c2, m2 * l2**2],
            ]
        ) + 1e-9 * np.array([[2.0, 1.0], [1.0, 1.0]])  # the preset's 1e-9 link inertias
        rest = np.array(
            [
                -m2 * l1 * l2 * s2 * qd2**2
                - 2 * m2 * l1 * l2 * s2 * qd1 * qd2
                + g * l2 * m2 * s12
                + (m1 + m2) * l1 * g * s1
                + v * qd1
                + k * math.tanh(100 * qd1),
                m2 * l1 * l2 * s2 * qd1**2 + g * l2 * m2 * s12 + v * qd2 + k * math.tanh(100 * qd2),
            ]
        )
        qdd = np.linalg.solve(mass, 3.0 * a - rest)
        xdot = np.array(twin.casadi_continuous(x, a)).ravel()
        np.testing.assert_allclose(xdot, np.concatenate([x[2:], qdd]), rtol=1e-10, atol=1e-10)


def test_analytic_jacobians_match_finite_differences_of_the_casadi_step():
    twin = TwoLinkArmCasadi(arm_params("default"))
    rng = np.random.default_rng(9)
    xs = random_states(rng, 5, (0.0, 2.0))
    us = rng.uniform(-1, 1, (5, 2))
    a_jac, b_jac = twin.jacobians(xs, us)
    eps = 1e-6
    for k in range(5):
        a_fd = np.column_stack(
            [
                (twin.step(xs[k] + eps * e, us[k]) - twin.step(xs[k] - eps * e, us[k])) / (2 * eps)
                for e in np.eye(4)
            ]
        )
        b_fd = np.column_stack(
            [
                (twin.step(xs[k], us[k] + eps * e) - twin.step(xs[k], us[k] - eps * e)) / (2 * eps)
                for e in np.eye(2)
            ]
        )
        np.testing.assert_allclose(a_jac[k], a_fd, rtol=1e-6, atol=1e-7)
        np.testing.assert_allclose(b_jac[k], b_fd, rtol=1e-6, atol=1e-7)
    assert twin.step(xs, us).shape == (5, 4)
    np.testing.assert_array_equal(twin.step(xs[2], us[2]), twin.step(xs, us)[2])
    assert np.array(twin.casadi_step(xs[0], us[0])).shape == (4, 1)



def test_buffered_step_and_jacobians_equal_plain_casadi_calls_bit_for_bit():
    """``step``/``jacobians`` evaluate through cached zero-copy ``Function.buffer`` objects (one
    per batch size); they must equal plain per-point calls of ``casadi_step`` and
    ``casadi_jacobians`` exactly, return fresh arrays, and survive changing batch sizes."""
    twin = TwoLinkArmCasadi(arm_params("default"))
    rng = np.random.default_rng(4)
    for n in (11, 1, 3, 11, 1):  # revisit cached buffers after other sizes
        xs = random_states(rng, n, (0.0, 2.0))
        us = rng.uniform(-1, 1, (n, 2))
        ref = np.stack([np.array(twin.casadi_step(xs[k], us[k]))[:, 0] for k in range(n)])
        out = twin.step(xs, us)
        np.testing.assert_array_equal(out, ref)
        kept = out.copy()
        twin.step(xs + 0.1, us)  # must not overwrite the earlier result
        np.testing.assert_array_equal(out, kept)
        a_jac, b_jac = twin.jacobians(xs, us)
        for k in range(n):
            a_ref, b_ref = twin.casadi_jacobians(xs[k], us[k])
            np.testing.assert_array_equal(a_jac[k], np.array(a_ref))
            np.testing.assert_array_equal(b_jac[k], np.array(b_ref))
    # strided views, lists and integer/float32 dtypes are read like float64 copies
    X = random_states(rng, 12, (0.0, 2.0)).reshape(3, 4, 4)
    U = rng.uniform(-1, 1, (3, 4, 2))
    np.testing.assert_array_equal(twin.step(X[:, 1], U[:, 1]),
                                  twin.step(X[:, 1].copy(), U[:, 1].copy()))
    np.testing.assert_array_equal(twin.step(X, U).reshape(-1, 4),
                                  twin.step(X.reshape(-1, 4), U.reshape(-1, 2)))
    np.testing.assert_array_equal(twin.step(X[0, 0].tolist(), U[0, 0].tolist()),
                                  twin.step(X[0, 0], U[0, 0]))
    xi, ui = np.array([1, 0, 0, 0]), np.array([0.5, -0.25], dtype=np.float32)
    np.testing.assert_array_equal(twin.step(xi, ui), twin.step(xi.astype(float),
                                                               ui.astype(float)))
    assert twin.step(np.zeros((0, 4)), np.zeros((0, 2))).shape == (0, 4)
    with pytest.raises(ValueError, match="u contains 1 non-finite"):
        twin.step(X[0], np.where(U[0] == U[0, 2, 1], np.inf, U[0]))


# --- bad input ------------------------------------------------------------------------------


@pytest.mark.parametrize(
    "kwargs, match",
    [
        ({"preset": "nope"}, r"unknown preset 'nope'.*default.*paper"),
        ({"dt": 0.0}, "dt must be"),
        ({"dt": -0.02}, "dt must be"),
        ({"episode_steps": 0}, "episode_steps"),
        ({"params": {"link_mass": (-1.0, 1.0)}}, "link_mass"),
        ({"params": {"mass": 1.0}}, "unknown arm parameter"),
        ({"target_limit": 3.0}, "target_limit"),
        ({"cost_Q": [1.0, 1.0, -1.0, 0.0]}, "cost_Q"),
        ({"render_mode": "human"}, "render_mode"),
    ],
)
def test_bad_constructor_arguments_raise_value_error(kwargs, match):
    with pytest.raises(ValueError, match=match):
        TwoLinkArmEnv(**kwargs)


def test_dt_override_sets_timestep_and_render_fps():
    env = TwoLinkArmEnv(dt=0.01)
    assert env.dt == pytest.approx(0.01)
    assert env.model.opt.timestep == pytest.approx(0.001)
    assert env.metadata["render_fps"] == 100
    clone = pickle.loads(pickle.dumps(env))  # rebuilt from the constructor arguments
    assert clone.dt == pytest.approx(0.01) and clone.preset == "default"


def test_bad_reset_options_raise_value_error():
    env = TwoLinkArmEnv()
    limit = env.joint_limit
    for target in ([limit, 0.0], [0.0, -limit - 0.1], [np.nan, 0.0], [0.1, 0.2, 0.3]):
        with pytest.raises(ValueError, match="target"):
            env.reset(seed=0, options={"target": target})
    with pytest.raises(ValueError, match="state"):
        env.reset(seed=0, options={"state": [0.0, 0.0, np.inf, 0.0]})
    with pytest.raises(ValueError, match="unknown reset option"):
        env.reset(seed=0, options={"goal": [0.0, 0.0]})


_HYPOTHESIS_ENV = TwoLinkArmEnv()


@settings(max_examples=40, deadline=None)
@given(
    action=st.one_of(
        arrays(
            np.float64, st.sampled_from([(2,), (3,), (1,), (2, 1), ()]), elements=st.floats(-5, 5)
        ),
        arrays(np.float64, (2,), elements=st.floats(allow_nan=True, allow_infinity=True)),
    )
)
def test_step_accepts_exactly_finite_actions_of_shape_2(action):
    env = _HYPOTHESIS_ENV
    env.reset(seed=0)
    if action.shape == (2,) and np.all(np.isfinite(action)):
        _, reward, _, _, info = env.step(action)
        assert np.all(np.isfinite(info["state"])) and np.isfinite(reward)
        np.testing.assert_array_equal(env.data.ctrl, np.clip(action, -1, 1))
    else:
        with pytest.raises(ValueError, match="action"):
            env.step(action)


def test_linearize_rejects_bad_shapes_and_non_finite_values():
    env = TwoLinkArmEnv()
    with pytest.raises(ValueError, match="x"):
        env.linearize(np.zeros(3), np.zeros(2))
    with pytest.raises(ValueError, match="u"):
        env.linearize(np.zeros(4), [np.nan, 0.0])
    with pytest.raises(ValueError, match="U"):
        env.linearize_trajectory(np.zeros((5, 4)), np.zeros((4, 2)))
    with pytest.raises(ValueError, match="x"):
        env.analytic_model().step(np.zeros((3, 5)), np.zeros((3, 2)))


# --- rendering ------------------------------------------------------------------------------


def test_rgb_array_rendering_works_headless_and_helpers_write_files(tmp_path):
    import imageio.v2 as imageio

    from envs.rendering import render_episode, save_png_strip, save_video

    env = gym.make("mbtsr/TwoLinkArm-v0", render_mode="rgb_array", width=64, height=48)
    frames = render_episode(env, np.tile([0.8, 0.5], (8, 1)), seed=0)
    assert len(frames) == 9
    assert frames[0].shape == (48, 64, 3) and frames[0].dtype == np.uint8
    assert frames[0].std() > 1.0  # not a blank image
    assert not np.array_equal(frames[0], frames[-1])  # the arm moved
    strip = imageio.imread(save_png_strip(frames, tmp_path / "strip.png", n=3))
    assert strip.shape[:2] == (48, 3 * 64)
    gif = imageio.mimread(save_video(frames, tmp_path / "episode.gif", fps=25))
    assert len(gif) == 9
    with pytest.raises(ValueError, match="gif"):
        save_video(frames, tmp_path / "episode.avi")
    env.close()
