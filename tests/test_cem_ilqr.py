"""CEM proposes, iLQR refines (:mod:`mbtsr.cem_ilqr`): on a cost whose gradient is zero at the
initial plan (a contact-like dead zone) iLQR alone cannot move, CEM finds the valley and iLQR
refines it to the optimum; the result is never worse than the proposal; same seed and time,
same plan; the MPC drives it like any optimizer."""

from __future__ import annotations

import casadi as ca
import numpy as np
import pytest

from mbtsr.cem import CEMOptions
from mbtsr.cem_ilqr import CEMILQROptions, cem_ilqr
from mbtsr.costs import CasadiCost
from mbtsr.dynamics import LinearDynamics
from mbtsr.ilqr import ilqr
from mbtsr.mpc import MPC, MPCOptions

T = 10


def _dead_zone_problem():
    """``x+ = x + u`` (|u| <= 1) from 0; stage cost ``(max(x - 1, 0) - 1)^2 + 0.01 u^2``: flat
    (zero gradient) below x = 1, a valley at x = 2."""
    x, u, t = ca.SX.sym("x"), ca.SX.sym("u"), ca.SX.sym("t")
    well = (ca.fmax(x - 1.0, 0.0) - 1.0) ** 2
    cost = CasadiCost(ca.Function("l", [x, u, t], [well + 0.01 * u**2]),
                      ca.Function("lT", [x], [well]), 1, 1)
    return cost, LinearDynamics(np.eye(1), np.eye(1))


def test_cem_finds_what_the_gradient_cannot_and_ilqr_refines_it():
    cost, model = _dead_zone_problem()
    x0, U0 = np.zeros(1), np.zeros((T, 1))
    alone = ilqr(cost, model, x0, U0, u_min=-1, u_max=1)
    assert np.allclose(alone.U, 0.0)  # zero gradient: iLQR never leaves the flat region
    res = cem_ilqr(cost, model, x0, U0, u_min=-1, u_max=1,
                   options=CEMILQROptions(max_iter=50))
    assert res.proposal_cost is not None and res.cost <= res.proposal_cost
    assert res.cost < alone.cost - 5.0
    assert abs(res.X[-1, 0] - 2.0) < 0.05  # refined into the valley
    assert "proposal" in res.timings and res.timings["total"] >= res.timings["proposal"]


def test_same_seed_and_time_same_plan_and_time_varies_the_samples():
    cost, model = _dead_zone_problem()
    x0, U0 = np.zeros(1), np.zeros((T, 1))
    opts = CEMILQROptions(max_iter=1, cem=CEMOptions(samples=8, elites=2, iterations=1))
    a = cem_ilqr(cost, model, x0, U0, u_min=-1, u_max=1, options=opts, t0=3)
    b = cem_ilqr(cost, model, x0, U0, u_min=-1, u_max=1, options=opts, t0=3)
    c = cem_ilqr(cost, model, x0, U0, u_min=-1, u_max=1, options=opts, t0=4)
    np.testing.assert_array_equal(a.U, b.U)
    assert a.proposal_cost != c.proposal_cost  # new samples at every MPC step


def test_the_mpc_sets_the_refinement_iterations_and_options_are_checked():
    cost, model = _dead_zone_problem()
    seen = []

    def spy(*args, options=None, **kw):
        seen.append(options)
        return cem_ilqr(*args, options=options, **kw)

    mpc = MPC(spy, cost, model, T, u_min=-1, u_max=1,
              options=MPCOptions(iterations_per_step=1, first_step_iterations=4,
                                 optimizer_options=CEMILQROptions(), cold_start_fractions=()))
    mpc.act(np.zeros(1), 0)
    mpc.act(np.zeros(1), 1)
    assert [o.max_iter for o in seen] == [4, 1]
    mpc2 = MPC(cem_ilqr, cost, model, T, u_min=-1, u_max=1,
               options=MPCOptions(optimizer_options={"max_iter": 3}))
    assert mpc2._base_options == CEMILQROptions(max_iter=3)
    with pytest.raises(ValueError, match="unknown CEMILQROptions"):
        MPC(cem_ilqr, cost, model, T, u_min=-1, u_max=1,
            options=MPCOptions(optimizer_options={"samples": 3}))
    with pytest.raises(ValueError, match="max_iter"):
        CEMILQROptions(max_iter=0)


def test_a_cold_start_searches_longer():
    cost, model = _dead_zone_problem()
    seen = []

    def spy(*args, options=None, **kw):
        seen.append(options.cem.iterations)
        return cem_ilqr(*args, options=options, **kw)

    opts = CEMILQROptions(cem=CEMOptions(samples=8, elites=2, iterations=1),
                          cold_proposal_iterations=4)
    mpc = MPC(spy, cost, model, T, u_min=-1, u_max=1,
              options=MPCOptions(optimizer_options=opts, cold_start_fractions=(0.5,)))
    mpc.act(np.zeros(1), 0)
    mpc.act(np.zeros(1), 1)
    assert seen == [4, 4, 1]  # two cold-start horizons, then a warm start
    assert opts.for_cold_start().cem.iterations == 4
    assert CEMILQROptions(cold_proposal_iterations=1).for_cold_start().cem.iterations == 2


def test_a_warm_proposal_samples_warm_samples_and_a_cold_one_all(monkeypatch):
    import mbtsr.cem_ilqr as hybrid

    cost, model = _dead_zone_problem()
    seen = []
    real = hybrid.cem

    def spy(*args, options=None, **kw):
        seen.append((options.samples, options.elites))
        return real(*args, options=options, **kw)

    monkeypatch.setattr(hybrid, "cem", spy)
    opts = CEMILQROptions(cem=CEMOptions(samples=16, elites=6, iterations=1), warm_samples=4)
    mpc = MPC(cem_ilqr, cost, model, T, u_min=-1, u_max=1,
              options=MPCOptions(optimizer_options=opts, cold_start_fractions=()))
    mpc.act(np.zeros(1), 0)
    mpc.act(np.zeros(1), 1)
    assert seen == [(16, 6), (4, 4)]  # cold: all samples; warm: warm_samples, elites capped
    seen.clear()
    cem_ilqr(cost, model, np.zeros(1), np.zeros((T, 1)), u_min=-1, u_max=1,
             options=CEMILQROptions(cem=CEMOptions(samples=8, elites=2), warm_samples=None))
    assert seen == [(8, 2)]
    assert CEMILQROptions().warm_samples == 32 and CEMILQROptions().for_cold_start().warm_samples \
        is None
    with pytest.raises(ValueError, match="warm_samples"):
        CEMILQROptions(warm_samples=1)
