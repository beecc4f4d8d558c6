"""Crocoddyl twins of the iLQR benchmark problems (optional extra: ``pip install -e ".[peers]"``).

What it measures and how to run it: docs/experiments.md, section ``peers_crocoddyl``.
"""

from __future__ import annotations

import time
from dataclasses import dataclass, field

import numpy as np
from scipy.linalg import expm

from envs.two_link_arm import ASSET_PATH
from envs.two_link_arm_model import ArmParams, TwoLinkArmCasadi, arm_params
from mbtsr.costs import quadratic_cost
from mbtsr.dynamics import LinearDynamics

try:  # the optional peers extra
    import crocoddyl
    import pinocchio as pin

    HAVE_CROCODDYL = True
except ImportError:  # pragma: no cover - depends on the install
    crocoddyl = pin = None
    HAVE_CROCODDYL = False


@dataclass
class Problem:
    """One benchmark problem in mbtsr's terms (the crocoddyl twin is built from it): the cost
    ``quadratic_cost(Q, R, x_goal, Qf=Qf)`` and the control box ``[-1, 1]^m`` are derived from
    the fields, so the two solvers cannot get different weights."""

    name: str
    model: object  # mbtsr planning model
    x0: np.ndarray
    T: int
    Q: np.ndarray
    R: np.ndarray
    Qf: np.ndarray
    x_goal: np.ndarray
    dt: float = 1.0
    params: ArmParams | None = None
    jit: bool = False  # JIT-compile the cost's derivatives
    cost: object = field(init=False)  # mbtsr CasadiCost
    u_min: np.ndarray = field(init=False)
    u_max: np.ndarray = field(init=False)

    def __post_init__(self) -> None:
        self.cost = quadratic_cost(self.Q, self.R, self.x_goal, Qf=self.Qf, jit=self.jit)
        m = self.R.shape[0]
        self.u_min, self.u_max = np.full(m, -1.0), np.full(m, 1.0)


def box_lq_problem(T: int = 200) -> Problem:
    """Two coupled damped oscillators (``x = [p1, v1, p2, v2]``), ZOH with ``dt = 0.05``."""
    k, c, kc, dt = 4.0, 0.1, 1.0, 0.05
    Ac = np.array(
        [
            [0.0, 1.0, 0.0, 0.0],
            [-(k + kc), -c, kc, 0.0],
            [0.0, 0.0, 0.0, 1.0],
            [kc, 0.0, -(k + kc), -c],
        ]
    )
    Bc = np.array([[0.0, 0.0], [1.0, 0.0], [0.0, 0.0], [0.5, 1.0]])
    M = expm(np.block([[Ac, Bc], [np.zeros((2, 6))]]) * dt)
    A, B = M[:4, :4], M[:4, 4:]
    Q, R, Qf = np.diag([1.0, 0.1, 1.0, 0.1]), 0.01 * np.eye(2), np.diag([10.0, 1.0, 10.0, 1.0])
    goal = np.zeros(4)
    return Problem(
        name="box_lq", model=LinearDynamics(A, B), x0=np.array([2.0, 0.0, -1.5, 1.0]), T=T,
        Q=Q, R=R, Qf=Qf, x_goal=goal, jit=True,
    )


def arm_reach_problem(
    x0: np.ndarray, target: np.ndarray, T: int = 200, preset: str = "default",
    Q: np.ndarray | None = None, R: np.ndarray | None = None,
) -> Problem:
    """The arm reach without friction, one Euler step of 0.02 s per control (see module doc)."""
    base = arm_params(preset)
    p = arm_params(
        preset,
        damping=(0.0, 0.0),
        frictionloss=(0.0, 0.0),
        frame_skip=1,
        timestep=base.dt,
    )
    Q = np.diag([1.0, 1.0, 0.01, 0.01]) if Q is None else Q
    R = np.diag([0.01, 0.01]) if R is None else R
    goal = np.r_[np.asarray(target, dtype=float), 0.0, 0.0]
    return Problem(
        name="arm_reach", model=TwoLinkArmCasadi(p), x0=np.asarray(x0, dtype=float), T=T,
        Q=Q, R=R, Qf=Q, x_goal=goal, dt=p.timestep, params=p,
    )


# ---------------------------------------------------------------------------- crocoddyl side
def _require() -> None:
    if not HAVE_CROCODDYL:
        raise ImportError(
            'crocoddyl is not installed: pip install -c constraints.txt -e ".[peers]"'
        )


def crocoddyl_box_lq(p: Problem):
    """``ShootingProblem`` of :func:`box_lq_problem` (``ActionModelLQR`` + control bounds)."""
    _require()
    A, B = p.model.A, p.model.B
    n, m = B.shape

    def lqr(Qw, Rw, with_limits):
        # crocoddyl: 0.5 x^T Q x + 0.5 u^T R u + q^T x + r^T u;  ours: (x-g)^T Q (x-g) + u^T R u
        model = crocoddyl.ActionModelLQR(
            A, B, 2 * Qw, 2 * Rw, np.zeros((n, m)), np.zeros(n), -2 * Qw @ p.x_goal, np.zeros(m)
        )
        if with_limits:
            model.u_lb, model.u_ub = p.u_min.copy(), p.u_max.copy()
        return model

    running = lqr(p.Q, p.R, True)
    terminal = lqr(p.Qf, np.eye(m), False)
    return crocoddyl.ShootingProblem(p.x0, [running] * p.T, terminal)


def pinocchio_arm(params: ArmParams):
    """Pinocchio model of the arm from the project's MJCF, constants set from ``params``."""
    _require()
    model = pin.buildModelFromMJCF(str(ASSET_PATH))
    model.gravity.linear = np.array([0.0, 0.0, -params.gravity])
    for i in range(2):
        jid = i + 1
        mass, r, inertia = params.link_mass[i], params.com_distance[i], params.com_inertia[i]
        model.inertias[jid] = pin.Inertia(
            mass, np.array([0.0, 0.0, -r]), np.diag([inertia, inertia, 0.01 * inertia])
        )
        if i == 1:
            model.jointPlacements[jid] = pin.SE3(
                np.eye(3), np.array([0.0, 0.0, -params.link_length[0]])
            )
    model.armature = np.array(params.armature)
    return model


def check_pinocchio_matches_twin(params: ArmParams, seed: int = 0) -> float:
    """Max |ABA - twin acceleration| over random states and torques (friction-free twin)."""
    import casadi as ca

    from envs.two_link_arm_model import continuous_dynamics

    model = pinocchio_arm(params)
    data = model.createData()
    x, a = ca.SX.sym("x", 4), ca.SX.sym("a", 2)
    f = ca.Function("f", [x, a], [continuous_dynamics(x, a, params)])
    rng = np.random.default_rng(seed)
    err = 0.0
    for _ in range(20):
        q, v, u = rng.uniform(-2, 2, 2), rng.uniform(-3, 3, 2), rng.uniform(-1, 1, 2)
        acc = pin.aba(model, data, q, v, np.array(params.torque_limit) * u)
        err = max(err, float(np.abs(acc - np.array(f(np.r_[q, v], u))[2:, 0]).max()))
    return err


def crocoddyl_arm_reach(p: Problem):
    """``ShootingProblem`` of :func:`arm_reach_problem` on the pinocchio arm."""
    _require()
    params = p.params
    model = pinocchio_arm(params)
    model.armature = np.zeros(2)  # crocoddyl adds its own (below); pinocchio's is ignored there
    state = crocoddyl.StateMultibody(model)
    actuation = crocoddyl.ActuationModelFull(state)
    tl = np.array(params.torque_limit)
    dt = p.dt

    def action(Qw, Rw, scale, step):
        # ours: (x-g)^T Q (x-g) + a^T R a with torque tau = tl * a: a^T R a = tau^T (R / tl^2) tau
        costs = crocoddyl.CostModelSum(state, actuation.nu)
        terms = {"state": (crocoddyl.ResidualModelState(state, p.x_goal, actuation.nu), Qw, 1.0)}
        if Rw is not None:
            terms["control"] = (crocoddyl.ResidualModelControl(state, actuation.nu), Rw, tl**2)
        for name, (residual, W, div) in terms.items():
            weights = crocoddyl.ActivationModelWeightedQuad(2 * np.diag(W) / div / scale)
            costs.addCost(name, crocoddyl.CostModelResidual(state, weights, residual), 1.0)
        diff = crocoddyl.DifferentialActionModelFreeFwdDynamics(state, actuation, costs)
        diff.armature = np.array(params.armature)
        return crocoddyl.IntegratedActionModelEuler(diff, step)

    running, terminal = action(p.Q, p.R, dt, dt), action(p.Qf, None, 1.0, 0.0)
    running.u_lb, running.u_ub = -tl, tl
    return crocoddyl.ShootingProblem(p.x0, [running] * p.T, terminal), tl


def solve_crocoddyl(p: Problem, maxiter: int = 500, repeats: int = 1) -> dict:
    """Solve the crocoddyl twin with ``SolverBoxFDDP`` from zero controls (best of ``repeats``).

    :return: iterations, wall and CPU time, ms per iteration, crocoddyl's own cost, and
        ``cost``: the mbtsr cost of the returned controls (normalized) rolled out through the
        mbtsr model.
    """
    _require()
    if p.name == "box_lq":
        problem, scale = crocoddyl_box_lq(p), np.ones(p.u_min.shape)
    else:
        problem, scale = crocoddyl_arm_reach(p)
    problem.nthreads = 1  # one core, like mbtsr
    best = None
    for _ in range(repeats):
        solver = crocoddyl.SolverBoxFDDP(problem)
        xs = [p.x0] * (p.T + 1)
        us = [np.zeros(p.u_min.shape)] * p.T
        tic, cpu = time.perf_counter(), time.process_time()
        converged = solver.solve(xs, us, maxiter, False)
        wall, cpu = time.perf_counter() - tic, time.process_time() - cpu
        if best is None or cpu < best[3]:  # least disturbed by the other processes
            best = (solver, wall, converged, cpu)
    solver, wall, converged, cpu = best
    U = np.array(solver.us) / scale
    X = np.empty((p.T + 1, p.x0.size))
    X[0] = p.x0
    for t in range(p.T):
        X[t + 1] = p.model.step(X[t], U[t])
    iters = max(int(solver.iter), 1)
    return {
        "converged": bool(converged),
        "iterations": int(solver.iter),
        "wall_time_s": wall,
        "ms_per_iteration": wall / iters * 1e3,
        "cpu_time_s": cpu,
        "cpu_ms_per_iteration": cpu / iters * 1e3,
        "crocoddyl_cost": float(solver.cost),
        "cost": float(p.cost.total(X, U)),
        "controls_within_limits": bool(np.all(U >= p.u_min - 1e-9) and np.all(U <= p.u_max + 1e-9)),
    }
