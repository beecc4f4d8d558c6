"""JacProp labels: the LTV model ``l_i`` of each new trajectory (Algorithm 1, step (b)), with the
fallbacks for data that cannot support the fit (docs/agent.md, "LTV fallbacks")."""

from __future__ import annotations

import math
import warnings
from typing import Any

import numpy as np

from mbtsr.ltv import LTVModel, fit_ltv, fuse_prior, select_lambda
from mbtsr.training import RegularizationConfig
from mbtsr.trajectory import Trajectory

__all__ = ["JacobianLabeler", "LTV_MEMORY_BUDGET", "LTV_MEMORY_MAX", "check_ltv_memory",
           "light_ltv", "pooled_linear_fit"]

#: bytes an LTV fit may use for its posterior covariance (longer episodes are fitted in segments)
LTV_MEMORY_BUDGET = 256e6
#: the agent refuses LTV regularization when even a 2-step fit would need more than this
LTV_MEMORY_MAX = 2e9


def check_ltv_memory(regularization: RegularizationConfig, n: int, m: int) -> None:
    """Refuse LTV labels whose 2-step fit would hold more than :data:`LTV_MEMORY_MAX` bytes.

    :param n: model state dimension; ``m``: action dimension.
    :raises ValueError: naming the sizes and the ways out.
    """
    p = n + m
    if regularization.needs_ltv and 8 * 4 * 2 * n * p**2 > LTV_MEMORY_MAX:
        raise ValueError(
            f"regularization={regularization.kind!r} fits LTV models whose covariance holds "
            f"n (n+m)^2 = {n * p**2:.3g} numbers per time step for this model state (n={n}, "
            f"m={m}), more than this machine should hold; pass a smaller model state with "
            "state_fn/obs_fn, or choose AgentConfig(regularization='smooth') or 'none'"
        )


class JacobianLabeler:
    """LTV fits of the agent's trajectories, with fallbacks instead of errors.

    :param state_dim: model state dimension ``n``.
    :param act_dim: action dimension ``m``.
    :param regularization: its ``ltv_lambda`` (``None``: chosen per episode by
        :func:`mbtsr.ltv.select_lambda`) and ``needs_ltv``.
    :param ltv_prior: > 0 fuses each fit with the model's Jacobians (variance floor).
    """

    def __init__(self, state_dim: int, act_dim: int, regularization: RegularizationConfig,
                 ltv_prior: float = 0.0) -> None:
        self.n, self.m = int(state_dim), int(act_dim)
        self.regularization, self.ltv_prior = regularization, float(ltv_prior)
        self.lambdas: list[float] = []
        self.models: list[LTVModel] = []

    def add(self, traj: Trajectory, model: Any, earlier: list[Trajectory],
            episode: int) -> tuple[float, str]:
        """Label the new trajectory ``traj`` (when the regularization needs LTV labels).

        :param model: the ensemble before its update (the prior and a fallback's Jacobians).
        :param earlier: the trajectories before ``traj`` (a fallback's pooled fit).
        :param episode: for the warning.
        :return: ``(lam, note)``: the smoothness weight (NaN: no fit) and the fallbacks taken.
        """
        lam, note = math.nan, ""
        if self.regularization.needs_ltv:
            ltv, lam, note = self.label(traj, model, earlier, episode)
            self.models.append(ltv)
        self.lambdas.append(lam)
        return lam, note

    def label(self, traj: Trajectory, model: Any, earlier: list[Trajectory],
              episode: int = 0) -> tuple[LTVModel, float, str]:
        """The LTV model ``l_i`` of ``traj``, with the fallbacks of docs/agent.md ("LTV
        fallbacks"), each warned (``RuntimeWarning``) and returned as ``note``.

        :return: ``(model, lam, note)`` (``A [T, n, n]``, ``B [T, n, m]``).
        """
        notes: list[str] = []
        n, m = self.n, self.m
        lam = math.nan
        ltv = None
        if traj.T >= 2:
            lam = self.select_lambda(traj, notes)
            # the fit's posterior covariance holds T n (n+m)^2 numbers: long episodes of
            # high-dimensional envs are fitted in consecutive segments that fit the memory
            # budget (smoothness is then not enforced across segment boundaries)
            seg = max(2, int(LTV_MEMORY_BUDGET // (8 * 4 * n * (n + m) ** 2)))
            bounds = list(range(0, traj.T, seg))
            if len(bounds) > 1 and traj.T - bounds[-1] < 2:
                bounds.pop()
            if len(bounds) > 1:
                notes.append(f"{len(bounds)} segments of <= {seg} steps (memory)")
            parts = []
            for a, b in zip(bounds, bounds[1:] + [traj.T]):
                part = self._fit_segment(
                    Trajectory(traj.x[a : b + 1], traj.u[a:b], traj.dt), lam, model, notes)
                if part is None:
                    parts = None
                    break
                parts.append(part)
            if parts is not None:
                ltv = light_ltv(np.concatenate([p_[0] for p_ in parts]),
                                np.concatenate([p_[1] for p_ in parts]), lam)
        if ltv is None:
            if model.is_normalized:
                x, u = traj.inputs
                A, B = model.member_jacobians(x, u)
                ltv = light_ltv(A.mean(0), B.mean(0), lam)
                notes.append(f"episode of {traj.T} transition(s): labelled by the model's "
                             "Jacobians")
            else:
                ltv = pooled_linear_fit(earlier + [traj], traj.T, n, m)
                notes.append(f"episode of {traj.T} transition(s): time-invariant least-squares "
                             "fit pooled over all episodes")
        note = "; ".join(dict.fromkeys(notes))
        if note:
            warnings.warn(f"episode {episode}: LTV fit fallback: {note}", RuntimeWarning,
                          stacklevel=3)
        return ltv, lam, note

    def _fit_segment(
        self, traj: Trajectory, lam: float, model: Any, notes: list[str]
    ) -> tuple[np.ndarray, np.ndarray] | None:
        """``(A [T, n, n], B [T, n, m])`` of the smooth LTV fit of ``traj`` (fallback 2), fused
        with the model's Jacobians (``ltv_prior``); ``None`` if it stays unsolvable."""
        n = self.n
        try:
            ltv = fit_ltv(traj, lam)
        except ValueError:
            x, u = traj.inputs
            phi = np.concatenate([x, u], axis=1)
            scale = float(np.mean(np.sum(phi**2, axis=1))) * traj.T + lam**2 + 1e-12
            try:
                ltv = fit_ltv(traj, lam, P0=1.0 / (1e-6 * scale))
            except ValueError:
                return None
            notes.append("degenerate regressors (constant or unexcited observation/action "
                         "dimensions): weak prior on the first Jacobian")
        q = n + self.m
        if self.ltv_prior > 0 and model.is_normalized and n * q**3 > 1e7:
            notes.append("model prior (ltv_prior) skipped: n (n+m)^3 too large for the fusion")
        elif self.ltv_prior > 0 and model.is_normalized:
            x, u = traj.inputs
            A, B = model.member_jacobians(x, u)  # [K, T, n, n], [K, T, n, m]
            J = np.concatenate([A, B], axis=-1)
            mean, var = J.mean(0), J.var(0) + self.ltv_prior
            ltv = fuse_prior(ltv, mean[..., :n], mean[..., n:], var)
        return np.asarray(ltv.A), np.asarray(ltv.B)

    def select_lambda(self, traj: Trajectory, notes: list[str] | None = None) -> float:
        """``regularization.ltv_lambda``, or its automatic choice for ``traj`` (fallback 1
        appends its reason to ``notes``)."""
        if self.regularization.ltv_lambda is not None:
            return float(self.regularization.ltv_lambda)
        # constant state coordinates (a goal in the observation) carry no information on the
        # smoothness and make the criterion singular: select on the varying ones
        varying = np.ptp(traj.x, axis=0) > 1e-9 * (1.0 + np.abs(traj.x).max(axis=0))
        sub = traj if varying.all() or not varying.any() else Trajectory(
            traj.x[:, varying], traj.u, traj.dt)
        try:
            with warnings.catch_warnings():
                warnings.simplefilter("ignore", RuntimeWarning)  # a boundary optimum is fine
                lam, _ = select_lambda(sub)
            return float(lam)
        except ValueError as err:
            reason = ("too few transitions" if "more measurements" in str(err)
                      else "degenerate regressors")
            earlier = [v for v in self.lambdas if math.isfinite(v)]
            if earlier:
                lam = float(np.median(earlier))
                what = "the median of the earlier selections"
            else:
                x, u = traj.inputs
                phi = np.concatenate([x, u], axis=1)
                lam = float(np.sqrt(np.mean(np.sum(phi**2, axis=1)) / phi.shape[1])) or 1.0
                what = "the regressor scale"
            if notes is not None:
                notes.append(f"ltv_lambda='auto' cannot be selected ({reason}, {traj.T} "
                             f"transitions): using {what} ({lam:.3g})")
            return lam

    def state_dict(self) -> dict[str, Any]:
        """The checkpoint's fields: ``ltv_lambdas`` and ``ltv_models`` (``A``, ``B``, ``lam``;
        stored, not refitted)."""
        return {"ltv_lambdas": list(self.lambdas),
                "ltv_models": [{"A": m.A, "B": m.B, "lam": m.lam} for m in self.models]}

    def load_state_dict(self, state: dict[str, Any]) -> None:
        """Restore :meth:`state_dict`'s fields (arrays as numpy arrays or tensors)."""
        self.lambdas = [float(v) for v in state["ltv_lambdas"]]
        self.models = [light_ltv(np.asarray(d["A"]), np.asarray(d["B"]), float(d["lam"]))
                       for d in state["ltv_models"]]


def light_ltv(A: np.ndarray, B: np.ndarray, lam: float = math.nan) -> LTVModel:
    """An LTV model that keeps ``A [T, n, n]``, ``B [T, n, m]`` only; its ``cov`` is a
    zero-memory view of zeros."""
    T, n, m = B.shape
    cov = np.broadcast_to(np.zeros((), dtype=float), (T, n, n + m, n + m))
    return LTVModel(A, B, None, cov, lam=0.0 if not math.isfinite(lam) else lam)


def pooled_linear_fit(trajs: list[Trajectory], T: int, n: int, m: int) -> LTVModel:
    """``x+ = A x + B u`` by ridge least squares over all transitions of ``trajs`` (ridge 1e-6 of
    the regressor scale), repeated over ``T`` steps."""
    phi = np.concatenate([np.concatenate([t.x[:-1], t.u], axis=1) for t in trajs])
    y = np.concatenate([t.x[1:] for t in trajs])
    G = phi.T @ phi
    ridge = 1e-6 * (np.trace(G) / G.shape[0] + 1e-12)
    H = G + ridge * np.eye(n + m)
    K = np.linalg.solve(H, phi.T @ y).T  # [n, n+m]
    return light_ltv(
        np.broadcast_to(K[:, :n], (T, n, n)).copy(), np.broadcast_to(K[:, n:], (T, n, m)).copy()
    )
