"""Training of :class:`~mbtsr.ensemble.DynamicsEnsemble` with tangent-space regularization.

The objective (data term, sampled Jacobian propagation, exact matching, smoothness) and both
schedules (the paper's epochs, a step budget with hold-out and early stopping): docs/models.md,
"Training" to "Tangent-space regularization". One loop (:func:`_train_loop`) runs either
schedule, a plan of rounds of batches (:class:`_EpochPlan`, :class:`_StepPlan`); every term of
the objective is written once (:func:`_objective`).
"""

from __future__ import annotations

import copy
import itertools
import math
import time
from collections.abc import Callable, Iterable, Iterator, Sequence
from dataclasses import dataclass, field
from typing import Literal

import numpy as np
import torch
from torch.nn import functional as F  # noqa: N812
from tqdm.auto import tqdm

from mbtsr.ensemble import DynamicsEnsemble, _pool_transitions
from mbtsr.trajectory import Trajectory, as_trajectory_list
from mbtsr.validation import check_choice, check_int, check_nonnegative, check_positive

__all__ = ["TrainConfig", "RegularizationConfig", "REGULARIZERS", "DEFAULT_WEIGHTS", "TrainHistory",
           "MEMBER_DATA", "EARLY_STOPPING", "holdout_mask", "train_ensemble"]

ORIGINAL_LTV_LAMBDA = float(np.sqrt(1000.0))
"""The original's jacprop LTV fit used R1 = I, R2 = 1000 I, i.e. ``lam^2 = R2 / R1 = 1000``."""


MEMBER_DATA = ("shared", "order", "bootstrap")
EARLY_STOPPING = ("member", "ensemble")
MIN_REL_IMPROVEMENT = 0.01
"""Early stopping: an evaluation counts as progress (resets ``patience``) when a validation loss
falls by more than this fraction of its best value (mbrl-lib's ``improvement_threshold``)."""
LOGVAR_BOUND_WEIGHT = 0.01
"""Probabilistic members: weight of ``sum(max_logvar) - sum(min_logvar)`` in the loss (PETS)."""
HOLDOUT_SEED = 20260901
"""Seed of the hold-out split's uniform stream (fixed, independent of ``TrainConfig.seed``)."""


@dataclass(frozen=True)
class TrainConfig:
    """Optimizer (Adam) and schedule: ``epochs`` passes over all data (the paper's, the
    default) or a budget of ``steps``; a hold-out, early stopping or per-member data take the
    step budget (:attr:`uses_step_loop`). Defaults and sources: docs/models.md, "Training".

    :param epochs: passes over the data (``steps=None``; paper 1000 for g, 2000 for f).
    :param lr: Adam step size.
    :param batch: ``"trajectory"`` (one step per trajectory; epochs only) or an int minibatch
        size.
    :param weight_decay: L2 decay of weight matrices only, coupled unless
        ``decoupled_weight_decay`` (AdamW).
    :param decoupled_weight_decay: AdamW-style decay ``W <- W - lr * weight_decay * W``.
    :param betas: Adam's ``(beta1, beta2)``.
    :param adam_eps: Adam's epsilon.
    :param shuffle: reshuffle the batch order every epoch (epochs only).
    :param seed: seeds batch order, perturbation sampling, bootstrap resampling and dropout.
    :param progress: show a tqdm progress bar.
    :param steps: gradient-step budget per call (``None``: ``epochs`` passes, as
        ``epochs * ceil(rows / batch)`` steps when the step loop runs).
    :param holdout: fraction of transitions held out for the validation loss, a prefix-stable
        function of the index (:func:`holdout_mask`).
    :param eval_every: steps between validation evaluations (also at step 0 and the end).
    :param patience: stop after this many evaluations without an improvement of more than
        :data:`MIN_REL_IMPROVEMENT` and restore the best weights (needs held-out data).
    :param early_stopping: ``"member"`` (each member its own best weights) or ``"ensemble"``
        (one snapshot by the ensemble mean's loss).
    :param member_data: ``"shared"`` minibatches, ``"order"`` (own stream per member) or
        ``"bootstrap"`` (own resample per member, drawn once per call).
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
    steps: int | None = None
    holdout: float = 0.0
    eval_every: int = 100
    patience: int | None = None
    early_stopping: Literal["member", "ensemble"] = "member"
    member_data: Literal["shared", "order", "bootstrap"] = "shared"

    def __post_init__(self) -> None:
        check_int("epochs", self.epochs, 0)
        check_positive("lr", self.lr)
        if self.batch != "trajectory":
            check_int("batch", self.batch, 1)
        check_nonnegative("weight_decay", self.weight_decay)
        check_positive("adam_eps", self.adam_eps)
        betas = tuple(self.betas)
        if len(betas) != 2 or not all(np.isfinite(b) and 0 <= b < 1 for b in betas):
            raise ValueError(f"betas must be two numbers in [0, 1), got {self.betas!r}")
        object.__setattr__(self, "betas", (float(betas[0]), float(betas[1])))
        check_int("seed", self.seed, None)
        if self.steps is not None:
            check_int("steps", self.steps, 1)
        check_nonnegative("holdout", self.holdout)
        if not self.holdout < 1:
            raise ValueError(f"holdout must be in [0, 1), got {self.holdout!r}")
        check_int("eval_every", self.eval_every, 1)
        if self.patience is not None:
            check_int("patience", self.patience, 1)
        check_choice("early_stopping", self.early_stopping, EARLY_STOPPING)
        check_choice("member_data", self.member_data, MEMBER_DATA)
        if self.batch == "trajectory" and self.uses_step_loop:
            on = [f"{name}={getattr(self, name)!r}" for name, off in (
                ("holdout", 0.0), ("patience", None), ("member_data", "shared"))
                if getattr(self, name) != off]
            raise ValueError(f"batch='trajectory' is the epoch schedule's; {', '.join(on)} need an "
                             "int minibatch size")

    @property
    def uses_step_loop(self) -> bool:
        """Whether training takes the step budget: with ``steps``, or with a hold-out, early
        stopping or per-member data (then ``epochs`` passes over the training rows set the
        budget). Otherwise it takes the paper's epoch schedule."""
        return self.steps is not None or self.holdout > 0 or self.patience is not None or (
            self.member_data != "shared")


REGULARIZERS = ("sampled", "exact", "smooth", "none")
"""The names :meth:`RegularizationConfig.named` knows (the first three combine by weights)."""

DEFAULT_WEIGHTS = {"sampled": 1.0, "exact": 0.01, "smooth": 0.01}
"""Default weight of each named regularizer (sampled: the paper's 1; exact/smooth: the agent's
setting measured on the arm, ``docs/ablation.md``)."""


@dataclass(frozen=True)
class RegularizationConfig:
    """Tangent-space regularizers; each is on when its weight is > 0, and they combine.

    :param sampled_weight: weight of the loss on LTV-labelled perturbed copies (sampled Jacobian
        propagation; paper 1).
    :param sigma: perturbation std relative to each dimension's std over time (paper: 0.1).
    :param n_copies: perturbed copies per trajectory per epoch (paper: 1).
    :param copies_batch: ``"shared"``: copies join their transitions' batch; ``"own"``: each
        copy of each batch is its own step after the epoch's data batches (the original's).
    :param exact_weight: weight of ``sum_t ||J_model(t) - J_LTV(t)||_F^2`` (double backprop).
    :param smooth_weight: weight of ``sum_t ||J_model(t+1) - J_model(t)||_F^2`` (no LTV model).
    :param ltv_lambda: ``lam`` of :func:`mbtsr.ltv.fit_ltv` (the original code's is
        ``sqrt(1000)``); ``None`` picks it per trajectory with :func:`mbtsr.ltv.select_lambda`.
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
        check_choice("copies_batch", self.copies_batch, ("shared", "own"))
        check_int("n_copies", self.n_copies, 1)
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
        check_choice("regularization", kind, REGULARIZERS)
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

    Training records one row per round: every epoch, or with a step budget at step 0 and
    every ``eval_every`` steps (the rows' step counts are :attr:`eval_steps`).

    :param train_loss: ``[rounds]`` the data term (mean over members and the round's training
        transitions, normalized units; the Gaussian NLL for probabilistic members; NaN at step 0).
    :param val_loss: ``[rounds]`` the members' mean squared error (evaluation mode) on the
        validation trajectories or the held-out rows at the round's end; empty without them.
    :param penalties: ``{"sampled", "exact", "smooth"} -> [rounds]`` mean per-step value of each
        active regularizer (before its weight).
    :param wall_time: seconds spent in the call.
    :param optimizer_state: Adam's ``state_dict`` (a deep copy) to resume exactly.
    :param steps: optimizer steps taken.
    :param ltv_models: the LTV models used (one per training trajectory) or None.
    :param step_loss: ``[steps]`` the objective minimized at each optimizer step (summed over
        members, weights applied).
    :param eval_steps: ``[rounds]`` the step count at each round's end.
    :param val_member_loss: ``[rounds, K]`` every member's validation loss (config order).
    :param val_ensemble_loss: ``[rounds]`` the validation loss of the ensemble mean.
    :param best_steps: with early stopping, ``[K]`` the step count of every member's restored
        weights (config order); ``None`` otherwise.
    :param stopped_early: True when ``patience`` ended training before the step budget.
    :param n_train, n_holdout: transitions trained on and held out.
    """

    train_loss: np.ndarray
    val_loss: np.ndarray
    penalties: dict[str, np.ndarray] = field(default_factory=dict)
    wall_time: float = 0.0
    optimizer_state: dict | None = None
    steps: int = 0
    ltv_models: list | None = None
    step_loss: np.ndarray = field(default_factory=lambda: np.zeros(0))
    eval_steps: np.ndarray = field(default_factory=lambda: np.zeros(0, int))
    val_member_loss: np.ndarray = field(default_factory=lambda: np.zeros((0, 0)))
    val_ensemble_loss: np.ndarray = field(default_factory=lambda: np.zeros(0))
    best_steps: np.ndarray | None = None
    stopped_early: bool = False
    n_train: int = 0
    n_holdout: int = 0


def holdout_mask(n: int, fraction: float) -> np.ndarray:
    """``[n]`` bool, True for held-out transitions: the ``j``-th uniform of a stream seeded with
    :data:`HOLDOUT_SEED` is below ``fraction``. A prefix property: the mask of ``n`` rows is the
    first ``n`` entries of the mask of more rows (appended data never moves old rows)."""
    return np.random.default_rng(HOLDOUT_SEED).random(int(n)) < fraction


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


def _optimizer(model: DynamicsEnsemble, config: TrainConfig) -> torch.optim.Optimizer:
    """Adam (coupled L2 on weights) or AdamW (decoupled), weight matrices decayed only."""
    weights, others = [], []
    for name, p in model.named_parameters():
        leaf = name.rsplit(".", 1)[-1]
        (weights if leaf[0] == "W" and (leaf[1:].isdigit() or leaf in ("Wo", "Wv"))
         else others).append(p)
    groups = [
        {"params": weights, "weight_decay": config.weight_decay},
        {"params": others, "weight_decay": 0.0},
    ]
    cls = torch.optim.AdamW if config.decoupled_weight_decay else torch.optim.Adam
    kw = {"lr": config.lr, "betas": config.betas, "eps": config.adam_eps}
    # one fused kernel per group: the cheapest update at these sizes (CPU, torch >= 2.4)
    return cls(groups, fused=True, **kw)


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


def _finite_term(name: str, value: float, step: int) -> None:
    """A ``FloatingPointError`` naming the loss term ``name`` if its ``value`` overflowed
    (checked before the optimizer step, so the weights stay finite)."""
    if not math.isfinite(value):
        what = "data term" if name == "data" else f"{name!r} regularizer term"
        fix = ("lower lr or check the data scale" if name == "data" else
               f"lower reg.{name}_weight or lr, or check the data and LTV Jacobian scales")
        raise FloatingPointError(f"the {what} of the loss is {value} at step {step}; {fix}")


def _squared_norm(a: torch.Tensor, dims: tuple[int, ...]) -> torch.Tensor:
    return (a * a).sum(dims)


def _data_sum(y: torch.Tensor, target: torch.Tensor, logvar: torch.Tensor | None) -> torch.Tensor:
    """The data term summed over members, points and dimensions: squared error, or for
    probabilistic members the Gaussian NLL ``(y - target)^2 exp(-logvar) + logvar`` (without
    the constant ``log 2 pi`` and the factor 1/2, as mbrl-lib). ``target`` ``[B, n]`` (shared)
    or ``[K, B, n]``."""
    if logvar is None:
        return F.mse_loss(y, target.expand_as(y), reduction="sum")
    d = y - target
    return (d * d * torch.exp(-logvar) + logvar).sum()


def _logvar_bound_penalty(model: DynamicsEnsemble) -> torch.Tensor:
    """``LOGVAR_BOUND_WEIGHT * (sum max_logvar - sum min_logvar)`` over all (probabilistic)
    members: PETS' term that keeps the soft bounds tight."""
    return LOGVAR_BOUND_WEIGHT * sum(g.max_logvar.sum() - g.min_logvar.sum()
                                     for g in model.groups)


# ---------------------------------------------------------------------------------------------
# one optimizer step: a batch and the objective's terms
# ---------------------------------------------------------------------------------------------


@dataclass
class _Batch:
    """Inputs and labels of one optimizer step, shared by the members (``[rows, ...]``) or one
    set per member (``[K, rows, ...]``, stacked order).

    :param inputs: ``[R, n+m]`` normalized: the ``b`` data rows first, then any successor rows
        (smoothness), the perturbed copies last.
    :param jac_rows: how many of the first rows need Jacobians (exact and smoothness terms).
    :param target: ``[b, n]`` targets of the data rows; None: a step on copies alone.
    :param copy_target: ``[c, n]`` labels of the last ``c`` rows (the copies).
    :param copy_share: divides the recorded sampled term (``n_copies`` when each copy takes its
        own step, so that an epoch's sum is a mean over the copies).
    :param J_ltv: ``[b, n, n+m]`` LTV Jacobians of the data rows (exact term).
    :param pairs: smoothness pairs ``(successors, firsts, mask)``: row selectors of the
        Jacobians and a ``[K, p]`` 0/1 weight of every pair (None: all count).
    :param exact_scale, smooth_scale: the terms' ``S`` (module docstring).
    """

    inputs: torch.Tensor
    jac_rows: int = 0
    target: torch.Tensor | None = None
    copy_target: torch.Tensor | None = None
    copy_share: int = 1
    J_ltv: torch.Tensor | None = None
    exact_scale: float = 1.0
    pairs: tuple | None = None
    smooth_scale: float = 1.0


def _objective(model: DynamicsEnsemble, batch: _Batch, reg: RegularizationConfig
               ) -> tuple[torch.Tensor, dict[str, float]]:
    """The loss of one step (module docstring), summed over members, and the value of every
    term present (before its weight, divided by the number of members for the data and
    sampled terms, mean over members for the Jacobian terms). Each term is written here once.

    :return: ``(loss, {"data"?, "sampled"?, "exact"?, "smooth"?: float})``.
    """
    y, J, lv = model.stacked_forward(batch.inputs, jac_rows=batch.jac_rows, normalized=True,
                                     logvar=True)
    K = model.n_members
    terms, loss = {}, None
    if batch.target is not None:  # sum over members of the mean over points
        b = batch.target.shape[-2]
        loss = _data_sum(y[:, :b], batch.target, None if lv is None else lv[:, :b]) / b
        terms["data"] = float(loss.detach()) / K
    if batch.copy_target is not None:
        c = batch.copy_target.shape[-2]
        first = y.shape[1] - c
        pen = _data_sum(y[:, first:], batch.copy_target, None if lv is None else lv[:, first:])
        pen = pen / c
        loss = reg.sampled_weight * pen if loss is None else loss + reg.sampled_weight * pen
        terms["sampled"] = float(pen.detach()) / K / batch.copy_share
    if lv is not None:
        loss = loss + _logvar_bound_penalty(model)
    if batch.J_ltv is not None:
        pen = _squared_norm(J[:, :batch.J_ltv.shape[-3]] - batch.J_ltv, (-1, -2)).mean(-1)
        pen = pen * batch.exact_scale
        loss = loss + reg.exact_weight * pen.sum()
        terms["exact"] = float(pen.detach().mean())
    if batch.pairs is not None:
        successors, firsts, mask = batch.pairs
        d = _squared_norm(J[:, successors] - J[:, firsts], (-1, -2))
        pen = d.mean(-1) if mask is None else (d * mask).sum(-1) / mask.sum(-1).clamp(min=1.0)
        pen = pen * batch.smooth_scale
        loss = loss + reg.smooth_weight * pen.sum()
        terms["smooth"] = float(pen.detach().mean())
    return loss, terms


def _train_loop(model: DynamicsEnsemble, optimizer: torch.optim.Optimizer,
                rounds: Iterator[Iterable[_Batch]], reg: RegularizationConfig,
                report: _Report, bar: tqdm) -> tuple[int, list[float]]:
    """The training loop of both schedules: every batch of every round (an epoch, or
    ``eval_every`` steps) takes one optimizer step; the :class:`_Report` records the terms,
    evaluates after every round and may stop training (early stopping).

    :param rounds: the schedule's rounds of batches (:class:`_EpochPlan`, :class:`_StepPlan`).
    :return: ``(steps, [steps] objective of every step)``.
    """
    steps, step_loss = 0, []
    if not report.begin():
        for batches in rounds:
            for batch in batches:
                loss, terms = _objective(model, batch, reg)
                for name, value in terms.items():
                    _finite_term(name, value, steps)
                optimizer.zero_grad(set_to_none=True)
                loss.backward()
                optimizer.step()
                step_loss.append(float(loss.detach()))
                steps += 1
                report.add(terms, batch)
                bar.update(1)
            if report.end_round(steps):
                break
    report.finish()
    return steps, step_loss


# ---------------------------------------------------------------------------------------------
# the training data and the two schedules
# ---------------------------------------------------------------------------------------------


class _Plan:
    """What both schedules share: the pooled training transitions (float32, built once per
    call; inputs raw and normalized ``[N, n+m]``, targets ``[N, n]``), every row's successor in
    its trajectory (-1 at its end), the mean rows and pairs per trajectory (the minibatch
    penalties' ``S``) and, if a term needs them, the rows' LTV Jacobians ``[N, n, n+m]``."""

    def __init__(self, model: DynamicsEnsemble, trajs: list[Trajectory], ltv_models: list | None,
                 config: TrainConfig, reg: RegularizationConfig, data: tuple) -> None:
        self.model, self.trajs, self.ltv_models, self.config, self.reg = (
            model, trajs, ltv_models, config, reg)
        self.xu_raw, self.xu, self.target = data
        self.starts = np.concatenate([[0], np.cumsum([tr.T for tr in trajs])])
        N, count = int(self.starts[-1]), len(trajs)
        successor = np.arange(1, N + 1)
        successor[self.starts[1:] - 1] = -1
        self.successor = torch.as_tensor(successor)
        self.mean_terms, self.mean_pairs = N / count, (N - count) / count
        # per-trajectory perturbation scales (std over time, as sample_perturbed's default)
        self.scales = [(tr.x[:-1].std(0), tr.u.std(0)) for tr in trajs]
        self.J_ltv = torch.as_tensor(np.concatenate([
            np.concatenate([np.asarray(lm.A)[:tr.T], np.asarray(lm.B)[:tr.T]], -1)
            for lm, tr in zip(ltv_models, trajs)]), dtype=torch.float32) if reg.exact or (
                reg.sampled and config.uses_step_loop) else None


class _EpochPlan(_Plan):
    """The paper's epoch schedule: ``epochs`` rounds, each a full pass over all transitions in
    batches of one trajectory or ``batch`` rows (reshuffled every epoch with ``shuffle``,
    members share them), with the perturbed copies of every trajectory resampled at the start
    of the epoch by its LTV model (numpy stream seeded ``config.seed``). With
    ``copies_batch="own"`` the epoch ends with one step per copy of each batch."""

    def __init__(self, *args) -> None:
        super().__init__(*args)
        config, reg = self.config, self.reg
        self.rng = np.random.default_rng(config.seed)
        self.gen = torch.Generator().manual_seed(int(config.seed))
        self.per_trajectory = config.batch == "trajectory"
        self.own = reg.sampled and reg.copies_batch == "own"
        n_batches = (len(self.trajs) if self.per_trajectory
                     else math.ceil(int(self.starts[-1]) / int(config.batch)))
        self.budget = config.epochs * n_batches * (1 + reg.n_copies if self.own else 1)

    def __iter__(self) -> Iterator[Iterable[_Batch]]:
        for _ in range(self.config.epochs):
            copies = self._copies() if self.reg.sampled else None
            order = self._order()
            data = (self._batch(idx, None if self.own else copies) for idx in order)
            if not self.own:
                yield data
                continue
            own = (_Batch(copies[0][c, idx], target=None, copy_target=copies[1][c, idx],
                          copy_share=self.reg.n_copies)
                   for idx in order for c in range(self.reg.n_copies))
            yield itertools.chain(data, own)

    def _copies(self) -> tuple[torch.Tensor, torch.Tensor]:
        """``[C, N, n+m]`` normalized inputs and ``[C, N, n]`` targets of the epoch's copies,
        ``sample_perturbed`` of every LTV model with its trajectory's scales. An
        :class:`~mbtsr.ltv.LTVModel` (validated once, up front) runs its kernel without the
        per-call validation (a third of an epoch with many short trajectories)."""
        from mbtsr.ltv import LTVModel

        reg, model, C = self.reg, self.model, self.reg.n_copies
        copies = [lm._sample_perturbed(tr.x, tr.u, reg.sigma, C, self.rng, sx, su)
                  if type(lm) is LTVModel else lm.sample_perturbed(
                      tr.x, tr.u, sigma=reg.sigma, n_copies=C, seed=self.rng, std_x=sx, std_u=su)
                  for lm, tr, (sx, su) in zip(self.ltv_models, self.trajs, self.scales)]
        xt, ut, xnt = (np.concatenate([c[i] for c in copies], 1) for i in range(3))
        with torch.no_grad():
            xu = torch.as_tensor(np.concatenate([xt, ut], -1), dtype=torch.float32)
            target = model.normalized_residual(xu, torch.as_tensor(xnt, dtype=torch.float32))
            return model.normalize_inputs(xu), target

    def _order(self) -> list:
        """The epoch's batches: row slices or index tensors."""
        starts, config = self.starts, self.config
        if self.per_trajectory:
            order = (torch.randperm(len(starts) - 1, generator=self.gen).tolist()
                     if config.shuffle else range(len(starts) - 1))
            return [slice(int(starts[i]), int(starts[i + 1])) for i in order]
        N, size = int(starts[-1]), int(config.batch)
        if config.shuffle:
            return list(torch.split(torch.randperm(N, generator=self.gen), size))
        return [slice(a, min(a + size, N)) for a in range(0, N, size)]  # views, no gather

    def _batch(self, idx: slice | torch.Tensor, copies: tuple | None) -> _Batch:
        reg = self.reg
        parts = [self.xu[idx]]
        B = parts[0].shape[0]
        pairs, smooth_scale = None, B - 1
        if reg.smooth and self.per_trajectory:
            pairs = (slice(1, B), slice(0, B - 1), None) if B > 1 else None
        elif reg.smooth:  # a minibatch's pairs: its rows with their successors appended
            nxt = self.successor[idx]
            valid = (nxt >= 0).nonzero().squeeze(-1)
            parts.append(self.xu[nxt[valid]])
            pairs = (slice(B, B + valid.numel()), valid, None) if valid.numel() else None
            smooth_scale = self.mean_pairs
        jac_rows = sum(p.shape[0] for p in parts) if (reg.exact or reg.smooth) else 0
        copy_target = None
        if copies is not None:
            parts.append(copies[0][:, idx].reshape(-1, parts[0].shape[-1]))
            copy_target = copies[1][:, idx].reshape(-1, self.target.shape[-1])
        return _Batch(
            parts[0] if len(parts) == 1 else torch.cat(parts, 0), jac_rows, self.target[idx],
            copy_target, J_ltv=self.J_ltv[idx] if reg.exact else None,
            exact_scale=B if self.per_trajectory else self.mean_terms, pairs=pairs,
            smooth_scale=smooth_scale)


class _StepPlan(_Plan):
    """The step budget: ``config.steps`` steps (or ``epochs`` passes over the training rows)
    in rounds of ``eval_every``. Every step takes one minibatch per member
    (:class:`_MemberStreams` over the rows not held out), its rows' successors (smoothness,
    masked at a trajectory's end) and ``n_copies`` perturbed copies of its rows drawn afresh
    (torch stream seeded ``config.seed + 2``), labelled by their rows' LTV Jacobians."""

    def __init__(self, *args, train_rows: torch.Tensor) -> None:
        super().__init__(*args)
        config, trajs, ltv_models = self.config, self.trajs, self.ltv_models
        self.streams = _MemberStreams(train_rows, self.model.n_members, config.batch,
                                      config.member_data,
                                      torch.Generator().manual_seed(int(config.seed)))
        self.noise_gen = torch.Generator().manual_seed(int(config.seed) + 2)
        self.budget = config.steps or config.epochs * math.ceil(
            train_rows.numel() / self.streams.batch)
        self.c_rows = self.s_rows = None  # per-row affine LTV terms and perturbation scales
        if self.reg.sampled and any(getattr(lm, "c", None) is not None for lm in ltv_models):
            self.c_rows = torch.as_tensor(np.concatenate([
                np.asarray(lm.c)[:tr.T] if getattr(lm, "c", None) is not None
                else np.zeros((tr.T, tr.n)) for lm, tr in zip(ltv_models, trajs)]),
                dtype=torch.float32)
        if self.reg.sampled:
            self.s_rows = torch.as_tensor(np.concatenate([
                np.broadcast_to(np.concatenate(s), (tr.T, tr.n + tr.m))
                for s, tr in zip(self.scales, trajs)]), dtype=torch.float32)

    def __iter__(self) -> Iterator[Iterable[_Batch]]:
        for start in range(0, self.budget, self.config.eval_every):
            yield (self._batch() for _ in range(min(self.config.eval_every,
                                                    self.budget - start)))

    def _batch(self) -> _Batch:
        reg, model = self.reg, self.model
        idx = self.streams.next()  # [K, b]
        K, b = idx.shape
        parts, pairs = [self.xu[idx]], None
        if reg.smooth:
            nxt = self.successor[idx]
            parts.append(self.xu[nxt.clamp(min=0)])
            pairs = (slice(b, 2 * b), slice(0, b), (nxt >= 0).float())
        jac_rows = (2 * b if reg.smooth else b) if (reg.exact or reg.smooth) else 0
        copy_target = None
        if reg.sampled:
            C, n = reg.n_copies, model.state_dim
            x0 = self.xu_raw[idx]  # [K, b, n+m]
            noise = torch.randn((C, *x0.shape), generator=self.noise_gen)
            xp = x0 + reg.sigma * self.s_rows[idx] * noise  # [C, K, b, n+m]
            label = torch.einsum("kboi,ckbi->ckbo", self.J_ltv[idx], xp)
            if self.c_rows is not None:
                label = label + self.c_rows[idx]
            with torch.no_grad():
                copy_target = model.normalized_residual(xp, label).transpose(0, 1).reshape(
                    K, C * b, n)
                parts.append(model.normalize_inputs(xp).transpose(0, 1).reshape(K, C * b, -1))
        return _Batch(
            parts[0] if len(parts) == 1 else torch.cat(parts, 1), jac_rows, self.target[idx],
            copy_target, J_ltv=self.J_ltv[idx] if reg.exact else None,
            exact_scale=self.mean_terms, pairs=pairs, smooth_scale=self.mean_pairs)


class _MemberStreams:
    """Per-member minibatch streams over training rows (stacked member order): a random
    permutation of the member's rows (all training rows, or its bootstrap resample), consumed
    ``batch`` rows at a time and redrawn when used up; ``"shared"`` is one stream for all. The
    streams' pools are equally long, so all redraw at the same step: one ``[S, rows]`` tensor
    of permutations, sliced per step."""

    def __init__(self, rows: torch.Tensor, K: int, batch: int, mode: str,
                 gen: torch.Generator) -> None:
        N = rows.numel()
        self.gen, self.batch, self.K = gen, min(int(batch), N), K
        if mode == "bootstrap":
            self.pools = torch.stack([rows[torch.randint(N, (N,), generator=gen)]
                                      for _ in range(K)])
        else:
            self.pools = rows.expand(1 if mode == "shared" else K, -1)
        self._redraw()

    def _redraw(self) -> None:
        self.perm = torch.stack([pool[torch.randperm(pool.numel(), generator=self.gen)]
                                 for pool in self.pools])
        self.pos = 0

    def next(self) -> torch.Tensor:
        """``[K, batch]`` row indices of the next step."""
        if self.pos + self.batch > self.perm.shape[1]:
            self._redraw()
        self.pos += self.batch
        return self.perm[:, self.pos - self.batch:self.pos].expand(self.K, -1)


# ---------------------------------------------------------------------------------------------
# what is recorded: per epoch, or per evaluation (with early stopping)
# ---------------------------------------------------------------------------------------------


class _Report:
    """What training records, per round (an epoch, or ``eval_every`` steps; a step budget also
    evaluates at step 0): the data term's mean over the round's transitions, each penalty's
    mean over its data steps, every member's and the ensemble mean's validation loss, and
    ``callback(epoch or step, model)``. With ``patience``: early stopping that keeps the best
    weights (per member or for the ensemble) and restores them at the end."""

    def __init__(self, model: DynamicsEnsemble, config: TrainConfig, active: list[str],
                 val: tuple | None, callback: Callable | None, bar: tqdm, budget: int,
                 per_epoch: bool) -> None:
        K = model.n_members
        self.model, self.config, self.active, self.val = model, config, active, val
        self.callback, self.bar, self.budget, self.per_epoch = callback, bar, budget, per_epoch
        self.early = config.patience is not None and val is not None
        self.per_member = config.early_stopping == "member"
        self.best = np.full(K if self.per_member else 1, np.inf)
        self.best_step = np.zeros(K, int)
        self.snapshot = ({name: p.detach().clone() for name, p in model.named_parameters()}
                         if self.early else None)
        self.since_progress, self.stopped = 0, False
        self.rows: list[dict] = []
        self._clear()

    def _clear(self) -> None:
        self.sums = dict.fromkeys(["data", *self.active], 0.0)
        self.data_rows = self.data_steps = 0

    def begin(self) -> bool:
        self.stopped = not self.per_epoch and self._evaluate(0)
        return self.stopped

    def add(self, terms: dict[str, float], batch: _Batch) -> None:
        if batch.target is not None:
            self.data_rows += batch.target.shape[-2]
            self.data_steps += 1
        for k, v in terms.items():
            self.sums[k] += v * batch.target.shape[-2] if k == "data" else v

    def end_round(self, steps: int) -> bool:
        self.stopped = self._evaluate(steps) and steps < self.budget
        if self.config.progress:
            row = self.rows[-1]
            self.bar.set_postfix({"loss": f"{row['train']:.3g}", **(
                {"val": f"{row['val']:.3g}"} if "val" in row else {})}, refresh=False)
        return self.stopped

    def _evaluate(self, step: int) -> bool:
        """Record the round; update the best weights; True: patience ran out."""
        model, n = self.model, self.data_steps
        row = {"step": step, "train": self.sums["data"] / self.data_rows if n else np.nan,
               **{k: self.sums[k] / n if n else np.nan for k in self.active}}
        self._clear()
        self.rows.append(row)
        model.eval()  # validation and callback: evaluation mode, no gradients
        try:
            with torch.no_grad():
                if self.val is not None:
                    yv, _ = model.stacked_forward(self.val[0], normalized=True)  # [K, V, n]
                    err = _squared_norm(yv - self.val[1], (-1,))
                    row.update(val=float(err.mean()), member=err.mean(-1).numpy().astype(float),
                               ensemble=float(_squared_norm(yv.mean(0) - self.val[1],
                                                            (-1,)).mean()))
                if self.callback is not None:
                    self.callback(len(self.rows) - 1 if self.per_epoch else step, model)
        finally:
            model.train()
        if not self.early:
            return False
        score = row["member"] if self.per_member else np.array([row["ensemble"]])
        better = score < self.best
        progress = bool(np.any(score < self.best * (1.0 - MIN_REL_IMPROVEMENT)))  # losses >= 0
        if better.any():
            members = [(g, i) for g in model.groups for i in range(g.n_members)]  # stacked
            with torch.no_grad():
                for k in np.flatnonzero(better) if self.per_member else range(len(members)):
                    g, i = members[k]
                    for name, p in g.named_parameters():
                        self.snapshot[_param_key(model, g, name)][i].copy_(p[i])
                    self.best_step[k] = step
            self.best[better] = score[better]
        self.since_progress = 0 if progress else self.since_progress + 1
        return self.since_progress >= self.config.patience

    def finish(self) -> None:
        if self.early:
            with torch.no_grad():
                for name, p in self.model.named_parameters():
                    p.copy_(self.snapshot[name])

    def history(self, **common) -> TrainHistory:
        order = np.argsort(self.model._stacked_order)  # stacked -> config order
        rows, K = self.rows, self.model.n_members

        def column(key: str) -> np.ndarray:  # validation columns are empty without validation
            return np.array([r[key] for r in rows if key in r])

        return TrainHistory(
            train_loss=column("train"), val_loss=column("val"),
            penalties={k: column(k) for k in self.active},
            eval_steps=np.array([r["step"] for r in rows], int),
            val_member_loss=column("member").reshape(-1, K)[:, order],
            val_ensemble_loss=column("ensemble"),
            best_steps=self.best_step[order] if self.early else None,
            stopped_early=bool(self.stopped), **common)


def _param_key(model: DynamicsEnsemble, group: torch.nn.Module, name: str) -> str:
    """The model-level parameter name of ``group``'s parameter ``name``."""
    return f"groups.{list(model.groups).index(group)}.{name}"


# ---------------------------------------------------------------------------------------------
# the public entry point
# ---------------------------------------------------------------------------------------------


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
    regularization; a second call warm-starts (normalization is set on the first call only).

    :param model: the ensemble to train.
    :param trajs: training trajectories (each ``x: [T+1, n]``, ``u: [T, m]``).
    :param config: optimizer and schedule.
    :param reg: regularizers and their weights.
    :param validation: trajectories for the validation loss.
    :param ltv_models: one LTV model per training trajectory (``A [>=T, n, n]``,
        ``B [>=T, n, m]``, ``sample_perturbed``); fitted with :func:`mbtsr.ltv.fit_ltv` if None
        and a regularizer needs them.
    :param optimizer_state: an Adam ``state_dict`` from a previous call.
    :param callback: optional diagnostic ``callback(epoch, model)`` after every epoch (a step
        budget: ``callback(step, model)`` at every evaluation), the model in evaluation mode;
        it must not change the weights.
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
    trajs = as_trajectory_list(trajs)
    n, m = model.state_dim, model.action_dim
    xu_np, x_next_np = _pool_transitions(trajs, n, m)  # validates dims and finiteness
    val_data = None
    if validation is not None:
        val_data = _pool_transitions(as_trajectory_list(validation, "validation"), n, m)
    if config.uses_step_loop and config.patience is not None and config.holdout == 0 \
            and val_data is None:
        raise ValueError("config.patience needs held-out data: config.holdout > 0 or "
                         "validation trajectories")
    if not model.is_normalized:
        model.set_normalization(trajs)
    if ltv_models is not None:
        ltv_models = _check_ltv_models(ltv_models, trajs)
    elif reg.needs_ltv:
        ltv_models = _fit_ltv_models(trajs, reg)

    with torch.no_grad():  # inputs are normalized once here, not in every step
        def normalized(xu_raw: np.ndarray, x_next: np.ndarray) -> tuple:
            xu_raw = torch.as_tensor(xu_raw, dtype=torch.float32)
            return xu_raw, model.normalize_inputs(xu_raw), model.normalized_residual(
                xu_raw, torch.as_tensor(x_next, dtype=torch.float32))

        data = normalized(xu_np, x_next_np)
        val = None if val_data is None else normalized(*val_data)[1:]

    optimizer = _optimizer(model, config)
    if optimizer_state is not None:
        _check_optimizer_state(optimizer, optimizer_state)
        try:
            optimizer.load_state_dict(optimizer_state)
        except (ValueError, KeyError, TypeError, RuntimeError) as err:
            raise ValueError(f"optimizer_state does not fit this model/config: {err}") from None
    model.dropout_generator = torch.Generator().manual_seed(int(config.seed) + 1)
    active = [k for k in ("sampled", "exact", "smooth") if getattr(reg, k)]
    if config.uses_step_loop:
        held = holdout_mask(len(xu_np), config.holdout)
        if held.all():
            held[:] = False  # too little data to hold any out and still train
        if held.any():
            held_rows = torch.as_tensor(np.flatnonzero(held))
            val = (data[1][held_rows], data[2][held_rows])
        train_rows = torch.as_tensor(np.flatnonzero(~held))
        plan = _StepPlan(model, trajs, ltv_models, config, reg, data, train_rows=train_rows)
    else:
        held = np.zeros(len(xu_np), bool)
        plan = _EpochPlan(model, trajs, ltv_models, config, reg, data)
    bar = tqdm(total=plan.budget, desc="train_ensemble", disable=not config.progress,
               leave=False)
    report = _Report(model, config, active, val, callback, bar, plan.budget,
                     per_epoch=not config.uses_step_loop)
    model.train()
    try:
        steps, step_loss = _train_loop(model, optimizer, iter(plan), reg, report, bar)
    finally:
        bar.close()
        model.eval()
    return report.history(
        wall_time=time.perf_counter() - t_start,
        optimizer_state=copy.deepcopy(optimizer.state_dict()), steps=steps,
        ltv_models=ltv_models, step_loss=np.asarray(step_loss), n_train=int((~held).sum()),
        n_holdout=int(held.sum()))
