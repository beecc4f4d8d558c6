"""mbtsr: model-based control with tangent-space regularized neural-network dynamics models
(Bagge Carlson, Johansson and Robertsson, arXiv:1806.09919; README.md, docs/architecture.md).
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
