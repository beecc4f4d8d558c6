"""A learned reward that the planners use like a written cost.

:class:`RewardModel` learns ``r_hat(s, a)`` from the env's own rewards; its ``cost()`` is the
planning cost ``l(x_t, u_t, t) = -r_hat(x_t, u_t)`` (:class:`LearnedRewardCost`, closed-form
derivatives with a PSD Hessian). The convention, the model and its frozen form: docs/agent.md,
"The learned reward".
"""

from __future__ import annotations

import time
from dataclasses import asdict, dataclass

import numpy as np
import torch

from mbtsr.costs import CasadiCost, CostDerivatives
from mbtsr.dynamics import check_step_inputs
from mbtsr.ensemble import REL_STD_FLOOR
from mbtsr.training import MIN_REL_IMPROVEMENT, holdout_mask
from mbtsr.validation import as_array, check_int, check_nonnegative, check_positive

__all__ = ["RewardConfig", "RewardFit", "RewardModel", "FrozenReward", "LearnedRewardCost"]


@dataclass(frozen=True)
class RewardConfig:
    """Size and training budget of a :class:`RewardModel`.

    :param members: ensemble members ``K``.
    :param hidden: hidden units per member ``H``.
    :param steps: Adam steps per :meth:`RewardModel.fit` call (the budget).
    :param batch: minibatch per member and step.
    :param lr: initial learning rate (cosine decay to 0 over the budget).
    :param weight_decay: decoupled weight decay (AdamW).
    :param holdout: fraction of the transitions held out for early stopping (0: train on all,
        keep the last weights); the rows of :func:`mbtsr.training.holdout_mask`, as for the
        dynamics.
    :param eval_every: steps between hold-out evaluations.
    :param patience: stop after this many evaluations without progress of any member.
    :param seed: seed of the initial weights and the minibatches.
    """

    members: int = 5
    hidden: int = 32
    steps: int = 2000
    batch: int = 256
    lr: float = 1e-2
    weight_decay: float = 1e-4
    holdout: float = 0.2
    eval_every: int = 100
    patience: int = 5
    seed: int = 0

    def __post_init__(self) -> None:
        for name in ("members", "hidden", "steps", "batch", "eval_every", "patience"):
            check_int(name, getattr(self, name), 1)
        check_int("seed", self.seed, 0)
        check_positive("lr", self.lr)
        check_nonnegative("weight_decay", self.weight_decay)
        if not 0.0 <= check_nonnegative("holdout", self.holdout) < 1.0:
            raise ValueError(f"holdout must be a fraction in [0, 1), got {self.holdout!r}")


@dataclass(frozen=True)
class RewardFit:
    """What one :meth:`RewardModel.fit` call did.

    :param steps: Adam steps taken (``<= config.steps``).
    :param holdout_mse: ``[K]`` each member's best hold-out mean squared error in reward units
        (``None`` without a hold-out).
    :param seconds: wall time of the call.
    """

    steps: int
    holdout_mse: np.ndarray | None
    seconds: float


class RewardModel:
    """An ensemble of one-hidden-layer tanh MLPs plus quadratic forms, ``r_k(s, a)``, trained
    on observed rewards (docs/agent.md, "The learned reward").

    :param state_dim: ``n``, the planner's state size.
    :param action_dim: ``m``.
    :param config: :class:`RewardConfig` (default sizes and budget).
    """

    def __init__(self, state_dim: int, action_dim: int, config: RewardConfig | None = None) -> None:
        self.n = check_int("state_dim", state_dim, 1)
        self.m = check_int("action_dim", action_dim, 1)
        self.config = RewardConfig() if config is None else config
        if not isinstance(self.config, RewardConfig):
            raise TypeError(f"config must be a RewardConfig, got {type(self.config).__name__}")
        K, H, d = self.config.members, self.config.hidden, self.n + self.m
        gen = torch.Generator().manual_seed(self.config.seed)
        self.params = {  # float32 training weights, members stacked on axis 0
            "W1": torch.randn(K, d, H, generator=gen) / np.sqrt(d),
            "b1": 0.5 * torch.randn(K, H, generator=gen),
            "w2": torch.randn(K, H, generator=gen) / np.sqrt(H),
            "b2": torch.zeros(K),
            "P": torch.zeros(K, d, d),  # the quadratic term (symmetrized in _forward)
        }
        for p in self.params.values():
            p.requires_grad_(True)
        self.normalization: tuple[np.ndarray, ...] | None = None  # z mean, z std, r mean, r std
        self.fits = 0

    def _forward(self, z: torch.Tensor) -> torch.Tensor:
        """Member outputs in normalized units: ``z [K, B, d]`` (normalized) -> ``[K, B]``."""
        p = self.params
        h = torch.tanh(torch.baddbmm(p["b1"][:, None, :], z, p["W1"]))
        quad = (torch.bmm(z, p["P"] + p["P"].transpose(1, 2)) * z).sum(-1) / 2
        return (h * p["w2"][:, None, :]).sum(-1) + p["b2"][:, None] + quad

    def fit(self, states: np.ndarray, actions: np.ndarray, rewards: np.ndarray) -> RewardFit:
        """Train on transitions ``(s_t, a_t) -> r_t`` for ``config.steps`` Adam steps at most,
        continuing from the current weights (the agent refits after every episode on all data).
        The input and reward normalization are set by the first call and then kept.

        :param states: ``[N, n]`` planner states ``s_t``.
        :param actions: ``[N, m]`` actions ``a_t``.
        :param rewards: ``[N]`` rewards ``r_t`` of those steps.
        :return: :class:`RewardFit`.
        """
        tic = time.perf_counter()
        S = as_array("states", states, (None, self.n))
        A = as_array("actions", actions, (S.shape[0], self.m))
        r = as_array("rewards", rewards, (S.shape[0],))
        cfg, N = self.config, S.shape[0]
        held = holdout_mask(N, cfg.holdout)  # a row stays held out (or not) as data grows
        n_hold = int(held.sum())
        if N - n_hold < 1 or (cfg.holdout > 0 and n_hold < 1):
            raise ValueError(f"{N} transitions are too few for a hold-out of {cfg.holdout} "
                             f"({n_hold} held out): give more, or holdout=0")
        Z = np.hstack([S, A])
        if self.normalization is None:  # a constant input is not rescaled (as the dynamics)
            std, scale = Z.std(0), np.abs(Z).max(0)
            std = np.where((std <= REL_STD_FLOOR * scale) | (std == 0), 1.0, std)
            self.normalization = (Z.mean(0), std, r.mean(), max(float(r.std()), 1e-6))
        mz, sz, mr, sr = self.normalization
        rng = np.random.default_rng([cfg.seed, self.fits])
        self.fits += 1
        Zn = torch.as_tensor((Z - mz) / sz, dtype=torch.float32)
        yn = torch.as_tensor((r - mr) / sr, dtype=torch.float32)
        Zt, yt, Zh, yh = Zn[~held], yn[~held], Zn[held], yn[held]
        K, B = cfg.members, min(cfg.batch, N - n_hold)
        opt = torch.optim.AdamW(list(self.params.values()), lr=cfg.lr,
                                weight_decay=cfg.weight_decay)
        sched = torch.optim.lr_scheduler.CosineAnnealingLR(opt, cfg.steps)
        best = torch.full((K,), np.inf)
        best_params = {k: v.detach().clone() for k, v in self.params.items()}
        stale, step = 0, 0
        while step < cfg.steps:
            idx = torch.as_tensor(rng.integers(0, N - n_hold, size=(K, B)))
            loss = ((self._forward(Zt[idx]) - yt[idx]) ** 2).mean(1).sum()
            opt.zero_grad()
            loss.backward()
            opt.step()
            sched.step()
            step += 1
            if n_hold and (step % cfg.eval_every == 0 or step == cfg.steps):
                with torch.no_grad():
                    mse = ((self._forward(Zh.expand(K, -1, -1)) - yh) ** 2).mean(1)
                better = mse < best * (1 - MIN_REL_IMPROVEMENT)
                best = torch.where(better, mse, best)
                for k, v in self.params.items():
                    best_params[k][better] = v.detach()[better]
                stale = 0 if bool(better.any()) else stale + 1
                if stale >= cfg.patience:
                    break
        if n_hold:
            with torch.no_grad():
                for k, v in self.params.items():
                    v.copy_(best_params[k])
        hold = None if not n_hold else best.numpy().astype(float) * sr**2
        return RewardFit(steps=step, holdout_mse=hold, seconds=time.perf_counter() - tic)

    def state_dict(self) -> dict:
        """Everything :meth:`from_state_dict` needs (sizes, config, weights, normalization,
        number of fits), as plain Python and torch tensors (for a checkpoint)."""
        return {"state_dim": self.n, "action_dim": self.m, "config": asdict(self.config),
                "params": {k: v.detach().clone() for k, v in self.params.items()},
                "normalization": None if self.normalization is None
                else [np.asarray(a, dtype=float).tolist() for a in self.normalization],
                "fits": self.fits}

    @classmethod
    def from_state_dict(cls, state: dict) -> RewardModel:
        """The model of :meth:`state_dict`; a later :meth:`fit` continues as the saved one
        would have."""
        model = cls(state["state_dim"], state["action_dim"], RewardConfig(**state["config"]))
        with torch.no_grad():
            for k, v in model.params.items():
                v.copy_(torch.as_tensor(state["params"][k]))
        norm = state["normalization"]
        model.normalization = None if norm is None else (
            np.asarray(norm[0]), np.asarray(norm[1]), float(norm[2]), float(norm[3]))
        model.fits = int(state["fits"])
        return model

    def freeze(self) -> FrozenReward:
        """The ensemble mean as one numpy float64 layer (:class:`FrozenReward`)."""
        if self.normalization is None:
            raise RuntimeError("the reward model is untrained: call fit(states, actions, rewards)")
        mz, sz, mr, sr = self.normalization
        p = {k: v.detach().double().numpy() for k, v in self.params.items()}
        K, d, H = p["W1"].shape
        W = p["W1"] / sz[None, :, None]  # [K, d, H] on raw inputs
        b = p["b1"] - np.einsum("d,kdh->kh", mz, W)
        P = (p["P"] + p["P"].transpose(0, 2, 1)).mean(0) / 2 * sr / np.outer(sz, sz)
        return FrozenReward(W.transpose(1, 0, 2).reshape(d, K * H), b.reshape(K * H),
                            p["w2"].reshape(K * H) * sr / K, mr + sr * float(p["b2"].mean()),
                            self.n, P=P, z0=mz)

    def cost(self, terminal_weight: float = 1.0, param_dim: int = 0) -> LearnedRewardCost:
        """The planning cost of the current weights (a frozen copy; see
        :class:`LearnedRewardCost`)."""
        return LearnedRewardCost(self.freeze(), terminal_weight=terminal_weight,
                                 param_dim=param_dim)


class FrozenReward:
    """``r_hat(z) = c + w . tanh(W^T z + b) + (z - z0)^T P (z - z0)``, ``z = [x, u]``, in numpy
    float64 (read-only arrays).

    :param W: ``[n+m, U]`` input weights (``U`` units in all).
    :param b: ``[U]`` biases.
    :param w: ``[U]`` output weights.
    :param c: output offset.
    :param n: state size (the first ``n`` entries of ``z`` are ``x``).
    :param P: ``[n+m, n+m]`` symmetric weight of the quadratic term (``None``: no term).
    :param z0: ``[n+m]`` centre of the quadratic term (``None``: 0).
    """

    def __init__(self, W: np.ndarray, b: np.ndarray, w: np.ndarray, c: float, n: int,
                 P: np.ndarray | None = None, z0: np.ndarray | None = None) -> None:
        self.W = as_array("W", W, ndim=2)
        d, units = self.W.shape
        self.b, self.w = as_array("b", b, (units,)), as_array("w", w, (units,))
        self.c = float(as_array("c", c, ()))
        self.n = check_int("n", n, 1)
        self.m = d - self.n
        if self.m < 1:
            raise ValueError(f"W must have n + m rows with m >= 1, got {d} for n={n}")
        self.P = np.zeros((d, d)) if P is None else as_array("P", P, (d, d))
        if not np.allclose(self.P, self.P.T, rtol=1e-10, atol=1e-12):
            raise ValueError("P must be symmetric")
        self.z0 = np.zeros(d) if z0 is None else as_array("z0", z0, (d,))
        lam, V = np.linalg.eigh(2.0 * self.P)  # the term's Hessian, and its concave part
        self._P_concave = (V * np.minimum(lam, 0.0)) @ V.T
        self._b_centred = self.b + self.z0 @ self.W  # W^T z + b = W^T (z - z0) + _b_centred
        for a in (self.W, self.b, self.w, self.P, self.z0, self._P_concave, self._b_centred):
            a.flags.writeable = False

    def _terms(self, x: np.ndarray, u: np.ndarray) -> tuple[np.ndarray, ...]:
        """``x [N, n]``, ``u [N, m]`` -> ``r [N]``, hidden ``h [N, U]``, ``z - z0 [N, d]``,
        ``P (z - z0) [N, d]``."""
        e = np.concatenate([x, u], axis=-1) - self.z0
        h = e @ self.W  # in place from here: fresh [N, U] arrays cost more than the arithmetic
        h += self._b_centred
        np.tanh(h, out=h)
        Pe = e @ self.P
        return h @ self.w + self.c + (Pe * e).sum(-1), h, e, Pe

    def predict(self, x: np.ndarray, u: np.ndarray) -> np.ndarray:
        """Predicted rewards: ``x [..., n]``, ``u [..., m]`` -> ``[...]``."""
        return self._predict(*check_step_inputs(x, u, self.n, self.m))

    def _predict(self, x: np.ndarray, u: np.ndarray) -> np.ndarray:
        """:meth:`predict` without checks."""
        return self._terms(x.reshape(-1, self.n), u.reshape(-1, self.m))[0].reshape(x.shape[:-1])

    def derivatives(self, x: np.ndarray, u: np.ndarray, concave: bool = True
                    ) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
        """Value, gradient and Hessian in ``z = [x, u]``: ``x [N, n]``, ``u [N, m]`` ->
        ``r [N]``, ``g [N, n+m]``, ``H [N, n+m, n+m]``.

        :param concave: keep only the concave parts of the Hessian (so ``-H`` is PSD; the
            cost's approximation, docs/agent.md); ``False``: the exact Hessian.
        """
        x, u = check_step_inputs(x, u, self.n, self.m)
        if x.ndim != 2:
            raise ValueError(f"x must be [N, {self.n}] (one batch dim), got {list(x.shape)}")
        r, h, _, Pe = self._terms(x, u)
        s = 1.0 - h * h
        g = (s * self.w) @ self.W.T + 2.0 * Pe
        coef = -2.0 * h * s * self.w  # w_j tanh''(a_j)
        if concave:
            coef = np.minimum(coef, 0.0)
        H = (self.W[None] * coef[:, None, :]) @ self.W.T
        return r, g, H + (self._P_concave if concave else 2.0 * self.P)


class LearnedRewardCost(CasadiCost):
    """The planning cost of a learned reward: stage ``l(x, u, t) = -r_hat(x, u)``, terminal
    ``l_T(x) = -terminal_weight * r_hat(x, 0)``; derivatives in closed form with a PSD Hessian
    (:meth:`FrozenReward.derivatives`). A :class:`mbtsr.costs.CasadiCost` by its kernels
    (``_batch_values``, ``_derivatives``), with no symbolic ``stage``/``terminal``.

    :param reward: a :class:`FrozenReward`.
    :param terminal_weight: weight (>= 0) of the terminal cost.
    :param param_dim: size of the parameter vector the cost accepts and ignores (0: none).
    """

    def __init__(self, reward: FrozenReward, *, terminal_weight: float = 1.0,
                 param_dim: int = 0) -> None:
        if not isinstance(reward, FrozenReward):
            raise TypeError(f"reward must be a FrozenReward, got {type(reward).__name__}")
        self.reward = reward
        self.n, self.m = reward.n, reward.m
        self.param_dim = check_int("param_dim", param_dim, 0)
        self.terminal_weight = check_nonnegative("terminal_weight", terminal_weight)
        self.params = None

    def _batch_values(self, Xs, Us, XT, t0: int, table) -> tuple[np.ndarray, np.ndarray]:
        """Stage costs ``[..., T]`` of ``Xs [..., T, n], Us [..., T, m]`` and terminal costs
        ``[...']`` of ``XT [...', n]`` (times and parameters do not matter)."""
        r = self.reward
        ls = -r._predict(np.asarray(Xs, dtype=float), np.asarray(Us, dtype=float))
        XT = np.asarray(XT, dtype=float)
        lT = -self.terminal_weight * r._predict(XT, np.zeros(XT.shape[:-1] + (self.m,)))
        return ls, lT

    def _derivatives(self, X: np.ndarray, U: np.ndarray, t0: int, table: np.ndarray
                     ) -> CostDerivatives:
        """:class:`CostDerivatives` along ``X [T+1, n]``, ``U [T, m]`` (one batched call)."""
        n, T = self.n, U.shape[0]
        Ue = np.vstack([U, np.zeros((1, self.m))])  # the terminal stage at zero action
        _, g, H = self.reward.derivatives(X, Ue)
        wt = np.ones(T + 1)
        wt[T] = self.terminal_weight
        g, H = -wt[:, None] * g, -wt[:, None, None] * H
        return CostDerivatives(lx=g[:, :n], lu=g[:T, n:], lxx=H[:, :n, :n], luu=H[:T, n:, n:],
                               lux=H[:T, n:, :n])
