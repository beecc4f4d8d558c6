"""mbtsr: model-based control with tangent-space regularized neural-network dynamics models.

Implements Bagge Carlson, Johansson and Robertsson, "Tangent-Space Regularization for
Neural-Network Models of Dynamical Systems" (arXiv:1806.09919): LTV identification, neural
dynamics ensembles with sampled Jacobian propagation and exact Jacobian penalties, iLQR/MPC on
any model with the :class:`mbtsr.dynamics.DynamicsModel` protocol, and the paper's metrics.
"""

from mbtsr.dynamics import DynamicsModel, LinearDynamics, rollout
from mbtsr.trajectory import Trajectory, load_trajectories, save_trajectories, stack_trajectories

__version__ = "0.1.0"

__all__ = [
    "DynamicsModel",
    "LinearDynamics",
    "Trajectory",
    "load_trajectories",
    "rollout",
    "save_trajectories",
    "stack_trajectories",
]
