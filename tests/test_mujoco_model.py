"""envs.mujoco_model: the true dynamics of any Gymnasium MuJoCo env.

``step`` against ``env.step`` (bit for bit, with the env's solver warm start zeroed: the model is
a pure function of (x, u)); Jacobians against independent central differences of ``env.step``
itself (RK4 Reacher, the Euler arm); the observation map against the env's observations.
"""

from __future__ import annotations

import gymnasium as gym
import mujoco
import numpy as np
import pytest

import envs  # noqa: F401  (registers mbtsr/TwoLinkArm-v0)
from envs.mujoco_model import HybridDynamics, MujocoDynamics, state_of

ENVS = ["Reacher-v5", "InvertedPendulum-v5", "mbtsr/TwoLinkArm-v0"]


def env_step_from(env, x: np.ndarray, u: np.ndarray) -> np.ndarray:
    """One ``env.step`` from state ``x`` (set in the env's own data), returning the next state."""
    base = env.unwrapped
    base.data.qpos[:] = x[: base.model.nq]
    base.data.qvel[:] = x[base.model.nq :]
    base.data.qacc_warmstart[:] = 0.0
    env.step(u)
    return state_of(env)


@pytest.mark.parametrize("env_id", ENVS)
def test_step_equals_env_step_bit_for_bit_and_batches(env_id):
    env = gym.make(env_id)
    env.reset(seed=0)
    model = MujocoDynamics(env)
    rng = np.random.default_rng(0)
    xs, us, nexts = [], [], []
    for _ in range(20):
        x = state_of(env)
        u = rng.uniform(-1, 1, model.action_dim)
        env.unwrapped.data.qacc_warmstart[:] = 0.0
        env.step(u)
        xs.append(x)
        us.append(u)
        nexts.append(state_of(env))
        np.testing.assert_array_equal(model.step(x, u), nexts[-1])
    batched = model.step(np.array(xs).reshape(4, 5, -1), np.array(us).reshape(4, 5, -1))
    np.testing.assert_array_equal(batched.reshape(20, -1), np.array(nexts))


@pytest.mark.parametrize("env_id", ENVS)
def test_observation_map_reproduces_env_observations(env_id):
    env = gym.make(env_id)
    env.reset(seed=1)
    model = MujocoDynamics(env)
    rng = np.random.default_rng(1)
    for _ in range(5):
        obs, *_ = env.step(rng.uniform(-1, 1, model.action_dim))
        mapped = model.observation(env, state_of(env))
        if env_id == "Reacher-v5":
            # the env reads body positions from before the last substep (mj_step's kinematics);
            # the map is the env's _get_obs on consistent kinematics (mj_forward) of the state
            assert np.abs(mapped - obs).max() < 1e-4
            mujoco.mj_forward(env.unwrapped.model, env.unwrapped.data)
            obs = env.unwrapped._get_obs()
        np.testing.assert_array_equal(mapped, obs)
    x = state_of(env)
    env.step(np.zeros(model.action_dim))
    before = state_of(env).copy()
    model.observation(env, np.stack([x, x]))  # does not touch the env's simulation
    np.testing.assert_array_equal(state_of(env), before)


def central_differences(env, x, u, eps_x=1e-6, eps_u=1e-6):
    """Jacobians of ``env.step`` itself (independent of MujocoDynamics)."""
    n, m = x.size, u.size
    A, B = np.empty((n, n)), np.empty((n, m))
    for i in range(n):
        d = np.zeros(n)
        d[i] = eps_x
        A[:, i] = (env_step_from(env, x + d, u) - env_step_from(env, x - d, u)) / (2 * eps_x)
    for j in range(m):
        d = np.zeros(m)
        d[j] = eps_u
        B[:, j] = (env_step_from(env, x, u + d) - env_step_from(env, x, u - d)) / (2 * eps_u)
    return A, B


@pytest.mark.parametrize(
    "env_id,method",
    [
        ("Reacher-v5", "auto"),  # RK4 -> batched finite differences of whole steps
        ("mbtsr/TwoLinkArm-v0", "auto"),  # Euler -> chained mjd_transitionFD
        ("mbtsr/TwoLinkArm-v0", "fd"),
    ],
)
def test_jacobians_match_central_differences_of_env_step(env_id, method):
    env = gym.make(env_id)
    env.reset(seed=2)
    model = MujocoDynamics(env, jacobian_method=method)
    expected = {"Reacher-v5": "fd", "mbtsr/TwoLinkArm-v0": "transition_fd"}[env_id]
    assert model.jacobian_method == (expected if method == "auto" else method)
    rng = np.random.default_rng(2)
    X, U = [], []
    for _ in range(4):  # moving states (the arm's dry friction is smooth away from qd = 0)
        for _ in range(3):
            env.step(rng.uniform(-0.8, 0.8, model.action_dim))
        x = state_of(env)
        if env_id == "mbtsr/TwoLinkArm-v0":
            x[2:] = rng.choice([-1, 1], 2) * rng.uniform(0.5, 2.0, 2)
        X.append(x)
        U.append(rng.uniform(-0.8, 0.8, model.action_dim))
    X, U = np.array(X), np.array(U)
    A, B = model.jacobians(X, U)
    for k in range(len(X)):
        A_ref, B_ref = central_differences(env, X[k], U[k])
        scale = max(np.abs(A_ref).max(), np.abs(B_ref).max())
        np.testing.assert_allclose(A[k], A_ref, rtol=0, atol=1e-6 * scale)
        np.testing.assert_allclose(B[k], B_ref, rtol=0, atol=1e-6 * scale)


def test_rk4_integrator():
    env = gym.make("mbtsr/TwoLinkArm-v0")
    env.reset(seed=3)
    rk4 = MujocoDynamics(env, integrator="rk4")
    assert rk4.jacobian_method == "fd"
    euler = MujocoDynamics(env)
    x, u = np.array([0.3, -0.2, 1.0, -1.5]), np.array([0.4, -0.3])
    # both integrate the same ODE: close, not equal; the env's model is unchanged
    assert 0 < np.abs(rk4.step(x, u) - euler.step(x, u)).max() < 1e-2
    assert env.unwrapped.model.opt.integrator == euler.model.opt.integrator
    with pytest.raises(ValueError, match="transition_fd"):
        MujocoDynamics(env, integrator="rk4", jacobian_method="transition_fd")


def test_bad_input_is_named():
    env = gym.make("Reacher-v5")
    env.reset(seed=0)
    model = MujocoDynamics(env)
    with pytest.raises(ValueError, match="x"):
        model.step(np.zeros(7), np.zeros(2))
    with pytest.raises(ValueError, match="u"):
        model.step(np.zeros(8), np.array([np.nan, 0.0]))
    with pytest.raises(ValueError, match="u"):
        model.jacobians(np.zeros((3, 8)), np.zeros((2, 2)))
    with pytest.raises(ValueError, match="integrator"):
        MujocoDynamics(env, integrator="verlet")
    with pytest.raises(TypeError, match="MujocoEnv"):
        MujocoDynamics(gym.make("Pendulum-v1"))


def test_hybrid_uses_analytic_jacobians_and_true_steps():
    env = gym.make("mbtsr/TwoLinkArm-v0")
    env.reset(seed=0)
    true, analytic = MujocoDynamics(env), env.unwrapped.analytic_model()
    hybrid = HybridDynamics(true, analytic)
    x, u = np.array([[0.3, -0.2, 1.0, -1.5]]), np.array([[0.4, -0.3]])
    np.testing.assert_array_equal(hybrid.step(x, u), true.step(x, u))
    A_h, _ = hybrid.jacobians(x, u)
    A_t, _ = true.jacobians(x, u)
    np.testing.assert_array_equal(A_h, analytic.jacobians(x, u)[0])
    np.testing.assert_allclose(A_h, A_t, rtol=0, atol=1e-6 * np.abs(A_t).max())


def test_jit_analytic_twin_equals_the_symbolic_one():
    from envs.two_link_arm_model import TwoLinkArmCasadi, arm_params

    p = arm_params("default")
    plain, jitted = TwoLinkArmCasadi(p), TwoLinkArmCasadi(p, jit=True)
    rng = np.random.default_rng(4)
    X, U = rng.uniform(-2, 2, (7, 4)), rng.uniform(-1, 1, (7, 2))
    np.testing.assert_allclose(jitted.step(X, U), plain.step(X, U), rtol=1e-12, atol=1e-12)
    for a, b in zip(jitted.jacobians(X, U), plain.jacobians(X, U)):
        np.testing.assert_allclose(a, b, rtol=1e-10, atol=1e-10 * np.abs(b).max())
