"""Physical constants of the two-link arm and its analytic CasADi twin.

``q = 0`` is hanging straight down. The equations of motion (Spong et al., ch. 7), the Euler
substeps, the tanh Coulomb smoothing and the agreement with the MuJoCo env: docs/environments.md,
"analytic_model(): the CasADi twin".
"""

from __future__ import annotations

from dataclasses import asdict, dataclass, fields, replace

import casadi as ca
import numpy as np

from mbtsr.costs import casadi_jit_options
from mbtsr.dynamics import check_step_inputs
from mbtsr.validation import as_array, check_int, check_nonnegative, check_positive

__all__ = [
    "ArmParams",
    "PRESETS",
    "TwoLinkArmCasadi",
    "arm_params",
    "mass_matrix",
    "bias_torque",
    "continuous_dynamics",
    "euler_substep",
]


@dataclass(frozen=True)
class ArmParams:
    """Physical constants of the two-link arm, SI units; pairs are ``(link 1, link 2)``.

    :param link_mass: ``m_i`` [kg].
    :param link_length: ``l_i`` [m] (joint to joint / to the fingertip).
    :param com_distance: ``r_i`` [m], joint to the link's centre of mass.
    :param com_inertia: ``I_i`` [kg m^2] about the centre of mass, around the joint axis. MuJoCo
        needs it > 0; the paper preset uses 1e-9 for its point masses (the twin includes it too).
    :param armature: reflected rotor inertia added to the joint [kg m^2].
    :param damping: viscous friction ``D`` [N m s/rad] (MuJoCo joint ``damping``).
    :param frictionloss: Coulomb friction ``fc`` [N m] (MuJoCo joint ``frictionloss``).
    :param torque_limit: torque at normalized action +-1 [N m] (actuator ``gear``).
    :param gravity: gravitational acceleration [m/s^2].
    :param timestep: MuJoCo substep [s].
    :param frame_skip: substeps per env step; the control period is ``timestep * frame_skip``.
    :param friction_velocity: ``v_s`` [rad/s] of the analytic model's ``tanh`` friction.
    """

    link_mass: tuple[float, float]
    link_length: tuple[float, float]
    com_distance: tuple[float, float]
    com_inertia: tuple[float, float]
    armature: tuple[float, float]
    damping: tuple[float, float]
    frictionloss: tuple[float, float]
    torque_limit: tuple[float, float]
    gravity: float
    timestep: float = 0.002
    frame_skip: int = 10
    friction_velocity: float = 0.01

    @property
    def dt(self) -> float:
        """Control period [s] = ``timestep * frame_skip``."""
        return self.timestep * self.frame_skip

    def to_dict(self) -> dict:
        """JSON-friendly dict of all constants."""
        return {k: list(v) if isinstance(v, tuple) else v for k, v in asdict(self).items()}


def _rod(mass: float, length: float) -> float:
    """Inertia of a uniform rod about its centre, perpendicular to it: ``m l^2 / 12``."""
    return mass * length**2 / 12.0


PRESETS: dict[str, ArmParams] = {
    # a plausible small real arm (docs/environments.md, "Presets")
    "default": ArmParams(
        link_mass=(1.2, 0.6),
        link_length=(0.30, 0.25),
        com_distance=(0.15, 0.125),
        com_inertia=(_rod(1.2, 0.30), _rod(0.6, 0.25)),
        armature=(0.05, 0.02),
        damping=(0.2, 0.1),
        frictionloss=(0.2, 0.1),
        torque_limit=(8.0, 3.0),
        gravity=9.81,
    ),
    # the robot of the paper's original code, without its M11 typo
    "paper": ArmParams(
        link_mass=(0.2, 0.2),
        link_length=(1.0, 1.0),
        com_distance=(1.0, 1.0),
        com_inertia=(1e-9, 1e-9),
        armature=(0.0, 0.0),
        damping=(2.0, 2.0),
        frictionloss=(0.1, 0.1),
        torque_limit=(3.0, 3.0),
        gravity=1.82,
    ),
}


def _check_pair(name: str, value: object, *, positive: bool) -> tuple[float, float]:
    arr = as_array(name, value, (2,))
    if np.any(arr <= 0 if positive else arr < 0):
        raise ValueError(f"{name} must be {'>' if positive else '>='} 0 for both links, got "
                         f"{arr.tolist()}")
    return (float(arr[0]), float(arr[1]))


def validate_params(p: ArmParams) -> ArmParams:
    """Return ``p`` with pairs as float tuples, or raise ``ValueError`` naming the bad field."""
    positive = ("link_mass", "link_length", "com_distance", "com_inertia", "torque_limit")
    clean = {k: _check_pair(k, getattr(p, k), positive=k in positive)
             for k in (*positive, "armature", "damping", "frictionloss")}
    return replace(
        p,
        **clean,
        gravity=check_nonnegative("gravity", p.gravity),
        timestep=check_positive("timestep", p.timestep),
        frame_skip=check_int("frame_skip", p.frame_skip, 1),
        friction_velocity=check_positive("friction_velocity", p.friction_velocity),
    )


def arm_params(preset: str = "default", *, dt: float | None = None, **overrides) -> ArmParams:
    """The constants of a preset, with optional overrides.

    :param preset: ``"default"`` (a plausible real arm) or ``"paper"`` (the original code's robot).
    :param dt: control period [s]; sets ``timestep = dt / frame_skip``. ``None`` keeps 0.02 s.
    :param overrides: any :class:`ArmParams` field, e.g. ``link_mass=(1.0, 0.5)``.
    """
    if preset not in PRESETS:
        raise ValueError(f"unknown preset {preset!r}; valid presets: {sorted(PRESETS)}")
    valid = {f.name for f in fields(ArmParams)}
    unknown = set(overrides) - valid
    if unknown:
        raise ValueError(f"unknown arm parameter(s) {sorted(unknown)}; valid: {sorted(valid)}")
    p = replace(PRESETS[preset], **overrides)
    if dt is not None:
        p = replace(p, timestep=check_positive("dt", dt) / int(p.frame_skip))
    return validate_params(p)


# --- the equations of motion, written with CasADi operations (work on SX, MX and floats) ---


def mass_matrix(q: ca.SX, p: ArmParams) -> ca.SX:
    """Joint-space inertia ``M(q)``: ``q: [2]`` -> ``[2, 2]``."""
    (m1, m2), (l1, _), (r1, r2) = p.link_mass, p.link_length, p.com_distance
    (i1, i2), (a1, a2) = p.com_inertia, p.armature
    c2 = ca.cos(q[1])
    m11 = i1 + m1 * r1**2 + i2 + m2 * (l1**2 + r2**2 + 2 * l1 * r2 * c2) + a1
    m12 = i2 + m2 * (r2**2 + l1 * r2 * c2)
    m22 = i2 + m2 * r2**2 + a2
    return ca.vertcat(ca.horzcat(m11, m12), ca.horzcat(m12, m22))


def bias_torque(q: ca.SX, qd: ca.SX, p: ArmParams) -> ca.SX:
    """Coriolis/centrifugal plus gravity torque ``c(q, qd) + g(q)``: -> ``[2]``."""
    (m1, m2), (l1, _), (r1, r2) = p.link_mass, p.link_length, p.com_distance
    h = m2 * l1 * r2 * ca.sin(q[1])
    coriolis = ca.vertcat(-h * (2 * qd[0] * qd[1] + qd[1] ** 2), h * qd[0] ** 2)
    s12 = ca.sin(q[0] + q[1])
    gravity = p.gravity * ca.vertcat(
        (m1 * r1 + m2 * l1) * ca.sin(q[0]) + m2 * r2 * s12, m2 * r2 * s12
    )
    return coriolis + gravity


def friction_torque(qd: ca.SX, p: ArmParams) -> ca.SX:
    """Viscous plus smoothed Coulomb friction ``D qd + fc tanh(qd / v_s)``: -> ``[2]``."""
    damping = ca.DM(p.damping)
    fc = ca.DM(p.frictionloss)
    return damping * qd + fc * ca.tanh(qd / p.friction_velocity)


def continuous_dynamics(x: ca.SX, a: ca.SX, p: ArmParams) -> ca.SX:
    """``xdot = [qd, M^-1 (tau - c - g - friction)]``: ``x: [4]``, ``a: [2]`` -> ``[4]``."""
    q, qd = x[:2], x[2:]
    tau = ca.DM(p.torque_limit) * a
    qdd = ca.solve(mass_matrix(q, p), tau - bias_torque(q, qd, p) - friction_torque(qd, p))
    return ca.vertcat(qd, qdd)


def euler_substep(x: ca.SX, a: ca.SX, p: ArmParams) -> ca.SX:
    """One MuJoCo-Euler substep of length ``p.timestep``: ``x: [4]``, ``a: [2]`` -> ``[4]``.

    Joint damping is implicit, everything else explicit, then a semi-implicit position update::

        (M + h D) qdd = tau - c - g - D qd - fc tanh(qd / v_s)
        qd+ = qd + h qdd,   q+ = q + h qd+
    """
    h = p.timestep
    q, qd = x[:2], x[2:]
    tau = ca.DM(p.torque_limit) * a
    force = tau - bias_torque(q, qd, p) - friction_torque(qd, p)
    qdd = ca.solve(mass_matrix(q, p) + h * ca.diag(ca.DM(p.damping)), force)
    qd_next = qd + h * qdd
    q_next = q + h * qd_next
    return ca.vertcat(q_next, qd_next)


class TwoLinkArmCasadi:
    """Analytic CasADi twin of ``mbtsr/TwoLinkArm-v0`` (a ``mbtsr.dynamics.DynamicsModel``; its
    attributes: docs/environments.md, "analytic_model()"). Actions are not clipped here (a
    smooth model): keep ``|a| <= 1``, as the env does, for the two to agree.

    :param params: the arm's constants (``arm_params(preset)``).
    :param jit: compile ``step`` and ``jacobians`` to C (1-3 s once per instance; 4x faster
        steps, 9x faster Jacobians, same numbers to round-off; needs a C compiler).
    """

    state_dim = 4
    action_dim = 2

    def __init__(self, params: ArmParams, *, jit: bool = False) -> None:
        self.params = validate_params(params)
        self.jit = bool(jit)
        self.dt = self.params.dt
        x = ca.SX.sym("x", 4)
        a = ca.SX.sym("a", 2)
        x_next = x
        for _ in range(self.params.frame_skip):
            x_next = euler_substep(x_next, a, self.params)
        self.casadi_continuous = ca.Function(
            "arm_xdot", [x, a], [continuous_dynamics(x, a, self.params)], ["x", "a"], ["xdot"]
        )
        self.casadi_step = ca.Function("arm_step", [x, a], [x_next], ["x", "a"], ["x_next"])
        self.casadi_jacobians = ca.Function(
            "arm_step_jacobians",
            [x, a],
            [ca.jacobian(x_next, x), ca.jacobian(x_next, a)],
            ["x", "a"],
            ["A", "B"],
        )
        self._kernels = {"step": self.casadi_step, "jac": self.casadi_jacobians}
        if self.jit:  # the same expressions compiled to C once (about 1-3 s); the public
            # casadi_* functions stay symbolic (IPOPT differentiates through casadi_step)
            opts = casadi_jit_options("-O1")
            self._kernels = {
                which: ca.Function(f"{fn.name()}_jit", [x, a], fn.call([x, a]), opts)
                for which, fn in self._kernels.items()
            }
        self._buffers: dict[tuple[str, int], tuple] = {}

    def _buffer(self, which: str, n: int) -> tuple:
        """Zero-copy evaluation of the ``n``-fold map of ``casadi_step`` (``which="step"``) or
        ``casadi_jacobians`` (``"jac"``) through ``Function.buffer`` (cached per batch size).

        :return: ``(function_buffer, evaluate, x_in [n, 4], u_in [n, 2], function)``: the
            inputs are bound once (CasADi reads the column-major ``[4, n]``/``[2, n]`` matrices,
            i.e. exactly these C-ordered arrays); outputs are bound per call with ``set_res``.
        """
        key = (which, n)
        entry = self._buffers.get(key)
        if entry is None:
            if len(self._buffers) > 16:
                self._buffers.clear()
            fn = self._kernels[which].map(n)
            buf, evaluate = fn.buffer()
            x_in, u_in = np.zeros((n, 4)), np.zeros((n, 2))
            buf.set_arg(0, memoryview(x_in))
            buf.set_arg(1, memoryview(u_in))
            entry = self._buffers[key] = (buf, evaluate, x_in, u_in, fn)
        return entry

    def step(self, x: np.ndarray, u: np.ndarray, t: int | None = None) -> np.ndarray:
        """Next state in one mapped call: ``x: [..., 4]``, ``u: [..., 2]`` -> ``[..., 4]``."""
        return self._step(*check_step_inputs(x, u, 4, 2), t)

    def _step(self, x: np.ndarray, u: np.ndarray, t: int | None = None) -> np.ndarray:
        """:meth:`step` without input checks: ``x: [..., 4]``, ``u: [..., 2]`` (same batch)."""
        batch = x.shape[:-1]
        n_b = x.size // 4
        if n_b == 0:
            return np.empty((*batch, 4))
        buf, evaluate, x_in, u_in, _ = self._buffer("step", n_b)
        x_in[...] = x.reshape(n_b, 4)
        u_in[...] = u.reshape(n_b, 2)
        out = np.empty((n_b, 4))  # column-major [4, n_b] = C-ordered [n_b, 4]; a fresh array
        buf.set_res(0, memoryview(out))
        evaluate()
        return out.reshape(*batch, 4)

    def jacobians(self, x: np.ndarray, u: np.ndarray, t: int = 0) -> tuple[np.ndarray, np.ndarray]:
        """Exact (symbolic) Jacobians of one env step along a trajectory, one mapped call.

        :param x: ``[T, 4]`` states.
        :param u: ``[T, 2]`` normalized actions.
        :return: ``A: [T, 4, 4]``, ``B: [T, 4, 2]``.
        """
        x = as_array("x", x, (None, 4))
        u = as_array("u", u, (x.shape[0], 2))
        n_t = x.shape[0]
        buf, evaluate, x_in, u_in, _ = self._buffer("jac", n_t)
        x_in[...] = x
        u_in[...] = u
        # mapped outputs are horizontally concatenated blocks [A_0 A_1 ...] ([4, 4 T] and
        # [4, 2 T], column-major): C-ordered that is [T, 4 (column j), 4 (row i)], A_t transposed
        a_t, b_t = np.empty((n_t, 4, 4)), np.empty((n_t, 2, 4))
        buf.set_res(0, memoryview(a_t))
        buf.set_res(1, memoryview(b_t))
        evaluate()
        return a_t.transpose(0, 2, 1), b_t.transpose(0, 2, 1)
