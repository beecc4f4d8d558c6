"""crocoddyl side by side (agents/experiments/peers_crocoddyl.py): same problems, same optimum.

Crocoddyl is the optional ``[peers]`` extra: these tests skip without it, except the one that
checks the bench's message in that case.
"""

from __future__ import annotations

import numpy as np
import pytest

from agents.experiments import peers_crocoddyl as peers
from mbtsr.ilqr import ilqr

needs_crocoddyl = pytest.mark.skipif(not peers.HAVE_CROCODDYL, reason="crocoddyl not installed")


@needs_crocoddyl
def test_pinocchio_arm_from_mjcf_matches_the_analytic_twin():
    p = peers.arm_reach_problem(np.zeros(4), np.array([1.0, -0.5]), T=5).params
    assert peers.check_pinocchio_matches_twin(p) < 1e-10


@needs_crocoddyl
@pytest.mark.parametrize("which", ["box_lq", "arm_reach"])
def test_crocoddyl_and_mbtsr_reach_the_same_optimum(which):
    if which == "box_lq":
        prob = peers.box_lq_problem(T=200)
    else:
        prob = peers.arm_reach_problem(np.array([0.1, -0.1, 0.0, 0.0]), np.array([0.9, -0.4]), T=60)
    croc = peers.solve_crocoddyl(prob)
    res = ilqr(prob.cost, prob.model, prob.x0, np.zeros((prob.T, 2)), u_min=-1.0, u_max=1.0)
    assert croc["converged"] and res.status == "converged"
    assert croc["controls_within_limits"]
    # crocoddyl's own cost equals the mbtsr cost of its controls: the problems are the same
    np.testing.assert_allclose(croc["crocoddyl_cost"], croc["cost"], rtol=1e-9)
    np.testing.assert_allclose(res.cost, croc["cost"], rtol=1e-6)
    if which == "box_lq":  # the limits are active
        assert np.any(np.isclose(np.abs(res.U), 1.0))


def test_bench_reports_crocoddyl_skipped_when_not_installed(monkeypatch, capsys):
    from agents.experiments import bench_ilqr

    monkeypatch.setattr(peers, "HAVE_CROCODDYL", False)
    out = bench_ilqr.peer_comparison(None, [(np.zeros(4), np.zeros(2))])
    assert out == {"skipped": "crocoddyl not installed"}
    assert "crocoddyl: skipped (not installed)" in capsys.readouterr().out
