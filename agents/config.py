"""Configuration of the Algorithm-1 agent: one frozen dataclass, validated on construction.

The defaults are the configuration that is measured in ``docs/ablation.md`` on
``mbtsr/TwoLinkArm-v0``; where the paper fixes a value it is used (sampled Jacobian propagation
with perturbations of 0.1 x the per-dimension standard deviation, one perturbed copy resampled
every epoch, the ``g`` formulation ``x+ = x + g(x, u)``, an ensemble of small tanh networks).
"""

from __future__ import annotations

import dataclasses
import json
import math
from dataclasses import dataclass, fields
from typing import TYPE_CHECKING, Any

if TYPE_CHECKING:  # the library's configs, imported on use (torch is heavy for a CLI's --help)
    from mbtsr.ensemble import EnsembleConfig
    from mbtsr.training import RegularizationConfig, TrainConfig

__all__ = ["AgentConfig", "REGULARIZATIONS", "FORMULATIONS", "EXCITATIONS", "PLANNERS"]

REGULARIZATIONS = ("sampled", "exact", "smooth", "none")
PLANNERS = ("ilqr", "cem")
FORMULATIONS = ("g", "f")
EXCITATIONS = ("filtered_gaussian", "multisine")


@dataclass(frozen=True)
class AgentConfig:
    """Everything that decides what :class:`agents.jacprop_agent.JacPropAgent` does.

    Data collection (Algorithm 1, "sample rollout trajectory"):

    :param n_excitation_episodes: number of first episodes driven by an excitation signal
        instead of the planner (the model is untrained then).
    :param excitation: ``"filtered_gaussian"`` (low-pass filtered Gaussian noise, the paper's
        robot input) or ``"multisine"``.
    :param excitation_scale: excitation amplitude as a fraction of the action half-range.
    :param excitation_window: moving-average window (steps) of the filtered Gaussian input.
    :param exploration_std: std of Gaussian noise added to planned actions during training
        rollouts, as a fraction of the action half-range (0 disables it).
    :param episode_steps: steps per rollout; ``None`` uses the env's ``TimeLimit``.

    Model (Objective 1 / 2 of the paper):

    :param formulation: ``"g"`` (``x+ = x + g(x,u)``, Objective 2) or ``"f"`` (``x+ = f(x,u)``).
    :param ensemble_size: number of ensemble members (their mean is the model).
    :param hidden_width: hidden units per layer of each member (paper: 20).
    :param hidden_layers: hidden layers per member, 1 (paper) or 2.
    :param activations: member ``k`` uses ``activations[k % len(activations)]``; the default is
        the paper's nominal ensemble (elu, sigmoid, tanh, swish).

    Model update (Algorithm 1, "fit f to tau_i and the perturbed tau_i"), warm-started:

    :param epochs_per_episode: training epochs after each new episode (on ALL data so far).
    :param lr: Adam step size; the Adam state is carried across episodes.
    :param batch_size: minibatch size (``0``: full batch).
    :param weight_decay: L2 weight decay.
    :param regularization: ``"sampled"`` (sampled Jacobian propagation: LTV-labelled perturbed
        points, Section 3 of the paper), ``"exact"`` (the penalty it approximates,
        ``sum_t ||J_model(t) - [A_t B_t]_LTV||_F^2``, by double backprop), ``"smooth"`` (the
        LTV-free penalty ``sum_t ||J_model(t+1) - J_model(t)||_F^2`` of Eq. (reg)) or
        ``"none"``. See :mod:`mbtsr.training` for the exact objective.
    :param jacprop_weight: weight of the perturbed points (``sampled``) in the loss.
    :param jacobian_penalty: weight of the Jacobian penalty (``exact`` / ``smooth``).
    :param perturbation_sigma: perturbation std as a fraction of the per-dimension data std.
    :param n_perturbed_copies: perturbed copies of every point, resampled every epoch.
    :param renormalize: before every update, recompute the model's input/output normalization
        from ALL data so far (:meth:`mbtsr.ensemble.DynamicsEnsemble.refit_normalization`,
        which keeps the represented function), instead of freezing the statistics of the
        first episode. ``False``: the first episode's statistics are kept (the old behaviour).
    :param ltv_lambda: smoothness weight of the LTV fit (Algorithm 1, "fit LTV model"), a
        positive number or ``"auto"`` (:func:`mbtsr.ltv.select_lambda` on every trajectory).
    :param ltv_prior: once the model has seen data, fuse each new LTV fit with the ensemble's
        Jacobians as a Gaussian prior (mean: ensemble mean, variance: ensemble variance +
        ``ltv_prior``; :func:`mbtsr.ltv.fuse_prior`), as the original code's "jacprop with
        prior" did. MPC rollouts excite the system little, and an LTV fit to one of them alone
        has wild Jacobians in the unexcited directions; the prior keeps the model's Jacobians
        there. ``0`` disables it.

    Planning (Algorithm 1, "optimize controller"): MPC = the planner re-solved every step on
    the learned model, warm-started with the shifted previous plan.

    :param planner: ``"ilqr"`` (iLQR on the model's Jacobians, the paper's controller) or
        ``"cem"`` (the cross-entropy method of PETS, :func:`mbtsr.cem.cem`: forward predictions
        only, never the model's Jacobians; the control for the paper's argument).
    :param cem_samples: CEM action sequences sampled per iteration.
    :param cem_elites: CEM elite sequences that refit the sampling distribution.
    :param cem_iterations: CEM iterations per MPC step (the first step of an episode gets
        ``first_plan_iterations``).
    :param replan_every: execute every plan open loop for this many steps before re-solving
        (1: re-plan every step, the default; larger: the feedback-limited regime, where
        feedback hides less of the model's error). The oracle uses the same setting.
    :param horizon: MPC horizon (steps).
    :param ilqr_iterations: iLQR iterations per MPC step (the first step of an episode gets
        ``first_plan_iterations``).
    :param first_plan_iterations: iLQR iterations for the full plan at the start of an episode.
    :param terminal_weight: the planner's terminal cost is ``terminal_weight`` x the user's
        ``terminal_cost_fn(obs)`` (default: the stage cost at zero action).

    Evaluation: the deterministic MPC policy (no exploration noise) on ``eval_episodes`` fixed
    episodes; logged as returns (sum of the env's rewards, per episode and their mean). The run
    is "solved" at the first evaluation whose mean return is ``>= solved_return`` when that is
    given (any env), else whose mean cost is within ``solved_ratio`` x the cost of MPC with the
    TRUE model on the same episodes (envs that offer a true model, e.g. the arm):

    :param solved_return: success threshold on the mean evaluation return (``None``: the
        oracle-ratio criterion, or no "solved" decision for envs without a true model).

    :param eval_every: evaluate every this many episodes from the last excitation episode on,
        and after the last episode of every ``learn`` call (0: never). ``episodes_to_solve`` is
        the episode of the first solved evaluation, so it is resolved to ``eval_every``
        episodes (an upper bound on the first episode whose model would have passed).
    :param eval_episodes: evaluation episodes (fixed targets/seeds, see ``eval_seed``).
    :param eval_seed: seed of the evaluation targets and resets.
    :param solved_ratio: the solved threshold relative to the oracle.
    :param stop_when_solved: stop ``learn`` at the first solved evaluation.
    :param eval_early_exit: stop an evaluation as soon as the summed cost exceeds
        ``solved_ratio`` x the oracle's summed cost (exact for costs >= 0: such an evaluation
        cannot be solved); its ``eval_cost`` is then not logged and ``cost_ratio`` is a lower
        bound (see ``eval_episodes_run``).
    :param oracle_cache_dir: folder where the oracle's evaluation costs are memoised across runs
        (``None``: recompute in every run).

    Bookkeeping:

    :param seed: master seed; every random draw of a run derives from it.
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

    # data collection
    n_excitation_episodes: int = 2
    excitation: str = "filtered_gaussian"
    excitation_scale: float = 0.3
    excitation_window: int = 8
    exploration_std: float = 0.1
    episode_steps: int | None = None
    # model
    formulation: str = "g"
    ensemble_size: int = 4
    hidden_width: int = 20
    hidden_layers: int = 1
    activations: tuple[str, ...] = ("elu", "sigmoid", "tanh", "swish")
    # model update
    epochs_per_episode: int = 150
    lr: float = 3e-3
    batch_size: int = 256
    weight_decay: float = 0.0
    regularization: str = "sampled"
    jacprop_weight: float = 1.0
    jacobian_penalty: float = 0.01
    perturbation_sigma: float = 0.1
    n_perturbed_copies: int = 1
    renormalize: bool = True
    ltv_lambda: float | str = "auto"
    ltv_prior: float = 0.01
    # planning
    planner: str = "ilqr"
    cem_samples: int = 200
    cem_elites: int = 20
    cem_iterations: int = 3
    replan_every: int = 1
    horizon: int = 30
    ilqr_iterations: int = 2
    first_plan_iterations: int = 20
    terminal_weight: float = 1.0
    # evaluation
    eval_every: int = 4
    eval_episodes: int = 3
    eval_seed: int = 1000
    solved_ratio: float = 1.2
    solved_return: float | None = None
    stop_when_solved: bool = False
    eval_early_exit: bool = True
    oracle_cache_dir: str | None = None
    # bookkeeping
    seed: int = 0
    run_dir: str | None = None
    checkpoint: bool = True
    tensorboard: bool = True
    video: bool = False
    video_every: int = 5
    jacobian_error: bool = True
    progress: bool = True
    torch_threads: int = 0

    def __post_init__(self) -> None:
        if isinstance(self.activations, str):
            object.__setattr__(self, "activations", (self.activations,))
        object.__setattr__(self, "activations", tuple(self.activations))
        _int_at_least(self, "n_excitation_episodes", 1)
        _choice(self, "excitation", EXCITATIONS)
        _float_range(self, "excitation_scale", 0.0, 1.0, low_open=True)
        _int_at_least(self, "excitation_window", 1)
        _float_range(self, "exploration_std", 0.0, math.inf)
        if self.episode_steps is not None:
            _int_at_least(self, "episode_steps", 2)
        _choice(self, "formulation", FORMULATIONS)
        _int_at_least(self, "ensemble_size", 1)
        _int_at_least(self, "hidden_width", 1)
        if self.hidden_layers not in (1, 2) or isinstance(self.hidden_layers, bool):
            raise ValueError(f"hidden_layers must be 1 or 2, got {self.hidden_layers!r}")
        from mbtsr.ensemble import ACTIVATIONS

        if len(self.activations) == 0 or any(a not in ACTIVATIONS for a in self.activations):
            raise ValueError(
                f"activations must be a non-empty tuple of names from {sorted(ACTIVATIONS)}, "
                f"got {self.activations!r}"
            )
        _int_at_least(self, "epochs_per_episode", 1)
        _float_range(self, "lr", 0.0, math.inf, low_open=True)
        _int_at_least(self, "batch_size", 0)
        _float_range(self, "weight_decay", 0.0, math.inf)
        _choice(self, "regularization", REGULARIZATIONS)
        _float_range(self, "jacprop_weight", 0.0, math.inf)
        _float_range(self, "jacobian_penalty", 0.0, math.inf)
        _float_range(self, "perturbation_sigma", 0.0, math.inf, low_open=True)
        _int_at_least(self, "n_perturbed_copies", 1)
        if isinstance(self.ltv_lambda, str):
            if self.ltv_lambda != "auto":
                raise ValueError(f"ltv_lambda must be > 0 or 'auto', got {self.ltv_lambda!r}")
        else:
            _float_range(self, "ltv_lambda", 0.0, math.inf, low_open=True)
        _float_range(self, "ltv_prior", 0.0, math.inf)
        _choice(self, "planner", PLANNERS)
        _int_at_least(self, "cem_samples", 2)
        _int_at_least(self, "cem_elites", 1)
        if self.cem_elites > self.cem_samples:
            raise ValueError(
                f"cem_elites must be <= cem_samples, got {self.cem_elites} > {self.cem_samples}")
        _int_at_least(self, "cem_iterations", 1)
        _int_at_least(self, "replan_every", 1)
        _int_at_least(self, "horizon", 2)
        if self.replan_every > self.horizon:
            raise ValueError(f"replan_every must be <= horizon={self.horizon}, got "
                             f"{self.replan_every}")
        _int_at_least(self, "ilqr_iterations", 1)
        _int_at_least(self, "first_plan_iterations", 1)
        _float_range(self, "terminal_weight", 0.0, math.inf)
        _int_at_least(self, "eval_every", 0)
        _int_at_least(self, "eval_episodes", 1)
        _int_at_least(self, "eval_seed", 0)
        _float_range(self, "solved_ratio", 1.0, math.inf)
        if self.solved_return is not None:
            _float_range(self, "solved_return", -math.inf, math.inf)
        _int_at_least(self, "seed", 0)
        _int_at_least(self, "video_every", 1)
        _int_at_least(self, "torch_threads", 0)
        if self.run_dir is not None and not isinstance(self.run_dir, str):
            object.__setattr__(self, "run_dir", str(self.run_dir))

    # ---- the library's configs this one composes: the ONLY place its fields are mapped ----
    def ensemble_config(self, state_dim: int, action_dim: int) -> EnsembleConfig:
        """The :class:`mbtsr.ensemble.EnsembleConfig` of the agent's model (member ``k`` uses
        ``activations[k % len(activations)]``; inputs and outputs normalized)."""
        from mbtsr.ensemble import EnsembleConfig, MemberSpec

        members = tuple(
            MemberSpec(activation=self.activations[k % len(self.activations)],
                       width=self.hidden_width, depth=self.hidden_layers)
            for k in range(self.ensemble_size)
        )
        return EnsembleConfig(state_dim=state_dim, action_dim=action_dim, members=members,
                              formulation=self.formulation, normalize=True, seed=self.seed)

    def train_config(self, seed: int = 0) -> TrainConfig:
        """The :class:`mbtsr.training.TrainConfig` of one model update (``seed`` drives the batch
        order and the perturbation draws; ``batch_size=0`` is one batch per trajectory)."""
        from mbtsr.training import TrainConfig

        return TrainConfig(epochs=self.epochs_per_episode, lr=self.lr,
                           batch="trajectory" if self.batch_size == 0 else self.batch_size,
                           weight_decay=self.weight_decay, seed=seed, progress=False)

    def regularization_config(self) -> RegularizationConfig:
        """The :class:`mbtsr.training.RegularizationConfig` of ``regularization``: ``sampled``
        weighs the perturbed copies by ``jacprop_weight``, ``exact``/``smooth`` their penalty by
        ``jacobian_penalty``, ``none`` nothing."""
        from mbtsr.training import RegularizationConfig

        weights = {
            "sampled": {"sampled_weight": self.jacprop_weight},
            "exact": {"exact_weight": self.jacobian_penalty},
            "smooth": {"smooth_weight": self.jacobian_penalty},
            "none": {},
        }[self.regularization]
        return RegularizationConfig(sigma=self.perturbation_sigma,
                                    n_copies=self.n_perturbed_copies, **weights)

    # ---- (de)serialisation: the resolved config is saved as JSON next to the results ----
    def to_dict(self) -> dict[str, Any]:
        """A JSON-friendly dict of all fields."""
        d = dataclasses.asdict(self)
        d["activations"] = list(self.activations)
        return d

    def to_json(self) -> str:
        return json.dumps(self.to_dict(), indent=2, sort_keys=True)

    @classmethod
    def from_dict(cls, d: dict[str, Any]) -> AgentConfig:
        """Inverse of :meth:`to_dict`; unknown keys are an error (naming them)."""
        known = {f.name for f in fields(cls)}
        unknown = sorted(set(d) - known)
        if unknown:
            raise ValueError(f"unknown AgentConfig field(s): {unknown}")
        d = dict(d)
        if "activations" in d:
            d["activations"] = tuple(d["activations"])
        return cls(**d)

    def replace(self, **changes: Any) -> AgentConfig:
        """A copy with ``changes`` applied (validated again)."""
        return dataclasses.replace(self, **changes)


def _int_at_least(cfg: AgentConfig, name: str, low: int) -> None:
    v = getattr(cfg, name)
    if isinstance(v, bool) or not isinstance(v, int) or v < low:
        raise ValueError(f"{name} must be an integer >= {low}, got {v!r}")


def _float_range(
    cfg: AgentConfig, name: str, low: float, high: float, *, low_open: bool = False
) -> None:
    v = getattr(cfg, name)
    if isinstance(v, bool) or not isinstance(v, (int, float)) or not math.isfinite(v):
        raise ValueError(f"{name} must be a finite number, got {v!r}")
    if (v <= low if low_open else v < low) or v > high:
        lo = "(" if low_open else "["
        raise ValueError(f"{name} must be in {lo}{low}, {high}], got {v!r}")


def _choice(cfg: AgentConfig, name: str, options: tuple[str, ...]) -> None:
    v = getattr(cfg, name)
    if v not in options:
        raise ValueError(f"{name} must be one of {options}, got {v!r}")
