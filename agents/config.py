"""Configuration of the Algorithm-1 agent: one tree of frozen dataclasses, validated when built
(docs/agent.md, "Public API" and "Config files"). A generic layer checks every leaf against its
type hint, ``_BOUNDS``, ``AgentConfig.FIXED`` and ``_DEPENDENT``; errors name the dotted field."""

from __future__ import annotations

import contextlib
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
import yaml

from agents.cli import built
from mbtsr.cem import CEMOptions
from mbtsr.ensemble import ModelConfig
from mbtsr.reward import RewardConfig
from mbtsr.training import RegularizationConfig, TrainConfig

__all__ = ["AgentConfig", "CollectionConfig", "PlannerConfig", "EvaluationConfig",
           "read_config_file", "split_run_config", "in_file", "PLANNERS"]

PLANNERS = ("ilqr", "cem", "cem-ilqr")


class _Section:
    """Checks every field against its type hint and ``_BOUNDS`` (``{dotted field: low or (low,
    high, low_open)}``), then :meth:`_check`; errors name the dotted field."""

    _BOUNDS: ClassVar[dict[str, Any]] = {}

    def __post_init__(self) -> None:
        at = next((f"{k}." for k, c in SECTIONS.items() if c is type(self)), "")
        for name, hint in _hints(type(self)).items():
            value = getattr(self, name)
            if isinstance(value, str) and name in _NAMED:  # a name for a section: it, fresh
                value = built(name, _NAMED[name], value)
                object.__setattr__(self, name, value)
            if not _is_section(hint):
                object.__setattr__(self, name, _coerce(value, hint, at + name, True))
            elif not isinstance(value, hint):
                raise ValueError(f"{at}{name} must be a {hint.__module__}.{hint.__name__} (or a "
                                 f"dict of its fields), got {type(value).__name__}")
            elif not isinstance(value, _Section):  # a library config: the tree checks its leaves
                for dotted, v, h in _leaves(value, f"{at}{name}."):
                    _coerce(v, h, dotted, True)
        for dotted, bound in self._BOUNDS.items():
            low, high, low_open = bound if isinstance(bound, tuple) else (bound, math.inf, False)
            v = functools.reduce(getattr, dotted.split("."), self)
            if v is not None and not (math.isfinite(v) and v <= high
                                      and (v > low if low_open else v >= low)):
                kind = "an integer" if isinstance(low, int) else "a finite number"
                top = f" and <= {high}" if high < math.inf else ""
                raise ValueError(f"{at}{dotted} must be {kind} {'>' if low_open else '>='} {low}"
                                 f"{top}, got {v!r}")
        self._check()

    def _check(self) -> None:
        """Rules between fields."""


@dataclass(frozen=True)
class CollectionConfig(_Section):
    """Data collection (Algorithm 1, "sample rollout trajectory").

    :param n_excitation_episodes: first episodes driven by an excitation signal, not the planner.
    :param excitation: the excitation signal (filtered Gaussian noise: the paper's robot input).
    :param excitation_scale: excitation amplitude, a fraction of the action half-range.
    :param excitation_window: moving-average window (steps) of the filtered Gaussian input.
    :param exploration_std: std of the training rollouts' action noise (of the half-range).
    :param episode_steps: steps per episode (``None``: the env's ``TimeLimit``).
    :param rollout_steps: steps per TRAINING rollout, shorter than the episode (``None``: all).
    :param continue_rollouts: the next rollout continues the env's episode (no reset).
    :param exploration_window: moving-average window (steps) of the exploration noise (1: white).
    :param explore_weight: directed exploration: CEM's cost minus this x disagreement (0: off).
    :param explore_on: what the disagreement is measured on: the next ``state`` or its ``cost``.
    """

    _BOUNDS: ClassVar[dict[str, Any]] = dict(
        n_excitation_episodes=1, excitation_scale=(0.0, 1.0, True), excitation_window=1,
        exploration_std=0.0, exploration_window=1, explore_weight=0.0, episode_steps=2,
        rollout_steps=2)
    n_excitation_episodes: int = 2
    excitation: Literal["filtered_gaussian", "multisine"] = "filtered_gaussian"
    excitation_scale: float = 0.3
    excitation_window: int = 8
    exploration_std: float = 0.1
    episode_steps: int | None = None
    rollout_steps: int | None = None
    continue_rollouts: bool = False
    exploration_window: int = 8
    explore_weight: float = 0.0
    explore_on: Literal["state", "cost"] = "state"

    def _check(self) -> None:
        if None not in (self.rollout_steps, self.episode_steps) and \
                self.rollout_steps >= self.episode_steps:
            raise ValueError(f"collection.rollout_steps={self.rollout_steps} has no effect: it "
                             f"must be shorter than collection.episode_steps={self.episode_steps}")
        if self.continue_rollouts and self.rollout_steps is None:
            raise ValueError("collection.continue_rollouts=True needs collection.rollout_steps "
                             "(rollouts shorter than the episode to continue)")


@dataclass(frozen=True)
class PlannerConfig(_Section):
    """Planning (Algorithm 1, "optimize controller"): MPC on the learned model, warm-started.

    :param horizon: MPC horizon in steps (``None``: by the rule of :meth:`for_task`, 15 for a
        written cost with a termination function, else 30).
    :param replan_every: execute every plan for this many steps before re-solving.
    :param replan_feedback: between re-plans, follow iLQR's local policy ``U_t + K_t (x_t -
        X_t)`` instead of the open-loop controls.
    :param kind: ``ilqr`` (the paper's), ``cem`` (PETS' cross-entropy method) or ``cem-ilqr``
        (CEM proposes, iLQR refines; docs/ilqr.md).
    :param terminal_weight: weight of the task's terminal cost, which is the stage cost at zero
        action if the task has none (``None``: by the rule, 100 or 1).
    :param ilqr_iterations: iLQR iterations per MPC step.
    :param first_plan_iterations: iLQR (or CEM) iterations for the plan at an episode's start.
    :param cem: the CEM settings of ``kind=cem`` (:class:`mbtsr.cem.CEMOptions`).
    :param proposal: the CEM settings of ``kind=cem-ilqr``'s proposal.
    :param warm_samples: the proposal's samples once warm-started (``None``: ``proposal.samples``).
    :param propagation: CEM's rollouts on the ensemble: ``mean`` (the mean model) or ``ts`` (PETS'
        trajectory sampling: one member per particle).
    """

    _BOUNDS: ClassVar[dict[str, Any]] = dict(
        horizon=2, replan_every=1, ilqr_iterations=1, first_plan_iterations=1,
        terminal_weight=0.0, warm_samples=2)
    horizon: int | None = None
    replan_every: int = 1
    replan_feedback: bool = False
    kind: Literal["ilqr", "cem", "cem-ilqr"] = "cem-ilqr"
    terminal_weight: float | None = None
    ilqr_iterations: int = 2
    first_plan_iterations: int = 20
    cem: CEMOptions = field(default_factory=lambda: CEMOptions(iterations=3))
    proposal: CEMOptions = field(
        default_factory=lambda: CEMOptions(samples=64, elites=8, iterations=2))
    warm_samples: int | None = 32
    propagation: Literal["mean", "ts"] = "mean"

    def _check(self) -> None:
        if self.propagation == "ts" and self.kind != "cem":
            raise ValueError("planner.propagation='ts' (trajectory sampling) needs "
                             f"planner.kind='cem', got {self.kind!r}")
        if self.replan_every > (self.horizon or 30):  # None: the rule's 15 or 30 (for_task)
            raise ValueError(f"planner.replan_every must be <= planner.horizon="
                             f"{self.horizon or '30 (the horizon rule)'}, got {self.replan_every}")

    def for_task(self, cost_fn: Any, termination_fn: Any) -> PlannerConfig:
        """These settings with ``horizon`` and ``terminal_weight`` that are ``None`` set by the
        rule: 15 and 100 for a written ``cost_fn`` with a ``termination_fn`` (neither ``None``),
        else 30 and 1 (docs/agent.md, "The planner's horizon")."""
        h, w = (30, 1.0) if None in (cost_fn, termination_fn) else (15, 100.0)
        if self.horizon is None and self.replan_every > h:
            raise ValueError(f"planner.replan_every={self.replan_every} exceeds the horizon "
                             f"rule's {h} steps for this task: set planner.horizon")
        return dataclasses.replace(self, horizon=self.horizon or h, terminal_weight=(  # >= 2
            w if self.terminal_weight is None else self.terminal_weight))


@dataclass(frozen=True)
class EvaluationConfig(_Section):
    """Evaluation of the MPC policy on fixed episodes and the "solved" criterion (docs/agent.md,
    "Evaluation, the oracle, solved").

    :param every: evaluate every this many episodes and at the end of ``learn`` (0: never).
    :param every_steps: also evaluate after every episode that crosses a multiple of this many
        env steps (0: off; SB3's ``eval_freq``).
    :param episodes: evaluation episodes.
    :param seed: seed of the evaluation episodes' targets and resets.
    :param early_exit: stop an evaluation during learning once its cost exceeds ``solved_ratio``
        x the oracle's (the final evaluation of a ``learn`` call runs every episode).
    :param solved_ratio: the solved threshold relative to the oracle.
    :param solved_return: the solved threshold on the mean return (``None``: the oracle's ratio).
    :param stop_when_solved: stop ``learn`` at the first solved evaluation.
    :param oracle_cache_dir: folder of the oracle's memoised costs (``None``: no cache).
    """

    _BOUNDS: ClassVar[dict[str, Any]] = dict(
        every=0, every_steps=0, episodes=1, seed=0, solved_ratio=1.0, solved_return=-math.inf)
    every: int = 4
    every_steps: int = 0
    episodes: int = 3
    seed: int = 1000
    early_exit: bool = True
    solved_ratio: float = 1.2
    solved_return: float | None = None
    stop_when_solved: bool = False
    oracle_cache_dir: str | None = None


#: the sections of the tree: field name -> its dataclass
SECTIONS: dict[str, type] = {
    "collection": CollectionConfig, "model": ModelConfig, "training": TrainConfig,
    "regularization": RegularizationConfig, "planner": PlannerConfig,
    "evaluation": EvaluationConfig, "reward": RewardConfig}
_NAMED: dict[str, Callable[[str], Any]] = {  # the sections a name can stand for
    "regularization": lambda name: RegularizationConfig.named(name, ltv_lambda=None),
    "planner": lambda name: PlannerConfig(kind=name)}


@dataclass(frozen=True)
class AgentConfig(_Section):
    """Everything that decides what :class:`agents.jacprop_agent.JacPropAgent` does.

    :param collection: data collection: excitation, exploration noise, episode length.
    :param model: the ensemble (``hidden_width``/``hidden_layers`` ``None``: sized by the task).
    :param training: one model update, warm-started on ALL data so far.
    :param regularization: the tangent-space regularizer, on by its weight (a name: ``sampled``,
        ``exact``, ``smooth``, ``none``: the plain baseline; docs/benchmark.md compares them).
    :param planner: the MPC planner on the learned model.
    :param evaluation: evaluation episodes and the "solved" criterion.
    :param reward: the reward model learned when the task has no written cost.
    :param seed: master seed; every random draw of a run derives from it.
    :param renormalize: recompute the model's normalization from ALL data before every update.
    :param ltv_prior: fuse each LTV fit with the ensemble's Jacobians, variance floor (0: off).
    :param run_dir: folder of the CSV log, TensorBoard, checkpoint and exports (``None``: none).
    :param checkpoint: write a checkpoint after every episode (needs ``run_dir``).
    :param tensorboard: write TensorBoard scalars (needs ``run_dir``).
    :param video: save a video of every ``video_every``-th episode (needs rgb_array rendering).
    :param video_every: see ``video``.
    :param jacobian_error: log the Jacobian error when the env can linearize itself.
    :param progress: show a progress bar in ``learn``.
    :param torch_threads: threads of torch and numpy's BLAS in ``learn`` (0: leave as is).
    """

    #: fields the agent sets itself, ``{dotted field: why}``: another value is refused, and the
    #: command line does not offer them (:mod:`agents.cli`)
    FIXED: ClassVar[dict[str, str]] = {
        "training.seed": "the agent seeds every update from seed",
        "reward.seed": "the agent seeds the reward model from seed",
        "regularization.ltv_affine": "the agent's LTV fits have no affine term",
        **{f"planner.{s}.{f}": why for s in ("cem", "proposal") for f, why in (
            ("seed", "the agent seeds every solve from seed"),
            ("explore_weight", "set collection.explore_weight (training rollouts only)"),
            ("explore_on", "set collection.explore_on (training rollouts only)"))}}
    _BOUNDS: ClassVar[dict[str, Any]] = dict(
        seed=0, ltv_prior=0.0, video_every=1, torch_threads=0,
        **{"training.epochs": 1, "regularization.ltv_lambda": (0.0, math.inf, True)})
    collection: CollectionConfig = field(default_factory=CollectionConfig)
    model: ModelConfig = field(default_factory=ModelConfig)
    training: TrainConfig = field(default_factory=lambda: TrainConfig(
        steps=4000, lr=1e-3, batch=256, holdout=0.1, eval_every=50, patience=10,
        early_stopping="member", member_data="order", progress=False))
    regularization: RegularizationConfig = field(default_factory=lambda: _NAMED[
        "regularization"]("none"))
    planner: PlannerConfig = field(default_factory=PlannerConfig)
    evaluation: EvaluationConfig = field(default_factory=EvaluationConfig)
    reward: RewardConfig = field(default_factory=RewardConfig)
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

    def _check(self) -> None:
        values = self.dotted()
        if self.training.patience is not None and self.training.holdout == 0:
            raise ValueError(
                f"training.patience={self.training.patience!r} has no effect: early stopping "
                "needs held-out data (training.holdout > 0): set training.patience=None to "
                "train the whole budget, or a hold-out")
        agent, own, _ = _defaults()
        for dotted, why in self.FIXED.items():
            if values[dotted] != own[dotted]:
                raise ValueError(f"{dotted} must be {own[dotted]!r}: {why}, got "
                                 f"{values[dotted]!r}")
        for fields, when in _DEPENDENT.items():
            chosen = [n for n, v in values.items() if v not in (agent[n], own.get(n, agent[n]))
                      and any(n == f or f[-1] == "." and n.startswith(f) for f in fields.split())]
            if chosen and not eval(when, {}, dict(self.__dict__)):  # noqa: S307 - our strings
                raise ValueError(f"{chosen[0]}={values[chosen[0]]!r} has no effect: it acts only "
                                 f"when {when}: remove it, or set that")

    def replace(self, changes: Mapping[str, Any] | None = None, /, **top: Any) -> AgentConfig:
        """A copy with changes, validated again: ``changes`` maps dotted fields or sections
        (``{"model": {"hidden_width": 32}, "planner": "cem"}``) to values, coerced as in
        :meth:`from_dict`; keywords set top-level fields. Errors name the dotted field."""
        return _replaced(self, {**(changes or {}), **top}, "")

    @classmethod
    def default(cls, changes: Mapping[str, Any] | None = None, /, **top: Any) -> AgentConfig:
        """``AgentConfig().replace(changes, **top)``."""
        return cls().replace(changes, **top)

    def dotted(self) -> dict[str, Any]:
        """``{dotted field: value}`` of every leaf of the tree (``"planner.cem.samples": 200``)."""
        return {name: value for name, value, _ in _leaves(self)}

    def changes(self) -> dict[str, Any]:
        """The leaves that differ from ``AgentConfig()``'s (``default(cfg.changes()) == cfg``)."""
        return {k: v for k, v in self.dotted().items() if v != _defaults()[0][k]}

    def to_dict(self) -> dict[str, Any]:
        """A JSON-friendly nested dict of all fields (tuples as lists)."""
        return json.loads(json.dumps(dataclasses.asdict(self)))

    def to_json(self) -> str:
        return json.dumps(self.to_dict(), indent=2, sort_keys=True)

    @classmethod
    def from_dict(cls, d: Mapping[str, Any], /, base: AgentConfig | None = None) -> AgentConfig:
        """The CHANGES a partial (nested or dotted) dict gives to ``base`` (default: the
        defaults), as :meth:`replace`, values coerced where unambiguous (:func:`_coerce`)."""
        if not isinstance(d, Mapping):
            raise ValueError(f"AgentConfig.from_dict needs a dict of AgentConfig fields, got "
                             f"{type(d).__name__} {d!r}")
        base, training = base or cls(), d.get("training")
        if (base.training.steps is not None and isinstance(training, Mapping)
                and "epochs" in training and "steps" not in training
                and {"collection", "model", "planner", "evaluation"} <= d.keys()):
            raise ValueError("training.epochs without training.steps: set training.steps: null "
                             "for the epoch schedule (a whole config saved before "
                             "training.steps existed is not read: it meant other defaults)")
        return base.replace(d)

    @classmethod
    def load(cls, path: str | os.PathLike, base: AgentConfig | None = None) -> AgentConfig:
        """The config in a JSON or YAML file (a run's ``config.json``: its ``agent`` section),
        as changes to ``base``; an error names the file."""
        try:
            return cls.from_dict(split_run_config(read_config_file(path))[0], base=base)
        except ValueError as err:
            raise in_file(path, err) from None


@functools.cache
def _hints(cls: type) -> dict[str, Any]:
    """The resolved type of every field of dataclass ``cls``."""
    hints = typing.get_type_hints(cls)
    return {f.name: hints[f.name] for f in dataclasses.fields(cls)}


@functools.cache
def _is_section(hint: Any) -> bool:
    return isinstance(hint, type) and dataclasses.is_dataclass(hint)


def _leaves(obj: Any, prefix: str = "") -> Iterator[tuple[str, Any, Any]]:
    """``(dotted name, value, declared type)`` of every non-section field of ``obj``'s tree."""
    for name, hint in _hints(type(obj)).items():
        if _is_section(hint):
            yield from _leaves(getattr(obj, name), f"{prefix}{name}.")
        else:
            yield prefix + name, getattr(obj, name), hint


@functools.cache
def _defaults() -> tuple[dict[str, Any], dict[str, Any], tuple[str, ...]]:
    """``AgentConfig()``'s dotted leaves (from the field defaults), every section's leaves at its
    class's defaults and every dotted path, sections included."""
    agent: dict[str, Any] = {}
    for f in dataclasses.fields(AgentConfig):
        value = f.default if f.default_factory is dataclasses.MISSING else f.default_factory()
        agent.update({k: v for k, v, _ in _leaves(value, f"{f.name}.")}
                     if _is_section(type(value)) else {f.name: value})
    own = {k: v for name, cls in SECTIONS.items() for k, v, _ in _leaves(cls(), f"{name}.")}
    paths = dict.fromkeys(".".join(p.split(".")[:i]) for p in agent
                          for i in range(1, p.count(".") + 2))
    return agent, own, tuple(paths)


def _describe(hint: Any) -> str:
    """``float | None`` -> ``"a number or null"`` (the words of the type errors)."""
    origin, args = typing.get_origin(hint), typing.get_args(hint)
    if origin in (typing.Union, types.UnionType):
        return " or ".join(_describe(a) for a in args)
    if origin is Literal:
        return repr(args[0]) if len(args) == 1 else f"one of {args}"
    if origin is tuple:
        count = "" if args[-1] is Ellipsis else f"{len(args)} "
        return f"a list of {count}{_describe(args[0]).split(' ', 1)[-1]}s"
    return {bool: "true or false", int: "an integer", float: "a number", str: "a string",
            type(None): "null"}.get(hint, getattr(hint, "__name__", str(hint)))


def _coerce(value: Any, hint: Any, name: str, strict: bool = False) -> Any:
    """``value`` as the type ``hint`` of field ``name``, unless ``strict`` coerced where
    unambiguous (docs/agent.md, "Config files": Types).
    :raises ValueError: ``"<name> must be <type>, got <value>"``."""
    union = typing.get_origin(hint) in (typing.Union, types.UnionType)
    given, options = value, typing.get_args(hint) if union else (hint,)
    if not strict and isinstance(value, str) and not any(
            o is str or str in typing.get_args(o) or value in typing.get_args(o) for o in options):
        w, words = value.strip().lower(), {"true": True, "false": False, "none": None, "null": None}
        with contextlib.suppress(ValueError):
            value = words[w] if w in words else int(w) if w.lstrip("+-").isdigit() else float(w)
    for option in options:
        origin, args = typing.get_origin(option), typing.get_args(option)
        number = isinstance(value, numbers.Real) and not isinstance(value, (bool, np.bool_))
        if origin is tuple and isinstance(value, tuple if strict else (tuple, list, str)):
            value = (value,) if isinstance(value, str) else value
            items = (args[0],) * len(value) if args[-1] is Ellipsis else args
            with contextlib.suppress(ValueError):
                if len(items) == len(value):
                    return tuple(_coerce(v, h, name, strict) for v, h in zip(value, items))
        elif value is None and option is type(None) or origin is Literal and value in args \
                and isinstance(value, str):
            return value
        elif option is bool and isinstance(value, (bool, np.bool_)):
            return bool(value)
        elif option is float and number:
            return float(value)
        elif option is int and number and (isinstance(value, numbers.Integral) or not strict
                                           and float(value).is_integer()):
            return int(value)
        elif option is str and isinstance(value, (str, os.PathLike)):
            return os.fspath(value)
    raise ValueError(f"{name} must be {_describe(hint)}, got {given!r}")


#: settings that act only under others: ``{fields: when}`` (a field ending in "." stands for its
#: section's fields); a chosen value there (neither the agent's default nor its section's) while
#: the condition ``when`` (a Python expression on the config's fields) is false is refused
_DEPENDENT = {
    "regularization.sigma regularization.n_copies regularization.copies_batch":
        "regularization.sampled_weight > 0",
    "regularization.ltv_lambda ltv_prior":
        "regularization.sampled_weight > 0 or regularization.exact_weight > 0",
    "planner.cem.": "planner.kind == 'cem'",
    "planner.proposal. planner.warm_samples": "planner.kind == 'cem-ilqr'",
    "planner.replan_feedback": "planner.replan_every > 1 and planner.kind != 'cem'",
    "planner.ilqr_iterations": "planner.kind != 'cem'",
    "collection.excitation_window": "collection.excitation == 'filtered_gaussian'",
    "collection.explore_on": "collection.explore_weight > 0",
    "collection.explore_weight": "planner.kind != 'ilqr' and model.ensemble_size > 1",
    "collection.exploration_window": "collection.exploration_std > 0",
    "training.epochs": "training.steps is None",
    "training.early_stopping": "training.patience is not None",
    "video_every": "video == True",
    "evaluation.solved_ratio evaluation.early_exit": "evaluation.solved_return is None",
}


def _unknown(key: str) -> ValueError:
    """The error of an unknown field, naming the closest valid one (whole path or last part)."""
    def score(path: str) -> tuple[float, float]:  # the closer of the whole and the last part
        whole, last = (difflib.SequenceMatcher(None, a, b).ratio() for a, b in (
            (key, path), (key.rpartition(".")[2], path.rpartition(".")[2])))
        return max(whole, last), whole

    return ValueError(f"unknown AgentConfig field {key!r}; the closest valid field is "
                      f"{max(_defaults()[2], key=score)!r}")


def _replaced(obj: Any, changes: Mapping[str, Any], prefix: str) -> Any:
    """``dataclasses.replace`` with dotted keys and section dicts at any depth, every leaf
    coerced to its type, every level validated again."""
    hints, direct, nested = _hints(type(obj)), {}, {}
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
        else:  # a section's instance or name is checked by the constructor
            direct[head] = value if section else _coerce(value, hints[head], prefix + head)
    for head, values in nested.items():
        if not _is_section(hints[head]):
            raise ValueError(f"unknown AgentConfig field '{prefix}{head}.{next(iter(values))}' "
                             f"({prefix}{head} is a field, not a section)")
        base = direct.get(head, getattr(obj, head))
        if isinstance(base, str) and head in _NAMED:  # a name, then its fields
            base = built(head, _NAMED[head], base)
        if not isinstance(base, hints[head]):
            raise ValueError(f"{prefix}{head} must be a {hints[head].__name__} or a name, got "
                             f"{base!r}")
        direct[head] = _replaced(base, values, f"{prefix}{head}.")
    return built(prefix[:-1], dataclasses.replace, obj, **direct)


#: the sections of a run's ``config.json`` beside ``agent`` (written by train_agent)
RUN_SECTIONS = ("script", "command", "ensemble", "env_spec")


def _unique(pairs: list[tuple[Any, Any]]) -> dict[Any, Any]:
    """A JSON object's dict; a key given twice is an error (JSON keeps the last, silently)."""
    if len(keys := [k for k, _ in pairs]) != len(set(keys)):
        raise ValueError(f"the key {next(k for k in keys if keys.count(k) > 1)!r} is given twice")
    return dict(pairs)


class _UniqueKeyLoader(yaml.SafeLoader):
    """YAML's safe loader (plain data only) that refuses a key given twice."""

    def construct_mapping(self, node: yaml.MappingNode, deep: bool = False) -> dict:
        keys = [self.construct_object(k, deep=deep) for k, _ in node.value]
        for i, key in enumerate(keys):
            if key in keys[:i]:
                raise ValueError(f"the key {key!r} is given twice "
                                 f"(line {node.value[i][0].start_mark.line + 1})")
        return super().construct_mapping(node, deep=deep)


def read_config_file(path: str | os.PathLike) -> dict[str, Any]:
    """The dict in a JSON (``.json``) or YAML (any other name) file, plain data only; an error
    names the file (unreadable, not valid JSON/YAML, a key given twice, empty, not a dict)."""
    p = Path(path)
    try:
        text = p.read_text(encoding="utf-8")
        data = json.loads(text, object_pairs_hook=_unique) if p.suffix.lower() == ".json" \
            else yaml.load(text, Loader=_UniqueKeyLoader)  # noqa: S506 - a SafeLoader
    except json.JSONDecodeError as err:
        raise ValueError(f"{p} is not valid JSON: {err.msg} (line {err.lineno}, column "
                         f"{err.colno})") from None
    except yaml.YAMLError as err:
        mark = getattr(err, "problem_mark", None)
        where = f" (line {mark.line + 1}, column {mark.column + 1})" if mark else ""
        problem = getattr(err, "problem", None) or str(err).splitlines()[0]
        raise ValueError(f"{p} is not valid YAML: {problem}{where}") from None
    except UnicodeDecodeError:
        raise ValueError(f"{p} is not a text file (a JSON or YAML config expected)") from None
    except OSError as err:
        raise ValueError(f"{p}: {(err.strerror or str(err)).lower()}") from None
    except ValueError as err:  # a key given twice
        raise ValueError(f"{p}: {err}") from None
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
    "script": {...}, ...}``; an unknown section is an error); any other dict is all agent."""
    if not isinstance(d.get("agent"), Mapping):
        return d, {}
    if unknown := sorted(set(d) - {"agent", *RUN_SECTIONS}):
        raise ValueError(f"unknown key(s) {unknown} beside 'agent' (a run's config.json holds "
                         f"'agent' and {list(RUN_SECTIONS)})")
    return d["agent"], {k: v for k, v in d.items() if k != "agent"}
