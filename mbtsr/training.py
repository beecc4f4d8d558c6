"""Training of :class:`~mbtsr.ensemble.DynamicsEnsemble` with tangent-space regularization.

Objective of member ``k`` for one optimizer step on a batch ``b`` of transitions (paper Sec. II
loss; regularizers of Sec. III, switchable and combinable, each with its weight)::

    L_k = mean_{t in b} ||y_k(t) - r(t)||^2                               data
        + w_sampled * mean_{copies, t in b} ||y_k(t~) - r~(t)||^2           sampled JacProp
        + w_exact  * S * mean_{t in b} ||J_k(t) - [A_t B_t]||_F^2          exact matching
        + w_smooth * S * mean_{t, t+1 in b} ||J_k(t+1) - J_k(t)||_F^2      smoothness ("AD")

``y_k`` is the member's normalized network output and ``r`` the normalized residual target
(``EnsembleConfig.normalize``), so the data term is the original's "sum over state dimensions,
mean over samples". ``J_k`` is the member's Jacobian of the FULL map in raw units (skip part
included), ``[A_t B_t]`` the Jacobian of the trajectory's LTV model (:func:`mbtsr.ltv.fit_ltv`).
``S`` turns the mean into the paper's sum over time: with ``batch="trajectory"`` it is the number
of terms in the batch (so the penalty is exactly ``w sum_t``, as in the original's AD loss); with
minibatches it is the mean number of terms per training trajectory, which keeps the meaning of
``w`` independent of the batch size. The members' objectives are summed (they share no weights).

Sampled Jacobian propagation (paper Alg. 1): one LTV model per training trajectory, fitted once
per :func:`train_ensemble` call (or passed in); every epoch ``n_copies`` fresh perturbed copies
``x~ = x + eps_x, u~ = u + eps_u, eps ~ N(0, (sigma * std over time)^2)`` of every trajectory are
labelled ``x~+ = A_t x~ + B_t u~`` by that model (:meth:`mbtsr.ltv.LTVModel.sample_perturbed`).
Where the copies go is :attr:`RegularizationConfig.copies_batch`: ``"shared"`` (default) puts
them in the batch of their original transitions (same optimizer step, so the optimizer steps per
epoch equal the baseline's); ``"own"`` gives every copy of every batch its own optimizer step
after the epoch's data batches, as the original code did (it chained the perturbed trajectories
after the data as extra batches), so an epoch takes ``(1 + n_copies)`` times the baseline's
steps. Compare methods with the baseline at equal optimizer steps (:attr:`TrainHistory.steps`).
"""

from __future__ import annotations

import copy
import math
import time
from collections.abc import Callable, Sequence
from dataclasses import dataclass, field
from typing import Literal

import numpy as np
import torch
from torch.nn import functional as F  # noqa: N812
from tqdm.auto import tqdm

from mbtsr.ensemble import DynamicsEnsemble, _pool_transitions
from mbtsr.trajectory import Trajectory
from mbtsr.validation import check_nonnegative, check_positive

__all__ = ["TrainConfig", "RegularizationConfig", "REGULARIZERS", "DEFAULT_WEIGHTS", "TrainHistory",
           "train_ensemble"]

ORIGINAL_LTV_LAMBDA = float(np.sqrt(1000.0))
"""The original's jacprop LTV fit used R1 = I, R2 = 1000 I, i.e. ``lam^2 = R2 / R1 = 1000``."""


def _check_int(name: str, value: object, minimum: int) -> int:
    if isinstance(value, bool) or not isinstance(value, (int, np.integer)) or value < minimum:
        raise ValueError(f"{name} must be an int >= {minimum}, got {value!r}")
    return int(value)


@dataclass(frozen=True)
class TrainConfig:
    """Optimizer and schedule (Adam, paper Sec. "Nominal model").

    :param epochs: passes over the data. Paper: 1000 for g and 2000 for f, half of that with
        sampled Jacobian propagation.
    :param lr: Adam step size. The original used 0.02 (linear system, robot v1) and 0.01 (later
        scripts); 0.01 is the default here (normalized data, see ``docs/models.md``).
    :param batch: ``"trajectory"`` (one optimizer step per trajectory, like the original) or an
        int minibatch size (transitions drawn without replacement across trajectories).
    :param weight_decay: L2 weight decay on weight matrices only (not biases or layer-norm
        parameters). Coupled (added to the gradient before Adam, as in the original) unless
        ``decoupled_weight_decay``.
    :param decoupled_weight_decay: AdamW-style decay ``W <- W - lr * weight_decay * W``.
    :param betas: Adam's ``(beta1, beta2)``.
    :param adam_eps: Adam's epsilon (original: 1e-8; some scripts 1e-2).
    :param shuffle: reshuffle the batch order every epoch.
    :param seed: seeds batch order, perturbation sampling and dropout.
    :param progress: show a tqdm progress bar.
    """

    epochs: int = 1000
    lr: float = 0.01
    batch: int | Literal["trajectory"] = "trajectory"
    weight_decay: float = 0.0
    decoupled_weight_decay: bool = False
    betas: tuple[float, float] = (0.9, 0.999)
    adam_eps: float = 1e-8
    shuffle: bool = True
    seed: int = 0
    progress: bool = True

    def __post_init__(self) -> None:
        _check_int("epochs", self.epochs, 0)
        check_positive("lr", self.lr)
        if self.batch != "trajectory":
            _check_int("batch", self.batch, 1)
        check_nonnegative("weight_decay", self.weight_decay)
        check_positive("adam_eps", self.adam_eps)
        betas = tuple(self.betas)
        if len(betas) != 2 or not all(np.isfinite(b) and 0 <= b < 1 for b in betas):
            raise ValueError(f"betas must be two numbers in [0, 1), got {self.betas!r}")
        object.__setattr__(self, "betas", (float(betas[0]), float(betas[1])))
        if isinstance(self.seed, bool) or not isinstance(self.seed, (int, np.integer)):
            raise ValueError(f"seed must be an int, got {self.seed!r}")


REGULARIZERS = ("sampled", "exact", "smooth", "none")
"""The names :meth:`RegularizationConfig.named` knows (the first three combine by weights)."""

DEFAULT_WEIGHTS = {"sampled": 1.0, "exact": 0.01, "smooth": 0.01}
"""Default weight of each named regularizer (sampled: the paper's 1; exact/smooth: the agent's
measured setting, ``docs/ablation.md``)."""


@dataclass(frozen=True)
class RegularizationConfig:
    """Tangent-space regularizers; each is on when its weight is > 0, and they combine.

    :param sampled_weight: weight of the loss on LTV-labelled perturbed copies (sampled Jacobian
        propagation, the paper's method; paper value 1 = copies count like data).
    :param sigma: perturbation std relative to each dimension's std over time (paper: 0.1).
    :param n_copies: perturbed copies per trajectory per epoch (paper: 1).
    :param copies_batch: ``"shared"``: the perturbed copies join the batch of their original
        transitions (one optimizer step per batch, as the baseline); ``"own"``: each copy of
        each batch is its own optimizer step after the epoch's data batches (the original
        code's behaviour; ``1 + n_copies`` times the steps per epoch), its loss
        ``sampled_weight * mean ||y(x~) - r~||^2`` alone.
    :param exact_weight: weight of ``sum_t ||J_model(t) - J_LTV(t)||_F^2`` (double backprop).
    :param smooth_weight: weight of ``sum_t ||J_model(t+1) - J_model(t)||_F^2`` (the original's
        later "AD jacprop", paper eq. (reg)); needs no LTV model.
    :param ltv_lambda: ``lam`` of :func:`mbtsr.ltv.fit_ltv` (``lam^2`` = drift-to-noise variance
        ratio, scale dependent); default ``sqrt(1000)``, the original's R2 = 1000 I, R1 = I.
        ``None`` picks it per trajectory with :func:`mbtsr.ltv.select_lambda`.
    :param ltv_affine: fit LTV models with an affine term ``c_t``.
    """

    sampled_weight: float = 0.0
    sigma: float = 0.1
    n_copies: int = 1
    copies_batch: Literal["shared", "own"] = "shared"
    exact_weight: float = 0.0
    smooth_weight: float = 0.0
    ltv_lambda: float | None = ORIGINAL_LTV_LAMBDA
    ltv_affine: bool = False

    def __post_init__(self) -> None:
        for name in ("sampled_weight", "exact_weight", "smooth_weight", "sigma"):
            check_nonnegative(name, getattr(self, name))
        if self.copies_batch not in ("shared", "own"):
            raise ValueError(f"copies_batch must be 'shared' or 'own', got {self.copies_batch!r}")
        _check_int("n_copies", self.n_copies, 1)
        if self.ltv_lambda is not None:
            check_nonnegative("ltv_lambda", self.ltv_lambda)

    @classmethod
    def paper(cls, **overrides) -> RegularizationConfig:
        """The paper's sampled Jacobian propagation: one copy, sigma 0.1, weight 1."""
        return cls(**{"sampled_weight": 1.0, "sigma": 0.1, "n_copies": 1, **overrides})

    @classmethod
    def named(cls, kind: str, weight: float | None = None, **fields) -> RegularizationConfig:
        """One regularizer by name: ``"sampled"``, ``"exact"``, ``"smooth"`` or ``"none"``.

        ``weight`` is that regularizer's weight (default :data:`DEFAULT_WEIGHTS`: 1 for
        ``sampled``, the paper's; 0.01 for ``exact``/``smooth``); every other weight is 0.
        ``fields`` sets the remaining fields (``sigma``, ``n_copies``, ``ltv_lambda`` ...).
        ``RegularizationConfig.named("none")`` is the unregularized baseline.
        """
        if kind not in REGULARIZERS:
            raise ValueError(f"regularization must be one of {REGULARIZERS}, got {kind!r}")
        if kind == "none":
            if weight is not None:
                raise ValueError(f"regularization 'none' takes no weight, got {weight!r}")
            return cls(**fields)
        w = DEFAULT_WEIGHTS[kind] if weight is None else weight
        return cls(**{f"{kind}_weight": w, **fields})

    @property
    def kind(self) -> str:
        """The active regularizers' names joined by ``+`` (``"none"`` when all weights are 0),
        e.g. ``"sampled"`` or ``"sampled+smooth"``; the inverse of :meth:`named`."""
        on = [k for k in REGULARIZERS[:3] if getattr(self, f"{k}_weight") > 0]
        return "+".join(on) or "none"

    @property
    def sampled(self) -> bool:
        return self.sampled_weight > 0

    @property
    def exact(self) -> bool:
        return self.exact_weight > 0

    @property
    def smooth(self) -> bool:
        return self.smooth_weight > 0

    @property
    def needs_ltv(self) -> bool:
        return self.sampled or self.exact


@dataclass
class TrainHistory:
    """What :func:`train_ensemble` returns.

    :param train_loss: ``[epochs]`` data term (mean over members and training transitions,
        normalized units) accumulated during each epoch.
    :param val_loss: ``[epochs]`` the same data term on the validation trajectories after each
        epoch (evaluation mode); empty without validation data.
    :param penalties: ``{"sampled", "exact", "smooth"} -> [epochs]`` mean per-step value of each
        active regularizer (before its weight).
    :param wall_time: seconds spent in the call.
    :param optimizer_state: Adam's ``state_dict`` (a deep copy) to resume exactly.
    :param steps: optimizer steps taken.
    :param ltv_models: the LTV models used (one per training trajectory) or None.
    :param step_loss: ``[steps]`` the objective minimized at each optimizer step (summed over
        members, weights applied).
    """

    train_loss: np.ndarray
    val_loss: np.ndarray
    penalties: dict[str, np.ndarray] = field(default_factory=dict)
    wall_time: float = 0.0
    optimizer_state: dict | None = None
    steps: int = 0
    ltv_models: list | None = None
    step_loss: np.ndarray = field(default_factory=lambda: np.zeros(0))


def _as_trajectory_list(name: str, trajs: object) -> list[Trajectory]:
    if isinstance(trajs, Trajectory):
        return [trajs]
    if not isinstance(trajs, Sequence) or len(trajs) == 0:
        raise ValueError(f"{name} must be a non-empty list of Trajectory")
    for i, tr in enumerate(trajs):
        if not isinstance(tr, Trajectory):
            raise ValueError(f"{name}[{i}] must be a Trajectory, got {type(tr).__name__}")
    return list(trajs)


def _fit_ltv_models(trajs: list[Trajectory], reg: RegularizationConfig) -> list:
    from mbtsr.ltv import fit_ltv, select_lambda

    models = []
    for tr in trajs:
        lam = reg.ltv_lambda
        if lam is None:
            lam, _ = select_lambda(tr, affine=reg.ltv_affine)
        models.append(fit_ltv(tr, lam, affine=reg.ltv_affine))
    return models


def _check_ltv_models(ltv_models: object, trajs: list[Trajectory]) -> list:
    if not isinstance(ltv_models, Sequence) or len(ltv_models) != len(trajs):
        raise ValueError(
            f"ltv_models must be a list with one LTV model per training trajectory "
            f"({len(trajs)}), got {type(ltv_models).__name__}"
            + (f" of length {len(ltv_models)}" if isinstance(ltv_models, Sequence) else "")
        )
    for i, (lm, tr) in enumerate(zip(ltv_models, trajs)):
        A, B = getattr(lm, "A", None), getattr(lm, "B", None)
        if A is None or B is None or not hasattr(lm, "sample_perturbed"):
            raise ValueError(f"ltv_models[{i}] must be an LTV model with A, B, sample_perturbed")
        if np.shape(A)[0] < tr.T or np.shape(A)[1:] != (tr.n, tr.n) or np.shape(B)[1:] != (
            tr.n, tr.m
        ):
            raise ValueError(
                f"ltv_models[{i}] has A {list(np.shape(A))}, B {list(np.shape(B))}; trajectory "
                f"{i} needs at least [{tr.T}, {tr.n}, {tr.n}] and [{tr.T}, {tr.n}, {tr.m}]"
            )
    return list(ltv_models)


def _perturbed_copies(lm, tr: Trajectory, reg: RegularizationConfig, rng: np.random.Generator,
                      sx: np.ndarray, su: np.ndarray) -> tuple:
    """``lm.sample_perturbed(tr.x, tr.u, ...)`` with the per-trajectory scales ``sx, su``.

    For :class:`mbtsr.ltv.LTVModel` (whose inputs were validated once, up front) the same
    draws and the same arithmetic are done here without the per-call input validation, which
    cost about a third of a training epoch with many short trajectories; any other model with
    ``sample_perturbed`` is called as is.
    """
    from mbtsr.ltv import LTVModel

    if type(lm) is not LTVModel:
        return lm.sample_perturbed(tr.x, tr.u, sigma=reg.sigma, n_copies=reg.n_copies, seed=rng,
                                   std_x=sx, std_u=su)
    T, C = tr.T, reg.n_copies
    x_t = tr.x[:T] + reg.sigma * sx * rng.standard_normal((C, T, tr.n))
    u_t = tr.u + reg.sigma * su * rng.standard_normal((C, T, tr.m))
    out = np.einsum("tij,...tj->...ti", lm.A[:T], x_t)
    out += np.einsum("tij,...tj->...ti", lm.B[:T], u_t)
    return x_t, u_t, (out + lm.c[:T] if lm.c is not None else out)


def _optimizer(model: DynamicsEnsemble, config: TrainConfig) -> torch.optim.Optimizer:
    """Adam (coupled L2 on weights) or AdamW (decoupled), weight matrices decayed only."""
    weights, others = [], []
    for name, p in model.named_parameters():
        (weights if name.rsplit(".", 1)[-1] in ("W1", "W2", "Wo") else others).append(p)
    groups = [
        {"params": weights, "weight_decay": config.weight_decay},
        {"params": others, "weight_decay": 0.0},
    ]
    cls = torch.optim.AdamW if config.decoupled_weight_decay else torch.optim.Adam
    kw = {"lr": config.lr, "betas": config.betas, "eps": config.adam_eps}
    try:  # one fused kernel per group: the cheapest update at these sizes (CPU, torch >= 2.4)
        return cls(groups, fused=True, **kw)
    except (RuntimeError, TypeError):  # pragma: no cover - older torch
        return cls(groups, foreach=True, **kw)


def _check_optimizer_state(optimizer: torch.optim.Optimizer, state: object) -> None:
    """Refuse an Adam ``state_dict`` saved for another architecture BEFORE loading it (the fused
    kernel would read past the moment buffers: a segfault, not an exception)."""
    if not isinstance(state, dict) or not isinstance(state.get("param_groups"), list | tuple) \
            or not isinstance(state.get("state"), dict):
        raise ValueError("optimizer_state must be an optimizer state_dict with 'state' and "
                         f"'param_groups', got {type(state).__name__}")
    groups = optimizer.param_groups
    saved_groups = state["param_groups"]
    if len(saved_groups) != len(groups) or any(
            not isinstance(sg, dict) or len(sg.get("params", ())) != len(g["params"])
            for sg, g in zip(saved_groups, groups)):
        sizes = [len(sg.get("params", ())) if isinstance(sg, dict) else None
                 for sg in saved_groups]
        raise ValueError(
            f"optimizer_state does not fit this model: it holds parameter groups of sizes {sizes}"
            f", the model's optimizer {[len(g['params']) for g in groups]} (another architecture)")
    for sg, g in zip(saved_groups, groups):
        for pid, param in zip(sg["params"], g["params"]):
            buffers = state["state"].get(pid, {})
            for key in ("exp_avg", "exp_avg_sq", "max_exp_avg_sq"):
                buf = buffers.get(key) if isinstance(buffers, dict) else None
                if buf is not None and (not isinstance(buf, torch.Tensor)
                                        or tuple(buf.shape) != tuple(param.shape)):
                    got = list(buf.shape) if isinstance(buf, torch.Tensor) else type(buf).__name__
                    raise ValueError(
                        f"optimizer_state does not fit this model: state {pid} {key} has shape "
                        f"{got}, the parameter {list(param.shape)} (another architecture)")


def _finite_term(name: str, value: float, epoch: int) -> float:
    """``value`` of the loss term ``name``; a ``FloatingPointError`` naming it if it overflowed
    (checked before the optimizer step, so the weights stay finite)."""
    if not math.isfinite(value):
        what = "data term" if name == "data" else f"{name!r} regularizer term"
        fix = ("lower lr or check the data scale" if name == "data" else
               f"lower reg.{name}_weight or lr, or check the data and LTV Jacobian scales")
        raise FloatingPointError(f"the {what} of the loss is {value} at epoch {epoch}; {fix}")
    return value


def _squared_norm(a: torch.Tensor, dims: tuple[int, ...]) -> torch.Tensor:
    return (a * a).sum(dims)


def _sum_squared(y: torch.Tensor, target: torch.Tensor) -> torch.Tensor:
    """``sum (y - target)^2`` with ``y: [K, B, n]`` and ``target: [B, n]`` shared by members."""
    return F.mse_loss(y, target.expand_as(y), reduction="sum")


def train_ensemble(
    model: DynamicsEnsemble,
    trajs: Sequence[Trajectory] | Trajectory,
    config: TrainConfig = TrainConfig(),  # noqa: B008 - frozen dataclass
    reg: RegularizationConfig = RegularizationConfig(),  # noqa: B008
    validation: Sequence[Trajectory] | None = None,
    ltv_models: Sequence | None = None,
    optimizer_state: dict | None = None,
    callback: Callable[[int, DynamicsEnsemble], None] | None = None,
) -> TrainHistory:
    """Fit all members of ``model`` to ``trajs`` (in place) with optional tangent-space
    regularization (see the module docstring for the objective).

    Calling it again on grown data warm-starts from the current weights; pass the previous
    ``history.optimizer_state`` to resume Adam exactly. Normalization statistics are set from
    ``trajs`` on the first call only.

    :param model: the ensemble to train.
    :param trajs: training trajectories (each ``x: [T+1, n]``, ``u: [T, m]``).
    :param config: optimizer and schedule.
    :param reg: regularizers and their weights.
    :param validation: trajectories for the per-epoch validation loss.
    :param ltv_models: one LTV model per training trajectory (``A [>=T, n, n]``,
        ``B [>=T, n, m]``, ``sample_perturbed``); fitted with :func:`mbtsr.ltv.fit_ltv` if None
        and a regularizer needs them.
    :param optimizer_state: an Adam ``state_dict`` from a previous call.
    :param callback: optional diagnostic ``callback(epoch, model)`` called after every epoch
        with the model in evaluation mode (e.g. to log Jacobian errors during training; off by
        default). It must not change the weights; it draws no random numbers of the training.
    :return: :class:`TrainHistory`.
    """
    t_start = time.perf_counter()
    if not isinstance(model, DynamicsEnsemble):
        raise ValueError(f"model must be a DynamicsEnsemble, got {type(model).__name__}")
    if not isinstance(config, TrainConfig):
        raise ValueError(f"config must be a TrainConfig, got {type(config).__name__}")
    if not isinstance(reg, RegularizationConfig):
        raise ValueError(f"reg must be a RegularizationConfig, got {type(reg).__name__}")
    if callback is not None and not callable(callback):
        raise ValueError(f"callback must be callable or None, got {type(callback).__name__}")
    trajs = _as_trajectory_list("trajs", trajs)
    n, m = model.state_dim, model.action_dim
    xu_np, x_next_np = _pool_transitions(trajs, n, m)  # validates dims and finiteness
    lengths = [tr.T for tr in trajs]
    starts = np.concatenate([[0], np.cumsum(lengths)])
    N = int(starts[-1])
    val_data = None
    if validation is not None:
        validation = _as_trajectory_list("validation", validation)
        val_data = _pool_transitions(validation, n, m)

    if not model.is_normalized:
        model.set_normalization(trajs)
    if reg.needs_ltv:
        ltv_models = (_fit_ltv_models(trajs, reg) if ltv_models is None
                      else _check_ltv_models(ltv_models, trajs))
    elif ltv_models is not None:
        ltv_models = _check_ltv_models(ltv_models, trajs)

    # ---- tensors (float32, pooled over trajectories)
    with torch.no_grad():  # inputs are normalized once here, not in every step
        xu_raw = torch.as_tensor(xu_np, dtype=torch.float32)
        xu = model.normalize_inputs(xu_raw)
        target = model.normalized_residual(
            xu_raw, torch.as_tensor(x_next_np, dtype=torch.float32))
        if val_data is not None:
            xu_val_raw = torch.as_tensor(val_data[0], dtype=torch.float32)
            xu_val = model.normalize_inputs(xu_val_raw)
            target_val = model.normalized_residual(
                xu_val_raw, torch.as_tensor(val_data[1], dtype=torch.float32))
    # per-trajectory perturbation scales (std over time, as sample_perturbed's default),
    # computed once instead of every epoch
    scales = [(tr.x[:-1].std(0), tr.u.std(0)) for tr in trajs]
    J_ltv = None
    if reg.exact:
        J_ltv = torch.as_tensor(np.concatenate([
            np.concatenate([np.asarray(lm.A)[:tr.T], np.asarray(lm.B)[:tr.T]], -1)
            for lm, tr in zip(ltv_models, trajs)]), dtype=torch.float32)  # [N, n, n+m]
    trajectory_batches = config.batch == "trajectory"
    next_index = None
    if reg.smooth and not trajectory_batches:
        nxt = np.arange(1, N + 1)
        nxt[starts[1:] - 1] = -1  # last transition of each trajectory has no successor
        next_index = torch.as_tensor(nxt)
    mean_terms = N / len(trajs)  # S for minibatches: terms per trajectory
    mean_pairs = (N - len(trajs)) / len(trajs)

    # ---- optimizer and random streams
    optimizer = _optimizer(model, config)
    if optimizer_state is not None:
        _check_optimizer_state(optimizer, optimizer_state)
        try:
            optimizer.load_state_dict(optimizer_state)
        except (ValueError, KeyError, TypeError, RuntimeError) as err:
            raise ValueError(f"optimizer_state does not fit this model/config: {err}") from None
    rng = np.random.default_rng(config.seed)
    batch_gen = torch.Generator().manual_seed(int(config.seed))
    model.dropout_generator = torch.Generator().manual_seed(int(config.seed) + 1)

    E = config.epochs
    train_loss = np.zeros(E)
    val_loss = np.zeros(E) if val_data is not None else np.zeros(0)
    active = [k for k in ("sampled", "exact", "smooth") if getattr(reg, k)]
    penalties = {k: np.zeros(E) for k in active}
    steps = 0
    step_loss: list[float] = []
    K = model.n_members
    model.train()
    bar = tqdm(range(E), desc="train_ensemble", disable=not config.progress, leave=False)
    try:
        for epoch in bar:
            xu_pert = target_pert = None
            if reg.sampled:
                copies = [_perturbed_copies(lm, tr, reg, rng, sx, su)
                          for lm, tr, (sx, su) in zip(ltv_models, trajs, scales)]
                xt = np.concatenate([c[0] for c in copies], 1)  # [C, N, n]
                ut = np.concatenate([c[1] for c in copies], 1)
                xnt = np.concatenate([c[2] for c in copies], 1)
                with torch.no_grad():
                    xu_pert = torch.as_tensor(np.concatenate([xt, ut], -1), dtype=torch.float32)
                    target_pert = model.normalized_residual(
                        xu_pert, torch.as_tensor(xnt, dtype=torch.float32))
                    xu_pert = model.normalize_inputs(xu_pert)
            if trajectory_batches:
                order = (torch.randperm(len(trajs), generator=batch_gen).tolist()
                         if config.shuffle else range(len(trajs)))
                batches = [slice(int(starts[i]), int(starts[i + 1])) for i in order]
            else:
                size = int(config.batch)
                if config.shuffle:
                    batches = list(torch.split(torch.randperm(N, generator=batch_gen), size))
                else:  # contiguous ranges index by views, without gathering
                    batches = [slice(a, min(a + size, N)) for a in range(0, N, size)]
            data_sum = 0.0
            pen_sum = dict.fromkeys(active, 0.0)
            own_copies = xu_pert is not None and reg.copies_batch == "own"
            for idx in batches:
                parts = [xu[idx]]
                B = parts[0].shape[0]
                succ_valid = None
                if next_index is not None:  # minibatch smoothness: add successors
                    nxt_i = next_index[idx]
                    succ_valid = (nxt_i >= 0).nonzero().squeeze(-1)
                    parts.append(xu[nxt_i[succ_valid]])
                jac_rows = sum(p.shape[0] for p in parts) if (reg.exact or reg.smooth) else 0
                if xu_pert is not None and not own_copies:
                    parts.append(xu_pert[:, idx].reshape(-1, n + m))
                inputs = parts[0] if len(parts) == 1 else torch.cat(parts, 0)
                y, J = model.stacked_forward(inputs, jac_rows=jac_rows, normalized=True)
                # sum over members of (mean over points of the squared error norm)
                loss = _sum_squared(y[:, :B], target[idx]) / B
                data_sum += _finite_term("data", float(loss.detach()), epoch) / K * B
                if reg.sampled and not own_copies:
                    tp = target_pert[:, idx].reshape(-1, n)
                    pen = _sum_squared(y[:, inputs.shape[0] - tp.shape[0]:], tp) / tp.shape[0]
                    loss = loss + reg.sampled_weight * pen
                    pen_sum["sampled"] += _finite_term("sampled", float(pen.detach()), epoch) / K
                if reg.exact:
                    scale = B if trajectory_batches else mean_terms
                    pen = _squared_norm(J[:, :B] - J_ltv[idx], (-1, -2)).mean(-1) * scale
                    loss = loss + reg.exact_weight * pen.sum()
                    pen_sum["exact"] += _finite_term("exact", float(pen.detach().mean()), epoch)
                if reg.smooth:
                    if trajectory_batches:
                        dJ = J[:, 1:B] - J[:, : B - 1]
                        scale = B - 1
                    else:
                        dJ = J[:, B:jac_rows] - J[:, succ_valid]
                        scale = mean_pairs
                    if dJ.shape[1] > 0:
                        pen = _squared_norm(dJ, (-1, -2)).mean(-1) * scale
                        loss = loss + reg.smooth_weight * pen.sum()
                        pen_sum["smooth"] += _finite_term("smooth", float(pen.detach().mean()),
                                                          epoch)
                optimizer.zero_grad(set_to_none=True)
                loss.backward()
                optimizer.step()
                step_loss.append(float(loss.detach()))
                steps += 1
            if own_copies:  # the original's extra batches: one step per copy of each batch
                for idx in batches:
                    for c in range(reg.n_copies):
                        y, _ = model.stacked_forward(xu_pert[c, idx], normalized=True)
                        tp = target_pert[c, idx]
                        pen = _sum_squared(y, tp) / tp.shape[0]
                        loss = reg.sampled_weight * pen
                        pen_sum["sampled"] += _finite_term(
                            "sampled", float(pen.detach()), epoch) / K / reg.n_copies
                        optimizer.zero_grad(set_to_none=True)
                        loss.backward()
                        optimizer.step()
                        step_loss.append(float(loss.detach()))
                        steps += 1
            train_loss[epoch] = data_sum / N
            if not np.isfinite(train_loss[epoch]):
                raise FloatingPointError(
                    f"training diverged at epoch {epoch} (non-finite loss); lower lr or check "
                    "the data scale")
            for k in active:
                penalties[k][epoch] = pen_sum[k] / len(batches)
            if val_data is not None:
                model.eval()
                with torch.no_grad():
                    yv, _ = model.stacked_forward(xu_val, normalized=True)
                    val_loss[epoch] = float(_squared_norm(yv - target_val, (-1,)).mean())
                model.train()
            if callback is not None:
                model.eval()
                with torch.no_grad():
                    callback(epoch, model)
                model.train()
            if config.progress and (epoch % 10 == 0 or epoch == E - 1):
                post = {"loss": f"{train_loss[epoch]:.3g}"}
                if val_data is not None:
                    post["val"] = f"{val_loss[epoch]:.3g}"
                bar.set_postfix(post, refresh=False)
    finally:
        bar.close()
        model.eval()
    return TrainHistory(
        train_loss=train_loss,
        val_loss=val_loss,
        penalties=penalties,
        wall_time=time.perf_counter() - t_start,
        optimizer_state=copy.deepcopy(optimizer.state_dict()),
        steps=steps,
        ltv_models=ltv_models,
        step_loss=np.asarray(step_loss),
    )
