"""The true dynamics of any Gymnasium MuJoCo env as a planning model.

:class:`MujocoDynamics` (state ``concat(qpos, qvel)``, one ``step`` = one ``env.step``, batched;
``mjd_transitionFD`` or batched finite-difference Jacobians), :class:`ObservedDynamics` (the
env's observation carried in the state, for costs written on observations) and
:class:`HybridDynamics`. The manual: docs/environments.md, "The true model of any MuJoCo env".
"""

from __future__ import annotations

import copy

import mujoco
import numpy as np
from mujoco import rollout

from mbtsr.dynamics import LINE_SEARCH_CHUNKS, check_step_inputs
from mbtsr.validation import as_array, check_choice, check_positive

__all__ = [
    "HybridDynamics",
    "MujocoDynamics",
    "ObservedDynamics",
    "state_of",
    "transition_jacobians",
]

_INTEGRATORS = {
    "euler": mujoco.mjtIntegrator.mjINT_EULER,
    "rk4": mujoco.mjtIntegrator.mjINT_RK4,
    "implicit": mujoco.mjtIntegrator.mjINT_IMPLICIT,
    "implicitfast": mujoco.mjtIntegrator.mjINT_IMPLICITFAST,
}
_SPEC = mujoco.mjtState.mjSTATE_FULLPHYSICS
_LOOP_MAX = 8  # batches up to this size step in a Python loop of mj_step, larger ones via rollout


def _unwrap(env):
    base = getattr(env, "unwrapped", env)
    if not (hasattr(base, "model") and hasattr(base, "data") and hasattr(base, "frame_skip")):
        raise TypeError(f"env must be a Gymnasium MujocoEnv (with model, data, frame_skip), got "
                        f"{type(base).__name__}")
    return base


def state_of(env) -> np.ndarray:
    """The current state ``concat(qpos, qvel)`` ``[nq + nv]`` of a live MuJoCo env."""
    base = _unwrap(env)
    return np.concatenate((base.data.qpos, base.data.qvel))


def transition_jacobians(
    model: mujoco.MjModel,
    scratch: mujoco.MjData,
    x: np.ndarray,
    u: np.ndarray,
    frame_skip: int,
    eps: float,
    out_a: np.ndarray,
    out_b: np.ndarray,
) -> None:
    """Jacobians of ``frame_skip`` substeps (control held) by chaining ``mjd_transitionFD``.

    :param scratch: an ``MjData`` of ``model``, overwritten (its mocap etc. are kept).
    :param x: ``[2 nv]`` state (``nq == nv``); ``u: [nu]``.
    :param out_a: ``[2 nv, 2 nv]`` and ``out_b: [2 nv, nu]`` outputs, written in place.
    """
    nv, nu = model.nv, model.nu
    a_k = np.empty((2 * nv, 2 * nv))
    b_k = np.empty((2 * nv, nu))
    out_a[:] = np.eye(2 * nv)
    out_b[:] = 0.0
    scratch.time = 0.0
    scratch.qpos[:] = x[:nv]
    scratch.qvel[:] = x[nv:]
    scratch.qacc_warmstart[:] = 0.0
    scratch.ctrl[:] = u
    for _ in range(frame_skip):
        mujoco.mjd_transitionFD(model, scratch, eps, True, a_k, b_k, None, None)
        np.matmul(a_k, out_a, out=out_a)
        out_b[:] = a_k @ out_b + b_k
        mujoco.mj_step(model, scratch)


class MujocoDynamics:
    """True dynamics of a Gymnasium MuJoCo env (docs/environments.md).

    :param env: a ``MujocoEnv`` (or a wrapper of one); its model is copied, not shared.
    :param integrator: ``None`` (the env's), ``"euler"``, ``"rk4"``, ``"implicit"`` or
        ``"implicitfast"``.
    :param jacobian_method: ``"auto"``, ``"transition_fd"`` or ``"fd"``.
    :param fd_eps: finite-difference step (absolute, per coordinate).

    ``line_search_chunks``: ``N`` steps cost ``N`` simulations (docs/ilqr.md, step 4).
    """

    line_search_chunks = LINE_SEARCH_CHUNKS

    def __init__(
        self,
        env,
        *,
        integrator: str | None = None,
        jacobian_method: str = "auto",
        fd_eps: float = 1e-6,
    ) -> None:
        base = _unwrap(env)
        self.model = copy.deepcopy(base.model)
        if integrator is not None:
            self.model.opt.integrator = _INTEGRATORS[check_choice("integrator", integrator,
                                                                  _INTEGRATORS)]
        if self.model.na:
            raise ValueError(
                f"env has {self.model.na} actuator activation state(s); MujocoDynamics supports "
                "state = (qpos, qvel) only"
            )
        self.fd_eps = check_positive("fd_eps", fd_eps)
        self.frame_skip = int(base.frame_skip)
        self.dt = float(self.model.opt.timestep) * self.frame_skip
        self.nq, self.nv = self.model.nq, self.model.nv
        self.state_dim = self.nq + self.nv
        self.action_dim = self.model.nu
        is_rk4 = self.model.opt.integrator == mujoco.mjtIntegrator.mjINT_RK4
        transition_ok = not is_rk4 and self.nq == self.nv
        check_choice("jacobian_method", jacobian_method, ("auto", "transition_fd", "fd"))
        if jacobian_method == "auto":
            jacobian_method = "transition_fd" if transition_ok else "fd"
        if jacobian_method == "transition_fd" and not transition_ok:
            raise ValueError(
                "jacobian_method='transition_fd' needs a non-RK4 integrator and nq == nv "
                f"(integrator {mujoco.mjtIntegrator(self.model.opt.integrator).name}, "
                f"nq={self.nq}, nv={self.nv}); use 'fd'"
            )
        self.jacobian_method = jacobian_method
        self._data, self._scratch = mujoco.MjData(self.model), mujoco.MjData(self.model)
        self._nstate = mujoco.mj_stateSize(self.model, _SPEC)
        self._template = np.empty(self._nstate)  # full-physics state: the env's mocap, time 0
        self.set_mocap(base.data.mocap_pos, base.data.mocap_quat)
        self._qpos0 = mujoco.mj_stateSize(self.model, mujoco.mjtState.mjSTATE_TIME)
        self._obs_scratch: dict[int, tuple] = {}  # id(env) -> (its model, a private MjData)

    def set_mocap(self, pos: np.ndarray, quat: np.ndarray | None = None) -> None:
        """Set the held mocap body poses (``[nmocap, 3]``, ``[nmocap, 4]``), e.g. a target."""
        self._scratch.mocap_pos[:] = as_array("pos", pos, (self.model.nmocap, 3))
        if quat is not None:
            self._scratch.mocap_quat[:] = as_array("quat", quat, (self.model.nmocap, 4))
        mujoco.mj_getState(self.model, self._scratch, self._template, _SPEC)
        self._template[0] = 0.0

    def _rollout_final(self, xs: np.ndarray, us: np.ndarray) -> np.ndarray:
        """States after ``frame_skip`` substeps: ``xs: [N, n]``, ``us: [N, m]`` -> ``[N, n]``."""
        N = xs.shape[0]
        state0 = np.empty((N, self._nstate))
        state0[:] = self._template
        state0[:, self._qpos0 : self._qpos0 + self.state_dim] = xs
        if N <= _LOOP_MAX:  # cheaper than rollout's wrapper
            d, model, out = self._data, self.model, np.empty((N, self.state_dim))
            for i in range(N):
                mujoco.mj_setState(model, d, state0[i], _SPEC)
                d.qacc_warmstart[:] = 0.0
                d.ctrl[:] = us[i]
                mujoco.mj_step(model, d, nstep=self.frame_skip)
                out[i, : self.nq] = d.qpos
                out[i, self.nq :] = d.qvel
            return out
        states, _ = rollout.rollout(
            self.model, self._data, state0, us[:, None, :], nstep=self.frame_skip
        )
        return states[:, -1, self._qpos0 : self._qpos0 + self.state_dim]

    def step(self, x: np.ndarray, u: np.ndarray, t: int | None = None) -> np.ndarray:
        """Next state, batched: ``x: [..., n]``, ``u: [..., m]`` -> ``[..., n]``."""
        return self._step(*check_step_inputs(x, u, self.state_dim, self.action_dim))

    def _step(self, x: np.ndarray, u: np.ndarray, t: int | None = None) -> np.ndarray:
        """:meth:`step` without input checks (for solvers that validated once): float64
        ``x: [..., n]``, ``u: [..., m]`` with equal batch dims, finite."""
        n = self.state_dim
        batch = x.shape[:-1]
        return self._rollout_final(
            x.reshape(-1, n), u.reshape(-1, self.action_dim)
        ).reshape(*batch, n)

    def jacobians(self, x: np.ndarray, u: np.ndarray, t: int = 0) -> tuple[np.ndarray, np.ndarray]:
        """``A_t = d step / dx``, ``B_t = d step / du``: ``x: [T, n]``, ``u: [T, m]`` ->
        ``([T, n, n], [T, n, m])``."""
        n, m = self.state_dim, self.action_dim
        x = as_array("x", x, (None, n))
        u = as_array("u", u, (x.shape[0], m))
        T = x.shape[0]
        A, B = np.empty((T, n, n)), np.empty((T, n, m))
        if self.jacobian_method == "transition_fd":
            for k in range(T):  # mjd_transitionFD has no batched form
                transition_jacobians(
                    self.model, self._scratch, x[k], u[k], self.frame_skip, self.fd_eps, A[k], B[k]
                )
            return A, B
        return self._fd_jacobians(x, u)

    def _fd_jacobians(self, x: np.ndarray, u: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
        """Centred differences of whole steps, all perturbations in one batched rollout.

        Controls are perturbed inside ``ctrlrange`` (one-sided at a bound), as MuJoCo does.
        """
        T, n = x.shape
        m = u.shape[1]
        eps = self.fd_eps
        p = n + m
        xs = np.repeat(x[:, None, :], 2 * p, axis=1)  # [T, 2p, n]
        us = np.repeat(u[:, None, :], 2 * p, axis=1)  # [T, 2p, m]
        idx = np.arange(n)
        xs[:, idx, idx] += eps
        xs[:, p + idx, idx] -= eps
        # control steps, one-sided at a limited bound (the env clamps beyond it)
        hi_step = np.full((T, m), eps)
        lo_step = np.full((T, m), eps)
        limited = self.model.actuator_ctrllimited.astype(bool)
        if limited.any():
            lo_c, hi_c = self.model.actuator_ctrlrange[:, 0], self.model.actuator_ctrlrange[:, 1]
            uc = np.clip(u, lo_c, hi_c)
            hi_step = np.where(limited & (uc + eps > hi_c), 0.0, hi_step)
            lo_step = np.where(limited & (uc - eps < lo_c), 0.0, lo_step)
            us = np.repeat(uc[:, None, :], 2 * p, axis=1)
        jdx = np.arange(m)
        us[:, n + jdx, jdx] += hi_step
        us[:, p + n + jdx, jdx] -= lo_step
        out = self._rollout_final(xs.reshape(-1, n), us.reshape(-1, m)).reshape(T, 2, p, n)
        J = (out[:, 0] - out[:, 1]).transpose(0, 2, 1)  # [T, n, p]
        J[:, :, :n] /= 2 * eps
        J[:, :, n:] /= (hi_step + lo_step)[:, None, :]
        return np.ascontiguousarray(J[:, :, :n]), np.ascontiguousarray(J[:, :, n:])

    def observation(self, env, x: np.ndarray) -> np.ndarray:
        """The env's observation at state ``x`` (``[n]`` or ``[N, n]``), by the env's own
        ``_get_obs`` on a private copy of its ``data`` (the env is not modified). The copy is
        made once per env and takes the env's mocap poses and controls at every call."""
        base = _unwrap(env)
        x = as_array("x", x)
        single = x.ndim == 1
        xs = as_array("x", x.reshape(-1, x.shape[-1]), (None, self.state_dim))
        saved = base.data
        scratch = self._obs_scratch.get(id(base))
        if scratch is None or scratch[0] is not base.model:
            scratch = (base.model, copy.copy(saved))
            self._obs_scratch[id(base)] = scratch
        data = scratch[1]
        data.mocap_pos[:] = saved.mocap_pos
        data.mocap_quat[:] = saved.mocap_quat
        data.ctrl[:] = saved.ctrl
        obs = np.empty((xs.shape[0],) + np.shape(base._get_obs()))
        try:
            base.data = data
            for i, row in enumerate(xs):
                data.qpos[:] = row[: self.nq]
                data.qvel[:] = row[self.nq :]
                mujoco.mj_forward(base.model, data)
                obs[i] = base._get_obs()
        finally:
            base.data = saved
        return obs[0] if single else obs


class HybridDynamics:
    """``step`` of one model, ``jacobians`` of another (same ``state_dim``/``action_dim``): e.g.
    MuJoCo's steps with the arm's analytic Jacobians (docs/environments.md, "dynamics_model()").
    """

    def __init__(self, step_model, jacobian_model) -> None:
        for attr in ("state_dim", "action_dim"):
            a, b = getattr(step_model, attr), getattr(jacobian_model, attr)
            if a != b:
                raise ValueError(f"{attr} differs: step model {a}, jacobian model {b}")
        self.step_model, self.jacobian_model = step_model, jacobian_model
        self.state_dim, self.action_dim = step_model.state_dim, step_model.action_dim
        self.dt = getattr(step_model, "dt", None)
        self.line_search_chunks = getattr(step_model, "line_search_chunks", None)
        self._step = getattr(step_model, "_step", step_model.step)
        self.step = step_model.step
        self.jacobians = jacobian_model.jacobians


class ObservedDynamics:
    """A :class:`MujocoDynamics` with the env's observation carried in the state.

    State ``z = [x (n), obs (d)]``, ``obs = observation(x)`` (the env's ``_get_obs``);
    ``step(z, u) = [x', observation(x')]``; ``A_z = [[A, 0], [C A, 0]]``, ``B_z = [B; C B]``,
    ``C = d observation / dx`` at ``x'``; ``affine`` is ``(C, c)`` for an affine observation,
    else ``None`` (docs/environments.md, "The true model of any MuJoCo env").

    :param dynamics: the true model. :param env: the env whose ``_get_obs`` defines the map
        (only read: its ``data`` is swapped for a copy during each evaluation, then restored).
    """

    line_search_chunks = LINE_SEARCH_CHUNKS

    def __init__(self, dynamics: MujocoDynamics, env, *, fd_eps: float = 1e-6) -> None:
        if not isinstance(dynamics, MujocoDynamics):
            raise TypeError(f"dynamics must be a MujocoDynamics, got {type(dynamics).__name__}")
        self.dynamics, self.env, self.fd_eps = dynamics, env, check_positive("fd_eps", fd_eps)
        self.n = dynamics.state_dim
        self.obs_dim = int(np.asarray(dynamics.observation(env, np.zeros(self.n))).shape[0])
        self.state_dim = self.n + self.obs_dim
        self.action_dim = dynamics.action_dim
        self.dt = dynamics.dt
        self.affine = self._affine_observation()

    def _affine_observation(self) -> tuple[np.ndarray, np.ndarray] | None:
        """``(C [d, n], c [d])`` if ``observation(x) = C x + c`` at 8 random states (qpos
        spread 1, qvel spread 30 around ``qpos0``, 0) to 1e-9 relative, else ``None``."""
        model, n = self.dynamics.model, self.n
        x0 = np.concatenate((model.qpos0, np.zeros(model.nv)))
        rng = np.random.default_rng(0)
        scale = np.concatenate((np.ones(model.nq), np.full(model.nv, 30.0)))
        probes = x0 + rng.standard_normal((8, n)) * scale
        o = self.dynamics.observation(self.env, np.vstack((x0, x0 + np.eye(n), probes)))
        C = (o[1 : n + 1] - o[0]).T  # exact for an affine map (unit steps)
        want = o[0] + (probes - x0) @ C.T
        if not np.allclose(o[n + 1 :], want, rtol=1e-9, atol=1e-9):
            return None
        return C, o[0] - C @ x0

    def lift(self, x: np.ndarray) -> np.ndarray:
        """``x [n] -> z = [x, observation(x)] [n + d]``."""
        x = as_array("x", x, (self.n,))
        return np.concatenate((x, self.dynamics.observation(self.env, x)))

    def _observe(self, xs: np.ndarray) -> np.ndarray:
        """``xs [N, n] -> [N, d]`` (finite input)."""
        if self.affine is not None:
            C, c = self.affine
            return xs @ C.T + c
        return np.asarray(self.dynamics.observation(self.env, xs), dtype=float).reshape(
            xs.shape[0], self.obs_dim)

    def step(self, z: np.ndarray, u: np.ndarray, t: int | None = None) -> np.ndarray:
        """``z: [..., n + d]``, ``u: [..., m]`` -> ``[..., n + d]``."""
        return self._step(*check_step_inputs(z, u, self.state_dim, self.action_dim))

    def _step(self, z: np.ndarray, u: np.ndarray, t: int | None = None) -> np.ndarray:
        batch = z.shape[:-1]
        xs = self.dynamics._step(z.reshape(-1, self.state_dim)[:, : self.n],
                                 u.reshape(-1, self.action_dim))
        return np.concatenate((xs, self._observe(xs)), axis=1).reshape(*batch, self.state_dim)

    def observation_jacobian(self, xs: np.ndarray) -> np.ndarray:
        """``C = d observation / dx`` at each state: ``xs [T, n] -> [T, d, n]`` (the affine map's
        ``C``, else centred differences of step ``fd_eps`` per raw coordinate)."""
        xs = as_array("xs", xs, (None, self.n))
        T, n, d, eps = xs.shape[0], self.n, self.obs_dim, self.fd_eps
        if self.affine is not None:
            return np.broadcast_to(self.affine[0], (T, d, n))
        pert = np.repeat(xs[:, None, :], 2 * n, axis=1)  # [T, 2n, n]
        idx = np.arange(n)
        pert[:, idx, idx] += eps
        pert[:, n + idx, idx] -= eps
        o = self._observe(pert.reshape(-1, n)).reshape(T, 2, n, d)
        return (o[:, 0] - o[:, 1]).transpose(0, 2, 1) / (2 * eps)

    def jacobians(self, z: np.ndarray, u: np.ndarray, t: int = 0) -> tuple[np.ndarray, np.ndarray]:
        """``z: [T, n + d]``, ``u: [T, m]`` -> ``(A_z [T, n+d, n+d], B_z [T, n+d, m])``."""
        z = as_array("z", z, (None, self.state_dim))
        u = as_array("u", u, (z.shape[0], self.action_dim))
        T, n, d = z.shape[0], self.n, self.obs_dim
        x = z[:, :n]
        A, B = self.dynamics.jacobians(x, u)
        C = self.observation_jacobian(self.dynamics._step(x, u) if self.affine is None else x)
        Az = np.zeros((T, n + d, n + d))
        Az[:, :n, :n] = A
        Az[:, n:, :n] = C @ A
        Bz = np.concatenate((B, C @ B), axis=1)
        return Az, Bz
