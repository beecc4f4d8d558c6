"""Model training (Algorithm 1, steps (c) + (d)): warm-started updates on ALL data so far with the
JacProp labels (:func:`mbtsr.training.train_ensemble`), and the model's errors on new data."""

from __future__ import annotations

import dataclasses
import math
from typing import Any

import numpy as np

from mbtsr.ensemble import DynamicsEnsemble
from mbtsr.ltv import LTVModel
from mbtsr.metrics import jacobian_error, prediction_rms
from mbtsr.training import RegularizationConfig, TrainConfig, TrainHistory, train_ensemble
from mbtsr.trajectory import Trajectory

__all__ = ["ModelTrainer", "model_errors"]


class ModelTrainer:
    """Warm-started updates of ``model`` (in place).

    :param model: the ensemble.
    :param training: the training settings (its ``seed`` is replaced per update).
    :param regularization: the tangent-space regularization.
    :param renormalize: refit the input/output normalization to all data before each update.
    """

    def __init__(self, model: DynamicsEnsemble, training: TrainConfig,
                 regularization: RegularizationConfig, renormalize: bool = False) -> None:
        self.model, self.training, self.regularization = model, training, regularization
        self.renormalize = bool(renormalize)
        self.optimizer_state: dict | None = None

    def configs(self, seed: int = 0) -> tuple[TrainConfig, RegularizationConfig]:
        """The :class:`~mbtsr.training.TrainConfig` of an update (``seed`` drives batch order
        and the perturbation draws) and its :class:`~mbtsr.training.RegularizationConfig`."""
        return dataclasses.replace(self.training, seed=seed), self.regularization

    def train(self, trajectories: list[Trajectory], labels: list[LTVModel],
              seed: int) -> TrainHistory:
        """One update on all ``trajectories`` with their JacProp ``labels`` (one LTV model per
        trajectory, or none without LTV regularization).

        :param seed: this update's seed.
        :return: the :class:`~mbtsr.training.TrainHistory` (losses, steps).
        """
        tcfg, reg = self.configs(seed)
        if self.renormalize:
            self.model.refit_normalization(trajectories)
        history = train_ensemble(self.model, trajectories, tcfg, reg,
                                 ltv_models=labels if labels else None,
                                 optimizer_state=self.optimizer_state)
        self.optimizer_state = history.optimizer_state
        return history


def model_errors(model: DynamicsEnsemble, traj: Trajectory,
                 true_env: Any = None) -> tuple[float, float]:
    """One-step RMS of the ensemble mean on ``traj`` and the paper's Jacobian error (eq.
    jacerr); NaN before the model has seen data, without a linearization, or when the model's
    state is not the env's own (its ``dynamics_model().state_dim`` differs).

    :param true_env: an unwrapped env with ``linearize_trajectory(x [T, n], u [T, m])`` or
        ``linearize(x, u)``, or ``None``.
    :return: ``(one_step_rms, jacobian_error)``.
    """
    if not model.is_normalized:
        return math.nan, math.nan
    one_step = float(prediction_rms(model, traj))
    if not (hasattr(true_env, "linearize_trajectory") or hasattr(true_env, "linearize")):
        return one_step, math.nan
    x, u = traj.inputs
    if (hasattr(true_env, "dynamics_model")
            and true_env.dynamics_model().state_dim != x.shape[1]):
        return one_step, math.nan  # the model's state is not the env's (e.g. the observation)
    if hasattr(true_env, "linearize_trajectory"):
        J_true = true_env.linearize_trajectory(x, u)
    else:
        pairs = [true_env.linearize(xt, ut) for xt, ut in zip(x, u)]
        J_true = (np.stack([p[0] for p in pairs]), np.stack([p[1] for p in pairs]))
    return one_step, float(jacobian_error(J_true, model.jacobians(x, u)))
