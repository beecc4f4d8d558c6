"""CEM proposes, iLQR refines: the default planner of the agent and of its true-model oracle.

A few iterations of :func:`mbtsr.cem.cem` around ``U0`` (samples seeded from ``cem.seed + t0``),
then :func:`mbtsr.ilqr.ilqr` from CEM's best sequence. Why both, with measurements:
docs/ilqr.md, "The default planner: CEM proposes, iLQR refines".
"""

from __future__ import annotations

import dataclasses
from collections.abc import Callable, Mapping
from dataclasses import dataclass, field
from typing import Any

import numpy as np

from mbtsr.cem import CEMOptions, cem
from mbtsr.ilqr import ILQROptions, ILQRResult, ilqr
from mbtsr.validation import check_int, check_nonnegative, options_from

__all__ = ["CEMILQROptions", "cem_ilqr"]


@dataclass(frozen=True)
class CEMILQROptions:
    """Settings of :func:`cem_ilqr`.

    :param max_iter: iLQR iterations after the CEM proposal (the MPC sets it per solve).
    :param cem: the proposal's CEM settings (:class:`mbtsr.cem.CEMOptions`).
    :param ilqr: the refinement's iLQR settings (its ``max_iter`` is replaced by ``max_iter``).
    :param lambda_init: iLQR's initial regularisation (``None``: ``ilqr.lambda_init``); the
        MPC sets it when it warm-starts the regularisation.
    :param cold_proposal_iterations: CEM iterations of a cold start (:meth:`for_cold_start`,
        which the MPC calls; with no plan to refine, CEM decides the strategy).
    :param warm_samples: CEM samples of a warm-started proposal, at most ``cem.samples``
        (``None``: ``cem.samples``; elites at most as many); a cold start samples
        ``cem.samples`` (why 32: docs/ilqr.md, "Planning at the control rate").
    """

    max_iter: int = 2
    cem: CEMOptions = field(default_factory=lambda: CEMOptions(samples=64, elites=8,
                                                               iterations=2))
    ilqr: ILQROptions = field(default_factory=lambda: ILQROptions(tol_fun_rel=1e-6))
    lambda_init: float | None = None
    cold_proposal_iterations: int = 6
    warm_samples: int | None = 32

    def for_cold_start(self) -> CEMILQROptions:
        """These options for a solve without a previous plan: ``cold_proposal_iterations``
        CEM iterations (at least ``cem.iterations``) of ``cem.samples`` samples."""
        its = max(int(self.cem.iterations), int(self.cold_proposal_iterations))
        return dataclasses.replace(self, cem=dataclasses.replace(self.cem, iterations=its),
                                   warm_samples=None)

    def __post_init__(self) -> None:
        for name in ("max_iter", "cold_proposal_iterations"):
            check_int(name, getattr(self, name), 1)
        if self.warm_samples is not None:
            check_int("warm_samples", self.warm_samples, 2)
        if not isinstance(self.cem, CEMOptions):
            raise TypeError(f"cem must be a CEMOptions, got {type(self.cem).__name__}")
        if not isinstance(self.ilqr, ILQROptions):
            raise TypeError(f"ilqr must be an ILQROptions, got {type(self.ilqr).__name__}")
        if self.lambda_init is not None:
            check_nonnegative("lambda_init", self.lambda_init)


def cem_ilqr(
    cost: Any,
    model: Any,
    x0: np.ndarray,
    U0: np.ndarray,
    *,
    u_min: np.ndarray | float,
    u_max: np.ndarray | float,
    params: Any = None,
    t0: int = 0,
    options: CEMILQROptions | Mapping | None = None,
    terminated: Callable[[np.ndarray], np.ndarray] | None = None,
) -> ILQRResult:
    """CEM's best sequence from ``U0``, refined by ``options.max_iter`` iLQR iterations.

    Arguments as :func:`mbtsr.ilqr.ilqr` (finite bounds required, as for CEM); all but
    ``options`` are passed to both.
    :return: iLQR's :class:`mbtsr.ilqr.ILQRResult`; its ``timings`` add ``"proposal"`` (CEM's
        seconds) to the total, and ``proposal_cost`` is the cost of CEM's sequence.
    """
    opts = options_from(CEMILQROptions, options)
    problem = {"u_min": u_min, "u_max": u_max, "params": params, "t0": t0,
               "terminated": terminated}
    search = dataclasses.replace(opts.cem, seed=int(opts.cem.seed) + int(t0))
    if opts.warm_samples is not None and opts.warm_samples < search.samples:
        search = dataclasses.replace(search, samples=opts.warm_samples,
                                     elites=min(search.elites, opts.warm_samples))
    proposal = cem(cost, model, x0, U0, options=search, **problem)
    refine = dataclasses.replace(opts.ilqr, max_iter=int(opts.max_iter))
    if opts.lambda_init is not None:
        refine = dataclasses.replace(refine, lambda_init=float(opts.lambda_init))
    res = ilqr(cost, model, x0, proposal.U, options=refine, **problem)
    spent = proposal.timings.get("total", 0.0)
    return dataclasses.replace(
        res, timings={**res.timings, "proposal": spent,
                      "total": res.timings.get("total", 0.0) + spent},
        proposal_cost=float(proposal.cost))
