"""``mbtsr/TwoLinkArm-v0``: a two-link arm in a vertical plane reaching a target configuration.

A planar two-link arm (shoulder and elbow hinges) swings in the vertical x-z plane under gravity,
with viscous and Coulomb joint friction and torque-limited motors, simulated by MuJoCo
(``envs/assets/two_link_arm.xml``): the robot benchmark of Bagge Carlson et al. (section 5) with
a reach task on top. State ``[q1, q2, q1dot, q2dot]``, action ``Box(-1, 1, (2,))`` (normalized
torques), observation the state and the target ``[target_q1, target_q2]``; reward the negative
quadratic cost of the next state and the action. Spaces, reward, start state, episode end,
presets, arguments, model access (``dynamics_model``, ``linearize``, ``analytic_model``) and
rendering: docs/environments.md, "mbtsr/TwoLinkArm-v0".
"""

from __future__ import annotations

import math
from collections.abc import Mapping
from pathlib import Path

import mujoco
import numpy as np
from gymnasium import spaces, utils
from gymnasium.envs.mujoco.mujoco_env import MujocoEnv

from envs.mujoco_model import MujocoDynamics
from envs.two_link_arm_model import ArmParams, TwoLinkArmCasadi, arm_params
from mbtsr.validation import as_array, check_choice, check_int, check_nonnegative, check_positive

__all__ = [
    "ASSET_PATH",
    "EXCITATION_STD",
    "MAX_DT",
    "TwoLinkArmEnv",
    "VELOCITY_LIMIT",
    "build_model",
]

ASSET_PATH = Path(__file__).resolve().parent / "assets" / "two_link_arm.xml"

#: Std of the normalized excitation input per preset (envs.collect's default input scale)
EXCITATION_STD = {"default": 0.15, "paper": 1.0 / 3.0}

FD_EPS = 1e-6  # mjd_transitionFD perturbation (centred differences)

#: Largest control period accepted [s] (docs/environments.md, "Presets")
MAX_DT = 0.1
#: A joint speed above this [rad/s] means the simulation diverged (the real arms stay < 50).
VELOCITY_LIMIT = 1e3
_INSTABILITY_WARNINGS = (
    mujoco.mjtWarning.mjWARN_BADQACC,
    mujoco.mjtWarning.mjWARN_BADQPOS,
    mujoco.mjtWarning.mjWARN_BADQVEL,
)


def build_model(p: ArmParams, path: str | Path = ASSET_PATH) -> mujoco.MjModel:
    """Compile the arm's XML with every physical constant taken from ``p`` (via ``MjSpec``)."""
    spec = mujoco.MjSpec.from_file(str(path))
    spec.option.timestep = p.timestep
    spec.option.gravity = [0.0, 0.0, -p.gravity]
    reach = sum(p.link_length)
    radius = 0.035 * reach
    for i, (link, joint) in enumerate((("link1", "shoulder"), ("link2", "elbow"))):
        body = spec.body(link)
        body.mass = p.link_mass[i]
        body.ipos = [0.0, 0.0, -p.com_distance[i]]
        inertia = p.com_inertia[i]
        body.inertia = [inertia, inertia, 0.01 * inertia]  # rod-like; only Iyy acts (planar)
        jnt = spec.joint(joint)
        jnt.damping = [p.damping[i], 0.0, 0.0]
        jnt.frictionloss = p.frictionloss[i]
        jnt.armature = p.armature[i]
        jnt.solref_friction = [2.0 * p.timestep, 1.0]
        geom = spec.geom(link)
        geom.fromto = [0.0, 0.0, 0.0, 0.0, 0.0, -p.link_length[i]]
        geom.size = [radius, 0.0, 0.0]
        spec.actuator(joint).gear = [p.torque_limit[i], 0.0, 0.0, 0.0, 0.0, 0.0]
    spec.body("link2").pos = [0.0, 0.0, -p.link_length[0]]
    spec.site("fingertip").pos = [0.0, 0.0, -p.link_length[1]]
    spec.geom("base").size = [radius * 1.5, 0.0, 0.0]
    spec.geom("target").size = [radius * 1.25, 0.0, 0.0]
    spec.camera("side").pos = [0.0, -2.55 * reach, 0.0]  # fovy 45 deg: sees +-1.05 reach
    spec.geom("backdrop").pos = [0.0, 0.4 * reach, 0.0]
    spec.geom("backdrop").size = [4.0 * reach, 4.0 * reach, 0.1]
    return spec.compile()


def fingertip_position(q: np.ndarray, p: ArmParams) -> np.ndarray:
    """Fingertip in world coordinates ``[x, y, z]`` for joint angles ``q: [2]``."""
    l1, l2 = p.link_length
    return np.array(
        [
            l1 * math.sin(q[0]) + l2 * math.sin(q[0] + q[1]),
            0.0,
            -(l1 * math.cos(q[0]) + l2 * math.cos(q[0] + q[1])),
        ]
    )


def _diag_weights(name: str, value: object, size: int) -> np.ndarray:
    """A ``[size, size]`` diagonal nonnegative cost matrix from a vector or a diagonal matrix."""
    arr = as_array(name, value)
    if arr.shape == (size, size):
        if np.any(arr != np.diag(np.diag(arr))):
            raise ValueError(f"{name} must be diagonal, got {arr.tolist()}")
        arr = np.diag(arr)
    if arr.shape != (size,):
        raise ValueError(f"{name} must be [{size}] or [{size}, {size}], got {list(arr.shape)}")
    if np.any(arr < 0):
        raise ValueError(f"{name} must be nonnegative, got {arr.tolist()}")
    return np.diag(arr)


class TwoLinkArmEnv(MujocoEnv, utils.EzPickle):
    """Two-link arm reach task; docs/environments.md is the manual.

    :param preset: ``"default"`` or ``"paper"``.
    :param episode_steps: steps before truncation (>= 1).
    :param render_mode: ``None`` or ``"rgb_array"``.
    :param dt: control period override [s] (``None``: 0.02).
    :param params: overrides of :class:`~envs.two_link_arm_model.ArmParams` fields.
    :param target_limit: random targets are ``U(-target_limit, target_limit)`` per joint [rad].
    :param joint_limit: targets must satisfy ``|q| < joint_limit`` [rad].
    :param init_noise: half-width of the uniform start-state noise [rad, rad/s].
    :param cost_Q: ``[4]`` or diagonal ``[4, 4]`` state weights.
    :param cost_R: ``[2]`` or diagonal ``[2, 2]`` action weights.
    :param width: rendered image width [px].
    :param height: rendered image height [px].
    """

    metadata = {"render_modes": ["rgb_array"], "render_fps": 50}

    def __init__(
        self,
        preset: str = "default",
        episode_steps: int = 100,
        render_mode: str | None = None,
        *,
        dt: float | None = None,
        params: Mapping | None = None,
        target_limit: float = 0.5 * math.pi,
        joint_limit: float = 0.9 * math.pi,
        init_noise: float = 0.05,
        cost_Q: object = (1.0, 1.0, 0.01, 0.01),  # noqa: N803 - the paper's symbol
        cost_R: object = (0.01, 0.01),  # noqa: N803
        width: int = 320,
        height: int = 240,
    ) -> None:
        # pickled through the constructor arguments (first, and no super() in this method:
        # locals() holds only them here)
        utils.EzPickle.__init__(self, **{k: v for k, v in locals().items() if k != "self"})
        check_choice("render_mode", render_mode, (None, *self.metadata["render_modes"]))
        for name, value in (("episode_steps", episode_steps), ("width", width), ("height", height)):
            check_int(name, value, 1)
        if dt is not None and not check_positive("dt", dt) <= MAX_DT:
            raise ValueError(
                f"dt must be <= MAX_DT={MAX_DT} s (10 Euler substeps per step; larger periods "
                f"make the simulation inaccurate or unstable), got {dt!r}"
            )
        self.params = arm_params(preset, dt=dt, **dict(params or {}))
        self.preset = preset
        self.episode_steps = int(episode_steps)
        self.joint_limit = check_positive("joint_limit", joint_limit)
        self.target_limit = check_nonnegative("target_limit", target_limit)
        if self.target_limit >= self.joint_limit:
            raise ValueError(
                f"target_limit must be < joint_limit={self.joint_limit}, got {target_limit!r}"
            )
        self.init_noise = check_nonnegative("init_noise", init_noise)
        self.cost_Q = _diag_weights("cost_Q", cost_Q, 4)
        self.cost_R = _diag_weights("cost_R", cost_R, 2)
        self.torque_limit = np.array(self.params.torque_limit)
        self.excitation_std = EXCITATION_STD.get(preset, EXCITATION_STD["default"])
        self.metadata = {**type(self).metadata, "render_fps": int(round(1.0 / self.params.dt))}

        MujocoEnv.__init__(
            self,
            str(ASSET_PATH),
            self.params.frame_skip,
            observation_space=spaces.Box(-np.inf, np.inf, shape=(6,), dtype=np.float64),
            render_mode=render_mode,
            width=width,
            height=height,
            camera_name="side",
        )
        self._q_diag = np.diag(self.cost_Q).copy()
        self._r_diag = np.diag(self.cost_R).copy()
        self._scratch = mujoco.MjData(self.model)
        self._target = np.zeros(2)
        self._goal = np.zeros(4)
        self._t = 0
        self._analytic: dict[bool, TwoLinkArmCasadi] = {}
        self._mujoco_model: MujocoDynamics | None = None

    # --- MujocoEnv hooks -------------------------------------------------------------------

    def _initialize_simulation(self) -> tuple[mujoco.MjModel, mujoco.MjData]:
        model = build_model(self.params, self.fullpath)
        model.vis.global_.offwidth = max(model.vis.global_.offwidth, self.width)
        model.vis.global_.offheight = max(model.vis.global_.offheight, self.height)
        return model, mujoco.MjData(model)

    # --- the Gymnasium API -------------------------------------------------------------------

    def _state(self) -> np.ndarray:
        return np.concatenate((self.data.qpos, self.data.qvel))

    def _obs(self, x: np.ndarray) -> np.ndarray:
        return np.concatenate((x, self._target))

    def reset(self, *, seed: int | None = None, options: dict | None = None):
        """Reset; ``options`` may hold ``"target"`` ``[2]`` and/or ``"state"`` ``[4]``."""
        super(MujocoEnv, self).reset(seed=seed)  # gymnasium.Env.reset: seeds np_random
        options = dict(options or {})
        unknown = set(options) - {"target", "state"}
        if unknown:
            raise ValueError(f"unknown reset option(s) {sorted(unknown)}; valid: target, state")
        # draw both, always, so that setting one does not shift the other's random numbers
        target = self.np_random.uniform(-self.target_limit, self.target_limit, size=2)
        x0 = self.np_random.uniform(-self.init_noise, self.init_noise, size=4)
        if "target" in options:
            target = as_array("options['target']", options["target"], (2,))
            if np.any(np.abs(target) >= self.joint_limit):
                raise ValueError(f"options['target'] must satisfy |q| < joint_limit="
                                 f"{self.joint_limit:.4f} rad, got {target.tolist()}")
        if "state" in options:
            x0 = as_array("options['state']", options["state"], (4,))
        mujoco.mj_resetData(self.model, self.data)
        self.data.qpos[:] = x0[:2]
        self.data.qvel[:] = x0[2:]
        self._target = np.array(target, dtype=np.float64)
        self._goal = np.concatenate((self._target, np.zeros(2)))
        self.data.mocap_pos[0] = fingertip_position(self._target, self.params)
        mujoco.mj_forward(self.model, self.data)
        self._t = 0
        x = self._state()
        return self._obs(x), {"state": x, "target": self._target.copy()}

    def _instability_warnings(self) -> int:
        w = self.data.warning
        return sum(int(w[k].number) for k in _INSTABILITY_WARNINGS)

    def step(self, action):
        """Apply the normalized torque ``action`` ``[2]`` for ``dt`` seconds; a diverged
        simulation truncates with ``info["unstable"]`` (docs/environments.md, "Start state,
        targets, episode end")."""
        a = np.clip(as_array("action", action, (2,)), -1.0, 1.0)
        warnings_before = self._instability_warnings()
        self.data.ctrl[:] = a
        mujoco.mj_step(self.model, self.data, nstep=self.frame_skip)
        self._t += 1
        x = self._state()
        err = x - self._goal
        cost_state = float(self._q_diag @ (err * err))
        cost_action = float(self._r_diag @ (a * a))
        info = {
            "state": x,
            "target": self._target.copy(),
            "cost_state": cost_state,
            "cost_action": cost_action,
            "unstable": False,
        }
        truncated = self._t >= self.episode_steps
        reason = None
        if self._instability_warnings() > warnings_before:
            reason = ("MuJoCo reported NaN/inf or huge accelerations or velocities and reset the "
                      "arm (the simulation is unstable)")
        elif not np.all(np.abs(x[2:]) <= VELOCITY_LIMIT):
            reason = f"a joint speed exceeds VELOCITY_LIMIT={VELOCITY_LIMIT:g} rad/s"
        if reason is not None:
            info["unstable"] = True
            info["instability"] = (f"step {self._t} at dt={self.dt:g} s: {reason}; reduce dt "
                                   "or the torque limit")
            truncated = True
        return self._obs(x), -(cost_state + cost_action), False, truncated, info

    def _get_obs(self) -> np.ndarray:  # the MujocoEnv convention (used by envs.mujoco_model)
        return self._obs(self._state())

    def reset_model(self) -> np.ndarray:  # required by MujocoEnv; reset() does the work
        return self._obs(self._state())

    # --- model access ----------------------------------------------------------------------

    @property
    def target(self) -> np.ndarray:
        """The current episode's target joint angles ``[2]``."""
        return self._target.copy()

    def _true_model(self) -> MujocoDynamics:
        if self._mujoco_model is None:
            self._mujoco_model = self.dynamics_model()
        return self._mujoco_model

    def linearize(self, x: object, u: object) -> tuple[np.ndarray, np.ndarray]:
        """Jacobians of one env step at ``(x [4], u [2])``: ``A [4, 4]``, ``B [4, 2]``, by
        :meth:`envs.mujoco_model.MujocoDynamics.jacobians` (the env's state is untouched)."""
        x = as_array("x", x, (4,))
        u = as_array("u", u, (2,))
        A, B = self._true_model().jacobians(x[None], u[None])
        return A[0], B[0]

    def linearize_trajectory(self, X: object, U: object) -> tuple[np.ndarray, np.ndarray]:  # noqa: N803
        """:meth:`linearize` along a trajectory.

        :param X: ``[T, 4]`` states.
        :param U: ``[T, 2]`` normalized actions.
        :return: ``A: [T, 4, 4]``, ``B: [T, 4, 2]``.
        """
        X = as_array("X", X, (None, 4))  # noqa: N806
        U = as_array("U", U, (X.shape[0], 2))  # noqa: N806
        return self._true_model().jacobians(X, U)

    def dynamics_model(self) -> MujocoDynamics:
        """The true MuJoCo model behind this env (:class:`envs.mujoco_model.MujocoDynamics`:
        state ``[q, qdot]`` = the first 4 observation entries, ``mjd_transitionFD`` Jacobians)."""
        return MujocoDynamics(self, jacobian_method="transition_fd", fd_eps=FD_EPS)

    def analytic_model(self, jit: bool = False) -> TwoLinkArmCasadi:
        """The analytic CasADi twin of this env's arm (built once per ``jit`` value, cached);
        ``jit=True`` compiles it to C for planning speed (see ``TwoLinkArmCasadi``)."""
        if bool(jit) not in self._analytic:
            self._analytic[bool(jit)] = TwoLinkArmCasadi(self.params, jit=jit)
        return self._analytic[bool(jit)]
