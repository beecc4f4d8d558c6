"""Configuration of the Algorithm-1 agent: one tree of frozen dataclasses, validated when built.

::

    AgentConfig
    ├── collection      CollectionConfig                        rollouts: excitation, exploration
    ├── model           mbtsr.ensemble.ModelConfig              the ensemble's architecture
    ├── training        mbtsr.training.TrainConfig              one model update (Adam, epochs)
    ├── regularization  mbtsr.training.RegularizationConfig     THE knob of the project
    ├── planner         PlannerConfig                           iLQR / CEM MPC on the model
    ├── evaluation      EvaluationConfig                        evaluation and the "solved" test
    └── seed, run_dir, renormalize, ltv_prior, checkpoint, ...  bookkeeping and the update loop

``model``, ``training`` and ``regularization`` are the library's own configs, used as they are:
the agent hands ``training`` (with a per-update seed) and ``regularization`` to
:func:`mbtsr.training.train_ensemble` and builds its ensemble with ``model.build(n, m, seed)``
(the dimensions come from the env). The common calls stay short::

    AgentConfig(regularization="none")                 # a name: RegularizationConfig.named("none")
    AgentConfig(regularization="exact", planner="cem")  # (planner: PlannerConfig(kind="cem"))
    cfg.replace({"planner.horizon": 50, "model.hidden_width": 32}, seed=3)

An error names the full dotted field (``model.hidden_width must be an integer >= 1, got 0``).
Files: :meth:`AgentConfig.load` reads JSON or YAML (:func:`read_config_file`), a partial dict
being CHANGES to the defaults (:meth:`AgentConfig.from_dict`, the semantics of ``replace``), every
value checked against its field's type and coerced only where unambiguous; a run's
``config.json`` loads through its ``agent`` section. A setting that has no effect under the others
(a sampled-only field with another regularizer, a CEM field with iLQR, ...: ``_DEPENDENT``) is
refused with the reason, unless it holds its default.
Configs saved before the tree and its step budget (2026-12-02) are not read.

Where the paper fixes a value it is used (sampled Jacobian propagation with perturbations of 0.1 x
the per-dimension standard deviation, one perturbed copy resampled every step, the ``g``
formulation ``x+ = x + g(x, u)``). The model is sized by the task's dimensions and trained with
a budget of gradient steps per update (``docs/models.md``); ``ModelConfig.paper()`` and
``training.steps=None`` with ``training.epochs`` give the paper-sized model and the former
epoch schedule.
"""

from __future__ import annotations

import dataclasses
import difflib
import functools
import json
import math
import numbers
import os
import types
import typing
from collections.abc import Callable, Iterator, Mapping
from dataclasses import dataclass, field
from pathlib import Path
from typing import Any, ClassVar, Literal

import numpy as np

from mbtsr.cem import CEMOptions, cem
from mbtsr.cem_ilqr import CEMILQROptions, cem_ilqr
from mbtsr.ensemble import ModelConfig
from mbtsr.ilqr import ilqr
from mbtsr.training import REGULARIZERS, RegularizationConfig, TrainConfig

__all__ = ["AgentConfig", "CollectionConfig", "PlannerConfig", "EvaluationConfig",
           "read_config_file", "split_run_config", "in_file", "REGULARIZERS",
           "PLANNERS", "PROPAGATIONS", "EXCITATIONS"]

PLANNERS = ("ilqr", "cem", "cem-ilqr")
PROPAGATIONS = ("mean", "ts")
EXCITATIONS = ("filtered_gaussian", "multisine")


class _Checked:
    """Range checks whose messages name the field by its dotted path in the tree."""

    _path: ClassVar[str] = ""

    def _name(self, name: str) -> str:
        return f"{self._path}.{name}" if self._path else name

    def _int_at_least(self, name: str, low: int) -> None:
        v = getattr(self, name)
        if isinstance(v, bool) or not isinstance(v, int) or v < low:
            raise ValueError(f"{self._name(name)} must be an integer >= {low}, got {v!r}")

    def _float_range(self, name: str, low: float, high: float = math.inf, *,
                     low_open: bool = False) -> None:
        v = getattr(self, name)
        if isinstance(v, bool) or not isinstance(v, (int, float)) or not math.isfinite(v):
            raise ValueError(f"{self._name(name)} must be a finite number, got {v!r}")
        if (v <= low if low_open else v < low) or v > high:
            lo = "(" if low_open else "["
            raise ValueError(f"{self._name(name)} must be in {lo}{low}, {high}], got {v!r}")

    def _choice(self, name: str, options: tuple[str, ...]) -> None:
        v = getattr(self, name)
        if v not in options:
            raise ValueError(f"{self._name(name)} must be one of {options}, got {v!r}")


@dataclass(frozen=True)
class CollectionConfig(_Checked):
    """Data collection (Algorithm 1, "sample rollout trajectory").

    :param n_excitation_episodes: number of first episodes driven by an excitation signal
        instead of the planner (the model is untrained then).
    :param excitation: ``"filtered_gaussian"`` (low-pass filtered Gaussian noise, the paper's
        robot input) or ``"multisine"``.
    :param excitation_scale: excitation amplitude as a fraction of the action half-range.
    :param excitation_window: moving-average window (steps) of the filtered Gaussian input.
    :param exploration_std: std of Gaussian noise added to planned actions during training
        rollouts, as a fraction of the action half-range (0 disables it).
    :param episode_steps: steps per episode (training rollouts and evaluation); ``None`` uses
        the env's ``TimeLimit``.
    :param rollout_steps: steps per TRAINING rollout when shorter than the episode (evaluation
        keeps ``episode_steps``); ``None``: the episode's length. The model is updated after
        every rollout, so a run of the same env steps makes more updates, and each rollout
        restarts from a reset (unless ``continue_rollouts``). On HalfCheetah 200-step rollouts
        raised the median return from 476.7 to 741.5; most of that came from the updates and
        the shorter excitation (both help over 5 seeds), not from the resets
        (docs/benchmark.md, "Resets or updates?", "The excitation's length"). Everything that
        counts episodes counts these rollouts: the excitation (``n_excitation_episodes``
        rollouts of this length), ``evaluation.every``, ``learn(episodes=...)``; for
        evaluations at fixed env steps use ``evaluation.every_steps``.
    :param continue_rollouts: with ``rollout_steps``, a training rollout that stops at
        ``rollout_steps`` hands the env's episode on: the next rollout continues it after the
        model update instead of resetting (the env resets when its episode ends). The model is
        then updated every ``rollout_steps`` env steps without the restarts, as MBPO trains its
        model every 250 env steps. Each continued rollout starts a new plan (cold start) and new
        exploration noise, and a remainder shorter than ``rollout_steps`` at the episode's end
        is a rollout (and an update) of its own. Every ``learn`` call (and so a resumed
        checkpoint) starts from a reset, as does a rollout after the env was stepped or reset
        by anything else (with a warning; detected by its ``TimeLimit``).
    :param exploration_window: moving-average window (steps) of the exploration noise,
        rescaled to its stationary std (1: white noise; longer windows move the system further
        from the plan at the same amplitude, as the excitation does). The filter starts from
        rest, so the first ``W - 1`` steps of a rollout get less noise (std ``sqrt((t+1)/W)``
        of it at step ``t``).
    :param explore_weight: directed exploration: training rollouts plan with the CEM samples
        (``planner.kind`` ``"cem"``, or ``"cem-ilqr"``'s proposal) ranked by cost minus this
        weight x the ensemble's disagreement along them, in units of the samples' spreads
        (:class:`mbtsr.cem.CEMOptions` ``explore_weight``): the agent steers towards where its
        members disagree, the data it lacks. Evaluation plans without it. 0: off.
    :param explore_on: ``"state"`` (the members' variance of the next state) or ``"cost"``
        (their spread of the stage cost of their next states: only disagreement the task's
        cost sees); :class:`mbtsr.cem.CEMOptions` ``explore_on``.
    """

    _path: ClassVar[str] = "collection"
    n_excitation_episodes: int = 2
    excitation: Literal["filtered_gaussian", "multisine"] = "filtered_gaussian"
    excitation_scale: float = 0.3
    excitation_window: int = 8
    exploration_std: float = 0.1
    episode_steps: int | None = None
    rollout_steps: int | None = None
    continue_rollouts: bool = False
    exploration_window: int = 1
    explore_weight: float = 0.0
    explore_on: Literal["state", "cost"] = "state"

    def __post_init__(self) -> None:
        self._int_at_least("n_excitation_episodes", 1)
        self._choice("excitation", EXCITATIONS)
        self._float_range("excitation_scale", 0.0, 1.0, low_open=True)
        self._int_at_least("excitation_window", 1)
        self._float_range("exploration_std", 0.0)
        self._int_at_least("exploration_window", 1)
        self._float_range("explore_weight", 0.0)
        self._choice("explore_on", ("state", "cost"))
        if self.episode_steps is not None:
            self._int_at_least("episode_steps", 2)
        if self.rollout_steps is not None:
            self._int_at_least("rollout_steps", 2)
            if self.episode_steps is not None and self.rollout_steps >= self.episode_steps:
                raise ValueError(
                    f"collection.rollout_steps={self.rollout_steps} has no effect: it must be "
                    f"shorter than collection.episode_steps={self.episode_steps} (None: "
                    "rollouts as long as the episode)")
        if self.continue_rollouts and self.rollout_steps is None:
            raise ValueError("collection.continue_rollouts=True needs collection.rollout_steps "
                             "(rollouts shorter than the episode to continue)")


@dataclass(frozen=True)
class PlannerConfig(_Checked):
    """Planning (Algorithm 1, "optimize controller"): MPC = the planner re-solved every step on
    the learned model, warm-started with the shifted previous plan.

    :param horizon: MPC horizon (steps).
    :param replan_every: execute every plan for this many steps before re-solving (1:
        re-plan every step, the default; larger: the feedback-limited regime, where feedback
        hides less of the model's error; a fraction of the planning time). The oracle uses the
        same setting.
    :param replan_feedback: between re-plans, follow iLQR's local policy
        ``u_t = U_t + K_t (x_t - X_t)`` (the last backward pass's gains, on the model's
        Jacobians) instead of the plan's open-loop controls ``U_t`` (needs
        ``replan_every > 1`` and a planner with iLQR: ``kind`` ``"ilqr"`` or ``"cem-ilqr"``).
    :param kind: ``"ilqr"`` (iLQR on the model's Jacobians, the paper's controller), ``"cem"``
        (the cross-entropy method of PETS, :func:`mbtsr.cem.cem`: forward predictions only,
        never the model's Jacobians; the control for the paper's argument) or ``"cem-ilqr"``
        (the default: CEM proposes, iLQR refines with ``ilqr_iterations``,
        :func:`mbtsr.cem_ilqr.cem_ilqr`; CEM finds contacts where gradients are zero, iLQR's
        feedback balances what open-loop samples cannot; measured on the true models in
        docs/ilqr.md).
    :param terminal_weight: the planner's terminal cost is ``terminal_weight`` x the user's
        ``terminal_cost_fn(obs)`` (default: the stage cost at zero action).
    :param ilqr_iterations: iLQR iterations per MPC step (the first step of an episode gets
        ``first_plan_iterations``).
    :param first_plan_iterations: iLQR (or CEM) iterations for the full plan at the start of an
        episode.
    :param cem: the CEM settings (:class:`mbtsr.cem.CEMOptions`, the library's own): ``samples``
        (200) action sequences per iteration, ``elites`` (20) that refit the sampling
        distribution, ``iterations`` (3) per MPC step (the first step of an episode gets
        ``first_plan_iterations``), ``particles`` (1) rollouts per sequence; the agent seeds
        every solve from ``seed`` (``cem.seed`` stays 0).
    :param proposal: the CEM settings of ``kind="cem-ilqr"``'s proposal (64 samples, 8 elites,
        2 iterations per MPC step; seeded like ``cem``).
    :param propagation: how CEM rolls a sequence out on the ensemble: ``"mean"`` (the
        ensemble-mean model, as iLQR) or ``"ts"`` (trajectory sampling, PETS' TS-inf: each of
        the ``cem.particles`` rollouts of a sequence follows one member,
        :meth:`mbtsr.ensemble.FrozenEnsemble.trajectory_sampling`, and the sequence's cost is
        their mean; set ``cem.particles`` to a multiple of ``model.ensemble_size``, e.g. equal
        to it for deterministic members; probabilistic members also sample their noise).
        ``"ts"`` needs ``kind="cem"`` (iLQR, also cem-ilqr's refinement, plans on the mean).
    """

    _path: ClassVar[str] = "planner"
    horizon: int = 30
    replan_every: int = 1
    replan_feedback: bool = False
    kind: Literal["ilqr", "cem", "cem-ilqr"] = "cem-ilqr"
    terminal_weight: float = 1.0
    ilqr_iterations: int = 2
    first_plan_iterations: int = 20
    cem: CEMOptions = field(default_factory=lambda: CEMOptions(iterations=3))
    proposal: CEMOptions = field(
        default_factory=lambda: CEMOptions(samples=64, elites=8, iterations=2))
    propagation: Literal["mean", "ts"] = "mean"

    def __post_init__(self) -> None:
        self._choice("kind", PLANNERS)
        self._choice("propagation", PROPAGATIONS)
        if self.propagation == "ts" and self.kind != "cem":
            raise ValueError("planner.propagation='ts' (trajectory sampling) needs "
                             f"planner.kind='cem', got {self.kind!r}")
        for name, low in (("horizon", 2), ("replan_every", 1), ("ilqr_iterations", 1),
                          ("first_plan_iterations", 1)):
            self._int_at_least(name, low)
        self._float_range("terminal_weight", 0.0)
        if self.replan_every > self.horizon:
            raise ValueError(f"planner.replan_every must be <= planner.horizon={self.horizon}, "
                             f"got {self.replan_every}")
        for name in ("cem", "proposal"):
            opts = getattr(self, name)
            if not isinstance(opts, CEMOptions):
                raise ValueError(f"planner.{name} must be a mbtsr.cem.CEMOptions, got "
                                 f"{type(opts).__name__}")
            if opts.seed != 0:
                raise ValueError(f"planner.{name}.seed must be 0: the agent seeds every solve "
                                 f"from seed, got {opts.seed!r}")
            for f, default in (("explore_weight", 0.0), ("explore_on", "state")):
                if getattr(opts, f) != default:
                    raise ValueError(f"planner.{name}.{f} must be {default!r}: set "
                                     f"collection.{f} (training rollouts only), got "
                                     f"{getattr(opts, f)!r}")

    def optimizer(self, seed: int = 0, explore_weight: float = 0.0, explore_on: str = "state"
                  ) -> tuple[Callable[..., Any], Any, int]:
        """``(optimizer, options, iterations per MPC step)`` of :class:`mbtsr.mpc.MPC` for
        this planner, its sampling seeded from ``seed`` (the agent's and the oracle's), its
        CEM ranking with the disagreement bonus ``explore_weight`` on ``explore_on`` (not for
        iLQR)."""
        explore = {"explore_weight": explore_weight, "explore_on": explore_on}
        if self.kind == "ilqr":
            if explore_weight:
                raise ValueError("explore_weight needs a planner with CEM ('cem' or "
                                 "'cem-ilqr'), got planner.kind='ilqr'")
            return ilqr, None, self.ilqr_iterations
        if self.kind == "cem":
            options = dataclasses.replace(self.cem, seed=seed, **explore)
            return cem, options, options.iterations
        return cem_ilqr, CEMILQROptions(
            max_iter=self.ilqr_iterations,
            cem=dataclasses.replace(self.proposal, seed=seed, **explore)
        ), self.ilqr_iterations


@dataclass(frozen=True)
class EvaluationConfig(_Checked):
    """Evaluation: the deterministic MPC policy (no exploration noise) on ``episodes`` fixed
    episodes, logged as returns (sum of the env's rewards, per episode and their mean). The run
    is "solved" at the first evaluation whose mean return is ``>= solved_return`` when that is
    given (any env), else whose mean cost is within ``solved_ratio`` x the cost of MPC with the
    TRUE model on the same episodes (envs that offer a true model, e.g. the arm).

    :param every: evaluate every this many episodes from the last excitation episode on, and
        after the last episode of every ``learn`` call (0: never). ``episodes_to_solve`` is the
        episode of the first solved evaluation, so it is resolved to ``every`` episodes (an upper
        bound on the first episode whose model would have passed).
    :param episodes: evaluation episodes (fixed targets/seeds, see ``seed``).
    :param seed: seed of the evaluation targets and resets.
    :param early_exit: stop an evaluation as soon as the summed cost exceeds ``solved_ratio`` x
        the oracle's summed cost (exact for costs >= 0: such an evaluation cannot be solved); its
        ``eval_cost`` is then not logged and ``cost_ratio`` is a lower bound (see
        ``eval_episodes_run``).
    :param solved_ratio: the solved threshold relative to the oracle.
    :param solved_return: success threshold on the mean evaluation return (``None``: the
        oracle-ratio criterion, or no "solved" decision for envs without a true model).
    :param every_steps: also evaluate at the end of every episode that crosses a multiple of
        this many env steps (0: off), as SB3's ``eval_freq``: long episodes (HalfCheetah's 1000
        steps) make ``every`` episodes too coarse, many short ones (a pendulum that falls) too
        fine.
    :param stop_when_solved: stop ``learn`` at the first solved evaluation.
    :param oracle_cache_dir: folder where the oracle's evaluation costs are memoised across runs
        (``None``: recompute in every run).
    """

    _path: ClassVar[str] = "evaluation"
    every: int = 4
    every_steps: int = 0
    episodes: int = 3
    seed: int = 1000
    early_exit: bool = True
    solved_ratio: float = 1.2
    solved_return: float | None = None
    stop_when_solved: bool = False
    oracle_cache_dir: str | None = None

    def __post_init__(self) -> None:
        self._int_at_least("every", 0)
        self._int_at_least("every_steps", 0)
        self._int_at_least("episodes", 1)
        self._int_at_least("seed", 0)
        self._float_range("solved_ratio", 1.0)
        if self.solved_return is not None:
            self._float_range("solved_return", -math.inf)
        if self.oracle_cache_dir is not None and not isinstance(self.oracle_cache_dir, str):
            object.__setattr__(self, "oracle_cache_dir", str(self.oracle_cache_dir))


def _default_training() -> TrainConfig:
    """The agent's update: a budget of gradient steps, early stopping on a 10 % hold-out, the
    members drawing their own minibatches (``docs/models.md``, "Training with a step budget")."""
    return TrainConfig(steps=500, lr=1e-3, batch=256, holdout=0.1, eval_every=50, patience=5,
                       early_stopping="member", member_data="order", progress=False)


def _default_regularization() -> RegularizationConfig:
    return RegularizationConfig.named("sampled", ltv_lambda=None)


#: the sub-configs of the tree: field name -> its dataclass
SECTIONS: dict[str, type] = {
    "collection": CollectionConfig, "model": ModelConfig, "training": TrainConfig,
    "regularization": RegularizationConfig, "planner": PlannerConfig,
    "evaluation": EvaluationConfig,
}


@dataclass(frozen=True)
class AgentConfig(_Checked):
    """Everything that decides what :class:`agents.jacprop_agent.JacPropAgent` does.

    ``regularization`` and ``planner`` also accept a name (``"none"``, ``"sampled"``, ``"exact"``,
    ``"smooth"``; ``"ilqr"``, ``"cem"``): ``RegularizationConfig.named(name, ltv_lambda=None)``
    and ``PlannerConfig(kind=name)``.

    :param collection: data collection: excitation episodes, exploration noise, episode length.
    :param model: the ensemble (Objective 1 / 2 of the paper); built by the agent with
        ``model.build(state_dim, action_dim, seed)`` once the env's dimensions are known. By
        default its depth and width follow the task's dimensions
        (:func:`mbtsr.ensemble.default_size`); ``ModelConfig.paper()`` is the paper's 4 x 1 x 20.
    :param training: one model update (Algorithm 1, "fit f to tau_i and the perturbed tau_i"),
        warm-started (weights and Adam state carried across episodes) on ALL data so far. The
        default: ``training.steps`` gradient steps per update (500, minibatches of 256, Adam
        1e-3), early stopping on a 10 % hold-out (evaluated every 50 steps, patience 5, every
        member restored to its best weights), members drawing their own minibatch order: an
        update costs at most the same at any data size. ``steps=None``: ``training.epochs``
        passes over all data (the former schedule). The agent gives every update its own seed
        (derived from ``seed``), so ``training.seed`` must stay 0.
    :param regularization: the tangent-space regularizer (:mod:`mbtsr.training` has the exact
        objective): ``sampled_weight`` > 0: sampled Jacobian propagation (LTV-labelled perturbed
        points, Section 3 of the paper, the default), ``exact_weight``: the penalty it
        approximates, ``sum_t ||J_model(t) - [A_t B_t]_LTV||_F^2``, by double backprop,
        ``smooth_weight``: the LTV-free ``sum_t ||J_model(t+1) - J_model(t)||_F^2`` of Eq. (reg),
        all 0: none. ``ltv_lambda`` is the smoothness weight of the agent's LTV fit (Algorithm 1,
        "fit LTV model"; ``None``: :func:`mbtsr.ltv.select_lambda` on every trajectory).
    :param planner: the MPC planner (iLQR or CEM) on the learned model.
    :param evaluation: evaluation episodes and the "solved" criterion.
    :param seed: master seed; every random draw of a run derives from it.
    :param renormalize: before every update, recompute the model's input/output normalization
        from ALL data so far (:meth:`mbtsr.ensemble.DynamicsEnsemble.refit_normalization`, which
        keeps the represented function), instead of freezing the statistics of the first
        episode. ``False``: the first episode's statistics are kept (the old behaviour).
    :param ltv_prior: once the model has seen data, fuse each new LTV fit with the ensemble's
        Jacobians as a Gaussian prior (mean: ensemble mean, variance: ensemble variance +
        ``ltv_prior``; :func:`mbtsr.ltv.fuse_prior`), as the original code's "jacprop with prior"
        did. MPC rollouts excite the system little, and an LTV fit to one of them alone has wild
        Jacobians in the unexcited directions; the prior keeps the model's Jacobians there.
        ``0`` disables it.
    :param run_dir: folder for the CSV log, TensorBoard, checkpoint and exports (``None``: none).
    :param checkpoint: write a checkpoint after every episode (needs ``run_dir``).
    :param tensorboard: write TensorBoard scalars (needs ``run_dir``).
    :param video: save a video of every ``video_every``-th episode (env must render rgb_array).
    :param video_every: see ``video``.
    :param jacobian_error: log the Jacobian error against ``env.unwrapped.linearize_trajectory``
        when the env provides it.
    :param progress: show a progress bar in ``learn``.
    :param torch_threads: threads of torch and of numpy's BLAS (``threadpoolctl``), applied by
        ``learn`` (0: leave as is). Default 1: the networks are small and overhead-bound, and
        on a busy 2-core machine torch's 2 threads ran ``scripts/train_agent.py`` 21x slower
        than one (489 s against 23 s, 2026-12-04).
    """

    collection: CollectionConfig = field(default_factory=CollectionConfig)
    model: ModelConfig = field(default_factory=ModelConfig)
    training: TrainConfig = field(default_factory=_default_training)
    regularization: RegularizationConfig = field(default_factory=_default_regularization)
    planner: PlannerConfig = field(default_factory=PlannerConfig)
    evaluation: EvaluationConfig = field(default_factory=EvaluationConfig)
    seed: int = 0
    renormalize: bool = True
    ltv_prior: float = 0.01
    run_dir: str | None = None
    checkpoint: bool = True
    tensorboard: bool = True
    video: bool = False
    video_every: int = 5
    jacobian_error: bool = True
    progress: bool = True
    torch_threads: int = 1

    def __post_init__(self) -> None:
        for name, named in _NAMED.items():  # a name for a section: that section, fresh
            if isinstance(getattr(self, name), str):
                object.__setattr__(self, name, _prefixed(name, named, getattr(self, name)))
        for name, cls in SECTIONS.items():
            if not isinstance(getattr(self, name), cls):
                raise ValueError(f"{name} must be a {cls.__module__}.{cls.__name__} (or a dict of "
                                 f"its fields), got {type(getattr(self, name)).__name__}")
        if self.run_dir is not None and not isinstance(self.run_dir, str):
            object.__setattr__(self, "run_dir", str(self.run_dir))
        for dotted, value, hint in _leaves(self):  # every leaf of its declared type
            _coerce(value, hint, dotted, strict=True)
        if self.training.epochs < 1:
            raise ValueError(
                f"training.epochs must be an integer >= 1, got {self.training.epochs!r}")
        if self.training.patience is not None and self.training.holdout == 0:
            raise ValueError(
                f"training.patience={self.training.patience!r} has no effect: early stopping "
                "needs held-out data (training.holdout > 0): set training.patience=None to "
                "train the whole budget, or a hold-out")
        if self.training.seed != 0:
            raise ValueError("training.seed must be 0: the agent seeds every update from seed, "
                             f"got {self.training.seed!r}")
        lam = self.regularization.ltv_lambda
        if lam is not None and not lam > 0:
            raise ValueError(f"regularization.ltv_lambda must be > 0 or None (automatic), "
                             f"got {lam!r}")
        if self.regularization.ltv_affine:
            raise ValueError("regularization.ltv_affine must be False: the agent's LTV fits "
                             "have no affine term")
        self._int_at_least("seed", 0)
        self._float_range("ltv_prior", 0.0)
        self._int_at_least("video_every", 1)
        self._int_at_least("torch_threads", 0)
        values = self.dotted()
        for dotted, reason in _inactive(values).items():
            raise ValueError(f"{dotted}={values[dotted]!r} has no effect: {reason}")

    # ---- convenience -------------------------------------------------------------------------
    def replace(self, changes: Mapping[str, Any] | None = None, /, **top: Any) -> AgentConfig:
        """A copy with changes applied (validated again): ``changes`` maps dotted field names to
        values (``{"planner.horizon": 50, "regularization": "none"}``), a section to a dict of its
        changes (``{"model": {"hidden_width": 32}}``); keywords set top-level fields
        (``seed=3``, ``model=ModelConfig(...)``, ``regularization="exact"``). Fields not given
        keep this config's values. Values are coerced where unambiguous (see
        :func:`from_dict`).

        :raises ValueError: naming the dotted field (unknown, with the closest valid one; of
            the wrong type; out of range; or without effect under the other settings).
        """
        return _replaced(self, {**(changes or {}), **top}, "")

    @classmethod
    def default(cls, changes: Mapping[str, Any] | None = None, /, **top: Any) -> AgentConfig:
        """``AgentConfig().replace(changes, **top)``: the defaults with these changes, e.g.
        ``AgentConfig.default({"planner.horizon": 20}, regularization="none")``."""
        return cls().replace(changes, **top)

    def dotted(self) -> dict[str, Any]:
        """``{dotted field: value}`` of every leaf of the tree (``"planner.cem.samples": 200``)."""
        return {name: value for name, value, _ in _leaves(self)}

    def changes(self) -> dict[str, Any]:
        """The leaves that differ from ``AgentConfig()``'s, by dotted name: the partial config
        that ``AgentConfig.default(cfg.changes()) == cfg`` rebuilds."""
        defaults = _default_leaves()
        return {k: v for k, v in self.dotted().items() if v != defaults[k]}

    # ---- (de)serialisation: the config is saved as JSON next to the results ------------------
    def to_dict(self) -> dict[str, Any]:
        """A JSON-friendly nested dict of all fields (tuples as lists)."""
        return json.loads(json.dumps(dataclasses.asdict(self)))

    def to_json(self) -> str:
        return json.dumps(self.to_dict(), indent=2, sort_keys=True)

    @classmethod
    def from_dict(cls, d: Mapping[str, Any], /, base: AgentConfig | None = None) -> AgentConfig:
        """A config from a (partial) nested dict: the CHANGES it gives to ``base`` (default
        ``AgentConfig()``), with the semantics of :meth:`replace`; :meth:`to_dict`'s inverse.

        Sections are dicts (``{"model": {"hidden_width": 32}}``) or, for ``regularization`` and
        ``planner``, names (``"none"``, ``"cem"``); dotted keys (``"planner.horizon"``) work too.
        Every value is checked against its field's type and coerced where unambiguous: a
        number given as a string (YAML 1.1 reads ``1e-3`` as one) is parsed (``"1e-3"`` -> 0.001
        for a float field, ``"50"`` -> 50 for an integer field, not ``"2.5"``), an integral
        float is an integer (``50.0`` -> 50), ``"true"``/``"false"`` are booleans,
        ``"none"``/``"null"`` is ``None`` where the field takes ``None`` but no string, a list is
        a tuple; anything else of the wrong type is refused.

        :param d: the fields, nested or dotted.
        :param base: the config the changes apply to (default ``AgentConfig()``).

        :raises ValueError: naming the dotted field: unknown (with the closest valid field),
            of the wrong type, out of range, or without effect under the other settings.
        """
        if not isinstance(d, Mapping):
            raise ValueError(f"AgentConfig.from_dict needs a dict of AgentConfig fields, got "
                             f"{type(d).__name__} {d!r}")
        training = d.get("training")  # a whole config saved before the step budget?
        base = base or cls()
        if (base.training.steps is not None and isinstance(training, Mapping)
                and "epochs" in training and "steps" not in training
                and {"collection", "model", "planner", "evaluation"} <= d.keys()):
            raise ValueError("training.epochs without training.steps: set training.steps: null "
                             "for the epoch schedule (a config saved before training.steps "
                             "existed, 2026-12-02, is not read: its training meant other "
                             "defaults)")
        return base.replace(d)

    @classmethod
    def from_json(cls, text: str) -> AgentConfig:
        """:meth:`from_dict` of a JSON object (a key given twice is an error).

        :param text: the JSON text, e.g. :meth:`to_json`'s.
        """
        return cls.from_dict(json.loads(text, object_pairs_hook=_unique_keys))

    @classmethod
    def load(cls, path: str | os.PathLike, base: AgentConfig | None = None) -> AgentConfig:
        """The config in a JSON or YAML file (:func:`read_config_file`): a dict of (some)
        AgentConfig fields, changes to ``base`` as in :meth:`from_dict`, or a run's
        ``config.json`` (its ``agent`` section).

        :raises ValueError: naming the file and the problem (unreadable, not JSON/YAML, not a
            dict, or a bad field named by its dotted path).
        """
        try:
            agent, _ = split_run_config(read_config_file(path))
            return cls.from_dict(agent, base=base)
        except ValueError as err:
            raise in_file(path, err) from None


# ---- the tree's fields: types, defaults, coercion ---------------------------------------------
_NAMED: dict[str, Any] = {  # the sections a name can stand for
    "regularization": lambda name: RegularizationConfig.named(name, ltv_lambda=None),
    "planner": lambda name: PlannerConfig(kind=name),
}


@functools.cache
def _hints(cls: type) -> dict[str, Any]:
    """The resolved type of every field of dataclass ``cls``."""
    hints = typing.get_type_hints(cls)
    return {f.name: hints[f.name] for f in dataclasses.fields(cls)}


def _is_section(hint: Any) -> bool:
    return isinstance(hint, type) and dataclasses.is_dataclass(hint)


def _leaves(obj: Any, prefix: str = "") -> Iterator[tuple[str, Any, Any]]:
    """``(dotted name, value, declared type)`` of every non-section field of ``obj``'s tree."""
    for name, hint in _hints(type(obj)).items():
        value = getattr(obj, name)
        if _is_section(hint):
            yield from _leaves(value, f"{prefix}{name}.")
        else:
            yield prefix + name, value, hint


def _field_default(f: dataclasses.Field) -> Any:
    return f.default_factory() if f.default_factory is not dataclasses.MISSING else f.default


@functools.cache
def _default_leaves() -> dict[str, Any]:
    """The dotted leaves of ``AgentConfig()`` (built from the field defaults, not by
    constructing it: its validation uses them)."""
    out: dict[str, Any] = {}
    for f in dataclasses.fields(AgentConfig):
        value = _field_default(f)
        if dataclasses.is_dataclass(value):
            out.update({k: v for k, v, _ in _leaves(value, f"{f.name}.")})
        else:
            out[f.name] = value
    return out


@functools.cache
def _class_default_leaves() -> dict[str, Any]:
    """The dotted leaves of every section at ITS class's defaults (``RegularizationConfig()``'s
    ``ltv_lambda`` is 31.6, the agent's None): a value equal to either default was not chosen."""
    out: dict[str, Any] = {}

    def walk(cls: type, prefix: str) -> None:
        for f in dataclasses.fields(cls):
            hint = _hints(cls)[f.name]
            if _is_section(hint):
                walk(hint, f"{prefix}{f.name}.")
            elif prefix and (f.default is not dataclasses.MISSING
                             or f.default_factory is not dataclasses.MISSING):
                out[prefix + f.name] = _field_default(f)

    walk(AgentConfig, "")
    return out


@functools.cache
def _all_paths() -> tuple[str, ...]:
    """Every dotted field of the tree, sections included (for "did you mean")."""
    out: list[str] = []

    def walk(cls: type, prefix: str) -> None:
        for name, hint in _hints(cls).items():
            out.append(prefix + name)
            if _is_section(hint):
                walk(hint, f"{prefix}{name}.")

    walk(AgentConfig, "")
    return tuple(out)


def _describe(hint: Any) -> str:
    """``float | None`` -> ``"a number or null"`` (the words of the type errors)."""
    origin, args = typing.get_origin(hint), typing.get_args(hint)
    if origin in (typing.Union, types.UnionType):
        return " or ".join(_describe(a) for a in args)
    if origin is Literal:
        return repr(args[0]) if len(args) == 1 else f"one of {args}"
    if origin is tuple:
        item = _describe(args[0]).split(" ", 1)[-1]  # "a number" -> "number"
        count = "" if args[-1] is Ellipsis else f"{len(args)} "
        return f"a list of {count}{item}s"
    return {bool: "true or false", int: "an integer", float: "a number", str: "a string",
            type(None): "null"}.get(hint, getattr(hint, "__name__", str(hint)))


def _number(value: Any) -> float | None:
    """A real number given as a number or a numeric string (not a bool), else None."""
    if isinstance(value, (bool, np.bool_)):
        return None
    if isinstance(value, numbers.Real):
        return float(value)
    if isinstance(value, str):
        try:
            return float(value.strip())
        except ValueError:
            return None
    return None


def _coerce(value: Any, hint: Any, name: str, *, strict: bool = False) -> Any:
    """``value`` as the type ``hint`` of field ``name`` (dotted), coerced where unambiguous (see
    :meth:`AgentConfig.from_dict`); ``strict``: no coercion, only the type check.

    :raises ValueError: ``"<name> must be <type>, got <value>"``.
    """
    origin, args = typing.get_origin(hint), typing.get_args(hint)
    bad = ValueError(f"{name} must be {_describe(hint)}, got {value!r}")
    if origin in (typing.Union, types.UnionType):
        if value is None:
            if type(None) in args:
                return None
            raise bad
        for option in sorted(args, key=lambda a: typing.get_origin(a) is not Literal):
            if option is not type(None):
                try:
                    return _coerce(value, option, name, strict=strict)
                except ValueError:
                    pass
        if (not strict and type(None) in args and str not in args and isinstance(value, str)
                and value.strip().lower() in ("none", "null")):
            return None
        raise bad
    if origin is Literal:
        if isinstance(value, str) and value in args:
            return value
        raise bad
    if origin is tuple:
        if not strict and isinstance(value, str) and args[-1] is Ellipsis:
            value = (value,)  # one name for a list of names
        if not isinstance(value, (tuple, list)) or (strict and not isinstance(value, tuple)):
            raise bad
        items = args[:1] * len(value) if args[-1] is Ellipsis else args
        if len(items) != len(value):
            raise bad
        try:
            return tuple(_coerce(v, h, name, strict=strict) for v, h in zip(value, items))
        except ValueError:
            raise bad from None
    if hint is bool:
        if isinstance(value, (bool, np.bool_)):
            return bool(value)
        if not strict and isinstance(value, str) and value.strip().lower() in ("true", "false"):
            return value.strip().lower() == "true"
        raise bad
    if hint is int:
        if isinstance(value, numbers.Integral) and not isinstance(value, (bool, np.bool_)):
            return int(value)
        number = None if strict else _number(value)
        if number is not None and math.isfinite(number) and number == int(number):
            return int(number)
        raise bad
    if hint is float:
        number = _number(value) if (not strict or not isinstance(value, str)) else None
        if number is None:
            raise bad
        return number
    if hint is str:
        if isinstance(value, str):
            return value
        if isinstance(value, os.PathLike):
            return os.fspath(value)
        raise bad
    return value  # a type the tree does not use: unchecked


#: settings that act only under another setting: (fields, needed(dotted values), reason); a
#: value other than the default in such a field, while it is not needed, is refused
_DEPENDENT: tuple[tuple[tuple[str, ...], Callable[[Mapping[str, Any]], bool], str], ...] = (
    (("regularization.sigma", "regularization.n_copies", "regularization.copies_batch"),
     lambda v: v["regularization.sampled_weight"] > 0,
     "it shapes the perturbed copies of sampled Jacobian propagation, which is off "
     "(regularization.sampled_weight is 0): remove it, or turn that on"),
    (("regularization.ltv_lambda", "ltv_prior"),
     lambda v: v["regularization.sampled_weight"] > 0 or v["regularization.exact_weight"] > 0,
     "the agent fits LTV models only for the sampled and exact regularizers, whose weights are "
     "0 here: remove it"),
    (("planner.cem.",), lambda v: v["planner.kind"] == "cem",
     "it is a setting of planner.kind='cem', which is not the planner: remove it, or set "
     "planner.kind='cem'"),
    (("planner.proposal.",), lambda v: v["planner.kind"] == "cem-ilqr",
     "it is a setting of the CEM proposal of planner.kind='cem-ilqr', which is not the "
     "planner: remove it, or set planner.kind='cem-ilqr'"),
    (("planner.replan_feedback",),
     lambda v: v["planner.replan_every"] > 1 and v["planner.kind"] != "cem",
     "it follows iLQR's gains between re-plans, so it needs planner.replan_every > 1 and a "
     "planner with iLQR (planner.kind 'ilqr' or 'cem-ilqr'): remove it, or set those"),
    (("planner.ilqr_iterations",), lambda v: v["planner.kind"] != "cem",
     "CEM runs planner.cem.iterations per step: remove it, or plan with iLQR"),
    (("collection.excitation_window",), lambda v: v["collection.excitation"] == "filtered_gaussian",
     "it is the window of collection.excitation='filtered_gaussian' and the excitation is "
     "'multisine': remove it"),
    (("collection.explore_on",), lambda v: v["collection.explore_weight"] > 0,
     "it chooses what directed exploration measures, which is off (collection.explore_weight "
     "is 0): remove it, or turn that on"),
    (("collection.explore_weight",),
     lambda v: v["planner.kind"] != "ilqr" and v["model.ensemble_size"] > 1,
     "it ranks CEM's samples by the members' disagreement, so it needs a planner with CEM "
     "(planner.kind 'cem' or 'cem-ilqr') and model.ensemble_size > 1: remove it, or set those"),
    (("collection.exploration_window",), lambda v: v["collection.exploration_std"] > 0,
     "it shapes the exploration noise, which is off (collection.exploration_std is 0): remove "
     "it, or turn that on"),
    (("training.epochs",), lambda v: v["training.steps"] is None,
     "training.steps sets a budget of gradient steps per update, so the epochs are not used: "
     "remove it, or set training.steps=None for the epoch schedule"),
    (("training.early_stopping",), lambda v: v["training.patience"] is not None,
     "it chooses how early stopping keeps the best weights, and training.patience is None (no "
     "early stopping): remove it, or set a patience"),
    (("video_every",), lambda v: bool(v["video"]),
     "video is off: remove it, or set video=true"),
    (("evaluation.solved_ratio", "evaluation.early_exit"),
     lambda v: v["evaluation.solved_return"] is None,
     "evaluation.solved_return is set, so the solved test is on the return and the oracle "
     "this relates to is not run: remove it, or evaluation.solved_return"),
)


def _inactive(values: Mapping[str, Any]) -> dict[str, str]:
    """``{dotted field: reason}`` of the fields of ``values`` (every dotted leaf) that hold a
    chosen value (neither the agent's default nor its section's) without effect under the
    others."""
    defaults, class_defaults = _default_leaves(), _class_default_leaves()
    out = {}
    for fields, needed, reason in _DEPENDENT:
        if needed(values):
            continue
        for name, value in values.items():
            chosen = value != defaults[name] and value != class_defaults.get(name, defaults[name])
            if chosen and any(name == f or (f.endswith(".") and name.startswith(f))
                              for f in fields):
                out[name] = reason
    return out


def _closest(key: str) -> str:
    """The valid dotted field nearest to ``key`` (difflib; whole path or last part)."""
    tail = key.rpartition(".")[2]

    def score(path: str) -> tuple[float, float]:
        whole = difflib.SequenceMatcher(None, key, path).ratio()
        last = difflib.SequenceMatcher(None, tail, path.rpartition(".")[2]).ratio()
        return max(whole, last), whole

    return max(_all_paths(), key=score)


def _unknown(key: str) -> ValueError:
    return ValueError(f"unknown AgentConfig field {key!r}; the closest valid field is "
                      f"{_closest(key)!r}")


def _prefixed(section: str, make: Any, *args: Any, **kwargs: Any) -> Any:
    """``make(*args, **kwargs)`` with a ``ValueError`` re-raised as ``"<section>.<message>"`` (the
    library's configs name their own fields, the tree names the path; ``CEMOptions`` names them
    ``options.<field>``)."""
    try:
        return make(*args, **kwargs)
    except (ValueError, TypeError) as err:
        msg = str(err)
        if not section or msg.startswith(f"{section}.") or msg.startswith(f"{section} "):
            raise
        if msg.startswith("options."):
            raise type(err)(msg.replace("options.", f"{section}.")) from None
        raise type(err)(f"{section}.{msg}") from None


def _replaced(obj: Any, changes: Mapping[str, Any], prefix: str) -> Any:
    """``dataclasses.replace`` with dotted keys (``"planner.cem.samples"``) and section dicts
    (``{"planner": {"cem": {"samples": 50}}}``) at any depth, every leaf coerced to its type;
    every level is validated again and its errors name the dotted path."""
    hints = _hints(type(obj))
    direct: dict[str, Any] = {}
    nested: dict[str, dict[str, Any]] = {}
    for key, value in changes.items():
        if not isinstance(key, str):
            where = f" in {prefix[:-1]!r}" if prefix else ""
            raise ValueError(f"AgentConfig field names are strings, got {key!r}{where}")
        head, _, rest = key.partition(".")
        if head not in hints:
            while isinstance(value, Mapping) and value and isinstance(next(iter(value)), str):
                key, value = f"{key}.{next(iter(value))}", next(iter(value.values()))
            raise _unknown(prefix + key)  # named down to its first leaf
        section = _is_section(hints[head])
        if rest or (section and isinstance(value, Mapping)):
            for sub, v in ({rest: value} if rest else value).items():
                if sub in nested.setdefault(head, {}):
                    raise ValueError(f"{prefix}{head}.{sub} is given twice")
                nested[head][sub] = v
        elif section:
            direct[head] = value  # an instance, or a name (checked by the constructor)
        else:
            direct[head] = _coerce(value, hints[head], prefix + head)
    for head, values in nested.items():
        if not _is_section(hints[head]):
            bad = f"{prefix}{head}.{next(iter(values))}"
            raise ValueError(f"unknown AgentConfig field {bad!r} ({prefix}{head} is a field, not "
                             "a section)")
        base = direct.get(head, getattr(obj, head))
        if isinstance(base, str) and not prefix and head in _NAMED:  # a name, then its fields
            base = _prefixed(head, _NAMED[head], base)
        if not isinstance(base, hints[head]):
            raise ValueError(f"{prefix}{head} must be a {hints[head].__name__} or a name, got "
                             f"{base!r}")
        direct[head] = _replaced(base, values, f"{prefix}{head}.")
    return _prefixed(prefix[:-1], dataclasses.replace, obj, **direct)


# ---- files: JSON and YAML, a run's config.json --------------------------------------------------
#: the sections of a run's ``config.json`` beside ``agent`` (written by scripts/train_agent.py)
RUN_SECTIONS = ("script", "command", "ensemble", "env_spec")


def _unique_keys(pairs: list[tuple[Any, Any]]) -> dict[Any, Any]:
    """A JSON object's dict; a key given twice is an error (JSON keeps the last, silently)."""
    out: dict[Any, Any] = {}
    for key, value in pairs:
        if key in out:
            raise ValueError(f"the key {key!r} is given twice")
        out[key] = value
    return out


def _yaml_load(text: str) -> Any:
    import yaml

    class UniqueKeyLoader(yaml.SafeLoader):
        def construct_mapping(self, node, deep=False):  # noqa: ANN001, ANN202
            keys = [self.construct_object(k, deep=deep) for k, _ in node.value]
            for i, key in enumerate(keys):
                if key in keys[:i]:
                    mark = node.value[i][0].start_mark
                    raise ValueError(f"the key {key!r} is given twice (line {mark.line + 1})")
            return super().construct_mapping(node, deep=deep)

    try:
        return yaml.load(text, Loader=UniqueKeyLoader)  # noqa: S506 - a SafeLoader
    except yaml.YAMLError as err:
        mark = getattr(err, "problem_mark", None)
        where = f" (line {mark.line + 1}, column {mark.column + 1})" if mark else ""
        problem = getattr(err, "problem", None) or str(err).splitlines()[0]
        raise ValueError(f"is not valid YAML: {problem}{where}") from None


def read_config_file(path: str | os.PathLike) -> dict[str, Any]:
    """The dict in a JSON (``.json``) or YAML (``.yaml``/``.yml``; other names: JSON, else YAML)
    file. Nothing but plain data is read (YAML's safe loader, no Python objects).

    :raises ValueError: naming the file: missing or unreadable, not valid JSON/YAML (with the
        line), a key given twice, empty, or not a dict.
    """
    p = Path(path)
    try:
        text = p.read_text(encoding="utf-8")
    except FileNotFoundError:
        raise ValueError(f"{p}: no such file") from None
    except IsADirectoryError:
        raise ValueError(f"{p} is a folder, not a config file") from None
    except UnicodeDecodeError:
        raise ValueError(f"{p} is not a text file (a JSON or YAML config expected)") from None
    except OSError as err:
        raise ValueError(f"{p}: cannot read it ({err.strerror})") from None
    suffix = p.suffix.lower()
    try:
        if suffix in (".yaml", ".yml"):
            data = _yaml_load(text)
        else:
            try:
                data = json.loads(text, object_pairs_hook=_unique_keys)
            except json.JSONDecodeError as err:
                if suffix == ".json":
                    raise ValueError(f"is not valid JSON: {err.msg} (line {err.lineno}, column "
                                     f"{err.colno})") from None
                data = _yaml_load(text)
    except ValueError as err:
        raise ValueError(f"{p} {err}" if str(err).startswith("is ") else f"{p}: {err}") from None
    if data is None:
        raise ValueError(f"{p} is empty (a dict of AgentConfig fields expected)")
    if not isinstance(data, Mapping):
        raise ValueError(f"{p} holds a {type(data).__name__}, not a dict of AgentConfig fields")
    return dict(data)


def in_file(path: str | os.PathLike, err: ValueError) -> ValueError:
    """``err`` with its message prefixed by ``"<path>: "`` (unless it names the file already)."""
    return err if str(err).startswith(str(path)) else ValueError(f"{path}: {err}")


def split_run_config(d: Mapping[str, Any]) -> tuple[Mapping[str, Any], dict[str, Any]]:
    """``(agent fields, the other sections)`` of a run's ``config.json`` (``{"agent": {...},
    "script": {...}, "command", "ensemble", "env_spec"}``); any other dict is all agent fields.

    :raises ValueError: for a key beside ``agent`` that a run's config.json does not hold.
    """
    if not isinstance(d.get("agent"), Mapping):
        return d, {}
    unknown = sorted(set(d) - {"agent", *RUN_SECTIONS})
    if unknown:
        raise ValueError(f"unknown key(s) {unknown} beside 'agent' (a run's config.json holds "
                         f"'agent' and {list(RUN_SECTIONS)})")
    return d["agent"], {k: v for k, v in d.items() if k != "agent"}
