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
Configs saved in the old flat format (``{"epochs_per_episode": 150, "hidden_width": 20, ...}``)
load through :func:`from_flat` (``AgentConfig.from_dict`` detects them).

The defaults are the configuration measured in ``docs/ablation.md`` on ``mbtsr/TwoLinkArm-v0``;
where the paper fixes a value it is used (sampled Jacobian propagation with perturbations of 0.1 x
the per-dimension standard deviation, one perturbed copy resampled every epoch, the ``g``
formulation ``x+ = x + g(x, u)``, an ensemble of small tanh networks).
"""

from __future__ import annotations

import dataclasses
import json
import math
from collections.abc import Callable, Mapping
from dataclasses import dataclass, field
from typing import Any, ClassVar, Literal

from mbtsr.cem import CEMOptions, cem
from mbtsr.cem_ilqr import CEMILQROptions, cem_ilqr
from mbtsr.ensemble import ModelConfig
from mbtsr.ilqr import ilqr
from mbtsr.training import REGULARIZERS, RegularizationConfig, TrainConfig

__all__ = ["AgentConfig", "CollectionConfig", "PlannerConfig", "EvaluationConfig", "from_flat",
           "REGULARIZERS", "PLANNERS", "EXCITATIONS"]

PLANNERS = ("ilqr", "cem", "cem-ilqr")
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
    :param episode_steps: steps per rollout; ``None`` uses the env's ``TimeLimit``.
    """

    _path: ClassVar[str] = "collection"
    n_excitation_episodes: int = 2
    excitation: Literal["filtered_gaussian", "multisine"] = "filtered_gaussian"
    excitation_scale: float = 0.3
    excitation_window: int = 8
    exploration_std: float = 0.1
    episode_steps: int | None = None

    def __post_init__(self) -> None:
        self._int_at_least("n_excitation_episodes", 1)
        self._choice("excitation", EXCITATIONS)
        self._float_range("excitation_scale", 0.0, 1.0, low_open=True)
        self._int_at_least("excitation_window", 1)
        self._float_range("exploration_std", 0.0)
        if self.episode_steps is not None:
            self._int_at_least("episode_steps", 2)


@dataclass(frozen=True)
class PlannerConfig(_Checked):
    """Planning (Algorithm 1, "optimize controller"): MPC = the planner re-solved every step on
    the learned model, warm-started with the shifted previous plan.

    :param horizon: MPC horizon (steps).
    :param replan_every: execute every plan open loop for this many steps before re-solving
        (1: re-plan every step, the default; larger: the feedback-limited regime, where feedback
        hides less of the model's error). The oracle uses the same setting.
    :param kind: ``"ilqr"`` (iLQR on the model's Jacobians, the paper's controller), ``"cem"``
        (the cross-entropy method of PETS, :func:`mbtsr.cem.cem`: forward predictions only,
        never the model's Jacobians; the control for the paper's argument) or ``"cem-ilqr"``
        (CEM proposes, iLQR refines with ``ilqr_iterations``: :func:`mbtsr.cem_ilqr.cem_ilqr`;
        CEM finds contacts where gradients are zero, iLQR's feedback balances what open-loop
        samples cannot).
    :param terminal_weight: the planner's terminal cost is ``terminal_weight`` x the user's
        ``terminal_cost_fn(obs)`` (default: the stage cost at zero action).
    :param ilqr_iterations: iLQR iterations per MPC step (the first step of an episode gets
        ``first_plan_iterations``).
    :param first_plan_iterations: iLQR (or CEM) iterations for the full plan at the start of an
        episode.
    :param cem: the CEM settings (:class:`mbtsr.cem.CEMOptions`, the library's own): ``samples``
        (200) action sequences per iteration, ``elites`` (20) that refit the sampling
        distribution, ``iterations`` (3) per MPC step (the first step of an episode gets
        ``first_plan_iterations``); the agent seeds every solve from ``seed`` (``cem.seed`` stays
        0).
    :param proposal: the CEM settings of ``kind="cem-ilqr"``'s proposal (64 samples, 8 elites,
        2 iterations per MPC step; seeded like ``cem``).
    """

    _path: ClassVar[str] = "planner"
    horizon: int = 30
    replan_every: int = 1
    kind: Literal["ilqr", "cem", "cem-ilqr"] = "ilqr"
    terminal_weight: float = 1.0
    ilqr_iterations: int = 2
    first_plan_iterations: int = 20
    cem: CEMOptions = field(default_factory=lambda: CEMOptions(iterations=3))
    proposal: CEMOptions = field(
        default_factory=lambda: CEMOptions(samples=64, elites=8, iterations=2))

    def __post_init__(self) -> None:
        self._choice("kind", PLANNERS)
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

    def optimizer(self, seed: int = 0) -> tuple[Callable[..., Any], Any, int]:
        """``(optimizer, options, iterations per MPC step)`` of :class:`mbtsr.mpc.MPC` for
        this planner, its sampling seeded from ``seed`` (the agent's and the oracle's)."""
        if self.kind == "ilqr":
            return ilqr, None, self.ilqr_iterations
        if self.kind == "cem":
            options = dataclasses.replace(self.cem, seed=seed)
            return cem, options, options.iterations
        return cem_ilqr, CEMILQROptions(
            max_iter=self.ilqr_iterations,
            cem=dataclasses.replace(self.proposal, seed=seed)), self.ilqr_iterations


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
    :param stop_when_solved: stop ``learn`` at the first solved evaluation.
    :param oracle_cache_dir: folder where the oracle's evaluation costs are memoised across runs
        (``None``: recompute in every run).
    """

    _path: ClassVar[str] = "evaluation"
    every: int = 4
    episodes: int = 3
    seed: int = 1000
    early_exit: bool = True
    solved_ratio: float = 1.2
    solved_return: float | None = None
    stop_when_solved: bool = False
    oracle_cache_dir: str | None = None

    def __post_init__(self) -> None:
        self._int_at_least("every", 0)
        self._int_at_least("episodes", 1)
        self._int_at_least("seed", 0)
        self._float_range("solved_ratio", 1.0)
        if self.solved_return is not None:
            self._float_range("solved_return", -math.inf)
        if self.oracle_cache_dir is not None and not isinstance(self.oracle_cache_dir, str):
            object.__setattr__(self, "oracle_cache_dir", str(self.oracle_cache_dir))


def _default_training() -> TrainConfig:
    return TrainConfig(epochs=150, lr=3e-3, batch=256, progress=False)


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
        ``model.build(state_dim, action_dim, seed)`` once the env's dimensions are known.
    :param training: one model update (Algorithm 1, "fit f to tau_i and the perturbed tau_i"),
        warm-started, on ALL data so far; ``training.epochs`` epochs after each new episode, the
        Adam state carried across episodes. ``batch="trajectory"``: one batch per trajectory.
        The agent gives every update its own seed (derived from ``seed``), so ``training.seed``
        must stay 0.
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
    :param torch_threads: ``torch.set_num_threads`` value applied by ``learn`` (0: leave as is).
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
    torch_threads: int = 0

    def __post_init__(self) -> None:
        if isinstance(self.regularization, str):
            object.__setattr__(self, "regularization",
                               _prefixed("regularization", RegularizationConfig.named,
                                         self.regularization, ltv_lambda=None))
        if isinstance(self.planner, str):
            object.__setattr__(self, "planner", PlannerConfig(kind=self.planner))
        for name, cls in SECTIONS.items():
            if not isinstance(getattr(self, name), cls):
                raise ValueError(f"{name} must be a {cls.__module__}.{cls.__name__}, got "
                                 f"{type(getattr(self, name)).__name__}")
        if self.training.epochs < 1:
            raise ValueError(
                f"training.epochs must be an integer >= 1, got {self.training.epochs!r}")
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
        if self.run_dir is not None and not isinstance(self.run_dir, str):
            object.__setattr__(self, "run_dir", str(self.run_dir))

    # ---- convenience -------------------------------------------------------------------------
    def replace(self, changes: Mapping[str, Any] | None = None, /, **top: Any) -> AgentConfig:
        """A copy with changes applied (validated again): ``changes`` maps dotted field names to
        values (``{"planner.horizon": 50, "regularization": "none"}``), keywords set top-level
        fields (``seed=3``, ``model=ModelConfig(...)``, ``regularization="exact"``).

        :raises ValueError: naming the dotted field (unknown, or a bad value).
        """
        return _replaced(self, {**(changes or {}), **top}, "")

    @classmethod
    def default(cls, changes: Mapping[str, Any] | None = None, /, **top: Any) -> AgentConfig:
        """``AgentConfig().replace(changes, **top)``: the defaults with these changes, e.g.
        ``AgentConfig.default({"planner.horizon": 20}, regularization="none")``."""
        return cls().replace(changes, **top)

    # ---- (de)serialisation: the config is saved as JSON next to the results ------------------
    def to_dict(self) -> dict[str, Any]:
        """A JSON-friendly nested dict of all fields (tuples as lists)."""
        return json.loads(json.dumps(dataclasses.asdict(self)))

    def to_json(self) -> str:
        return json.dumps(self.to_dict(), indent=2, sort_keys=True)

    @classmethod
    def from_dict(cls, d: Mapping[str, Any]) -> AgentConfig:
        """Inverse of :meth:`to_dict`; a dict in the old flat format (before the tree) is
        converted by :func:`from_flat`. Unknown keys are an error naming them."""
        if not isinstance(d, Mapping):
            raise ValueError(f"AgentConfig.from_dict needs a dict of AgentConfig fields, got "
                             f"{type(d).__name__} {d!r}")
        if _is_flat(d):
            return from_flat(d)
        return _built(cls, d, "")

    @classmethod
    def from_json(cls, text: str) -> AgentConfig:
        return cls.from_dict(json.loads(text))


def _field_names(cls: type) -> set[str]:
    return {f.name for f in dataclasses.fields(cls)}


_FIELD_NAMES = _field_names(AgentConfig)


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


def _sub_configs(obj: Any) -> dict[str, type]:
    """The fields of dataclass ``obj`` (an instance or a class with defaults) that hold configs."""
    inst = obj() if isinstance(obj, type) else obj
    return {f.name: type(getattr(inst, f.name)) for f in dataclasses.fields(inst)
            if dataclasses.is_dataclass(getattr(inst, f.name))}


def _replaced(obj: Any, changes: Mapping[str, Any], prefix: str) -> Any:
    """``dataclasses.replace`` with dotted keys (``"planner.cem.samples"``), at any depth; every
    level is validated again and its errors name the dotted path."""
    direct: dict[str, Any] = {}
    nested: dict[str, dict[str, Any]] = {}
    names = _field_names(type(obj))
    for key, value in changes.items():
        head, _, rest = key.partition(".")
        if head not in names:
            old = _FLAT_PATHS.get(key) if not prefix else None
            hint = f" (a field before the tree: now {old!r})" if old else ""
            raise ValueError(f"unknown AgentConfig field {prefix + key!r}{hint}")
        if rest:
            nested.setdefault(head, {})[rest] = value
        else:
            direct[head] = value
    for head, values in nested.items():
        base = direct.get(head, getattr(obj, head))
        if isinstance(base, str) and isinstance(obj, AgentConfig):  # a name, then its fields
            base = getattr(dataclasses.replace(obj, **{head: base}), head)
        if not dataclasses.is_dataclass(base):
            bad = f"{prefix}{head}.{next(iter(values))}"
            raise ValueError(f"unknown AgentConfig field {bad!r}")
        direct[head] = _replaced(base, values, f"{prefix}{head}.")
    return _prefixed(prefix[:-1], dataclasses.replace, obj, **direct)


def _built(cls: type, d: Mapping[str, Any], prefix: str) -> Any:
    """``cls`` from a nested dict of its fields (:meth:`AgentConfig.to_dict`'s inverse, at any
    depth); lists become tuples, unknown keys are an error naming their dotted path."""
    if not isinstance(d, Mapping):
        raise ValueError(f"{prefix[:-1]} must be a dict of {cls.__name__} fields, got {d!r}")
    unknown = sorted(set(d) - _field_names(cls))
    if unknown:
        raise ValueError(f"unknown AgentConfig field(s): {[prefix + k for k in unknown]}")
    subs = _sub_configs(cls)
    kwargs = {k: _built(subs[k], v, f"{prefix}{k}.") if k in subs
              else tuple(v) if isinstance(v, list) else v for k, v in d.items()}
    return _prefixed(prefix[:-1], cls, **kwargs)


# ---- the old flat format (before the tree): one function, tested in tests/test_config_tree.py --
_FLAT_PATHS = {
    **{n: f"collection.{n}" for n in _field_names(CollectionConfig)},
    **{n: f"model.{n}" for n in _field_names(ModelConfig)},
    "epochs_per_episode": "training.epochs", "lr": "training.lr",
    "weight_decay": "training.weight_decay",
    "planner": "planner.kind",
    **{n: f"planner.{n}" for n in _field_names(PlannerConfig) - {"kind", "cem"}},
    **{f"cem_{n}": f"planner.cem.{n}" for n in ("samples", "elites", "iterations")},
    **{f"eval_{n}": f"evaluation.{n}" for n in ("every", "episodes", "seed", "early_exit")},
    **{n: f"evaluation.{n}" for n in ("solved_ratio", "solved_return", "stop_when_solved",
                                       "oracle_cache_dir")},
    **{n: n for n in _FIELD_NAMES - set(SECTIONS)},
}
_FLAT_REGULARIZATION = ("regularization", "jacprop_weight", "jacobian_penalty",
                        "perturbation_sigma", "n_perturbed_copies", "ltv_lambda")


_FLAT_KEYS = set(_FLAT_PATHS) | set(_FLAT_REGULARIZATION) | {"batch_size"}
_FLAT_ONLY = _FLAT_KEYS - _FIELD_NAMES


def _is_flat(d: Mapping[str, Any]) -> bool:
    """Whether ``d`` is in the old flat format (a flat-only key, or a name for a section)."""
    return any(k in _FLAT_ONLY for k in d) or any(
        isinstance(d.get(k), str) for k in ("regularization", "planner"))


def from_flat(flat: Mapping[str, Any]) -> AgentConfig:
    """An :class:`AgentConfig` from the old flat dict (``AgentConfig.to_dict()`` before the tree,
    e.g. ``{"epochs_per_episode": 150, "hidden_width": 20, "regularization": "sampled", ...}``;
    missing keys take their defaults, which did not change).

    ``batch_size=0`` becomes ``training.batch="trajectory"``; ``regularization`` with
    ``jacprop_weight`` (sampled) or ``jacobian_penalty`` (exact/smooth), ``perturbation_sigma``,
    ``n_perturbed_copies`` and ``ltv_lambda`` (``"auto"`` -> ``None``) become one
    :class:`~mbtsr.training.RegularizationConfig`.
    """
    d = dict(flat)
    unknown = sorted(set(d) - _FLAT_KEYS)
    if unknown:
        raise ValueError(f"unknown AgentConfig field(s): {unknown}")
    kind = d.pop("regularization", "sampled")
    weights = {"sampled": d.pop("jacprop_weight", 1.0)}
    penalty = d.pop("jacobian_penalty", 0.01)
    weights.update(exact=penalty, smooth=penalty)
    lam = d.pop("ltv_lambda", "auto")
    reg = _prefixed("regularization", RegularizationConfig.named, kind, weights.get(kind),
                    sigma=d.pop("perturbation_sigma", 0.1), n_copies=d.pop("n_perturbed_copies", 1),
                    ltv_lambda=None if lam == "auto" else lam)
    changes: dict[str, Any] = {_FLAT_PATHS[k]: v for k, v in d.items() if k != "batch_size"}
    if "batch_size" in d:
        changes["training.batch"] = d["batch_size"] if d["batch_size"] != 0 else "trajectory"
    if "model.activations" in changes:
        changes["model.activations"] = tuple(changes["model.activations"])
    return AgentConfig(regularization=reg).replace(changes)
