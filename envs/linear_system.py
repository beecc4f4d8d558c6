"""``mbtsr/LinearSystem-v0``: the paper's random stable discrete-time linear system.

``x_{t+1} = A x_t + B u_t`` with ``(A, B)`` from :func:`random_stable_system` (the paper's
Algorithm 2), the same for the same ``system_seed``; reward ``-(x_{t+1}^T x_{t+1} + r u^T u)``.
Spaces, reward, start state, episode end, arguments and model access (``A``, ``B``,
``linearize``, ``dynamics_model``): docs/environments.md, "mbtsr/LinearSystem-v0".
"""

from __future__ import annotations

import gymnasium as gym
import numpy as np
import scipy.linalg
from gymnasium import spaces

from mbtsr.dynamics import LinearDynamics
from mbtsr.validation import as_array, check_int, check_nonnegative, check_positive

__all__ = ["LinearSystemEnv", "random_stable_system"]


def random_stable_system(
    n: int = 10,
    m: int = 10,
    dt: float = 0.02,
    seed: int | np.random.Generator | None = 1,
) -> tuple[np.ndarray, np.ndarray]:
    """The paper's random, "slightly" stable discrete-time system (Algorithm 2).

    :param n: state dimension.
    :param m: input dimension.
    :param dt: sample time [s] (> 0); the eigenvalues of ``A`` have modulus ``exp(-dt^2)``.
    :param seed: int or ``numpy.random.Generator``; ``A0`` is drawn before ``B``.
    :return: ``A: [n, n]``, ``B: [n, m]``.
    """
    n, m = check_int("n", n, 1), check_int("m", m, 1)
    dt = check_positive("dt", dt)
    rng = np.random.default_rng(seed)
    a0 = rng.standard_normal((n, n))
    a_cont = a0 - a0.T - dt * np.eye(n)
    a_disc = scipy.linalg.expm(dt * a_cont)
    b_disc = dt * rng.standard_normal((n, m))
    return a_disc, b_disc


class LinearSystemEnv(gym.Env):
    """Random stable linear system; docs/environments.md is the manual.

    :param n: state dimension.
    :param m: input dimension.
    :param dt: sample time [s].
    :param system_seed: seed of ``(A, B)`` (independent of the reset seed).
    :param episode_steps: steps before truncation.
    :param action_bound: symmetric action bound (> 0).
    :param control_cost: ``r`` in the reward (>= 0).
    """

    metadata = {"render_modes": []}

    def __init__(
        self,
        n: int = 10,
        m: int = 10,
        dt: float = 0.02,
        system_seed: int = 1,
        episode_steps: int = 200,
        action_bound: float = 50.0,
        control_cost: float = 1e-3,
    ) -> None:
        self.A, self.B = random_stable_system(n, m, dt, system_seed)
        self.n, self.m = self.B.shape
        self.dt = float(dt)
        self.system_seed = system_seed
        self.episode_steps = check_int("episode_steps", episode_steps, 1)
        self.action_bound = check_positive("action_bound", action_bound)
        self.control_cost = check_nonnegative("control_cost", control_cost)
        self.cost_Q = np.eye(self.n)
        self.cost_R = self.control_cost * np.eye(self.m)
        # the paper's linear-system input: 5-tap moving average of 10 N(0, 1) (std 4.47)
        self.excitation_kwargs = {"filtered_gaussian": {"window": 5, "scale": 10.0}}
        self.observation_space = spaces.Box(-np.inf, np.inf, shape=(self.n,), dtype=np.float64)
        self.action_space = spaces.Box(
            -self.action_bound, self.action_bound, shape=(self.m,), dtype=np.float64
        )
        self._x = np.zeros(self.n)
        self._t = 0

    def reset(self, *, seed: int | None = None, options: dict | None = None):
        """Reset to ``x0 ~ N(0, I)`` or ``options["state"]``."""
        super().reset(seed=seed)
        options = dict(options or {})
        unknown = set(options) - {"state"}
        if unknown:
            raise ValueError(f"unknown reset option(s) {sorted(unknown)}; valid: state")
        x0 = self.np_random.standard_normal(self.n)
        if "state" in options:
            x0 = as_array("options['state']", options["state"], (self.n,))
        self._x = np.array(x0, dtype=np.float64)
        self._t = 0
        return self._x.copy(), {"state": self._x.copy()}

    def step(self, action):
        """``x <- A x + B clip(u)``."""
        u = np.clip(as_array("action", action, (self.m,)), -self.action_bound, self.action_bound)
        self._x = self.A @ self._x + self.B @ u
        self._t += 1
        cost_state = float(self._x @ self._x)
        cost_action = float(self.control_cost * (u @ u))
        info = {"state": self._x.copy(), "cost_state": cost_state, "cost_action": cost_action}
        truncated = self._t >= self.episode_steps
        return self._x.copy(), -(cost_state + cost_action), False, truncated, info

    def linearize(self, x: object, u: object) -> tuple[np.ndarray, np.ndarray]:
        """``(A, B)`` (copies) at any ``x: [n]``, ``u: [m]`` (validated)."""
        as_array("x", x, (self.n,))
        as_array("u", u, (self.m,))
        return self.A.copy(), self.B.copy()

    def linearize_trajectory(self, X: object, U: object) -> tuple[np.ndarray, np.ndarray]:  # noqa: N803
        """``X: [T, n]``, ``U: [T, m]`` -> ``A: [T, n, n]``, ``B: [T, n, m]``."""
        return self.dynamics_model().jacobians(X, U)

    def dynamics_model(self) -> LinearDynamics:
        """The true model as :class:`mbtsr.dynamics.LinearDynamics`."""
        return LinearDynamics(self.A, self.B)
