"""Gymnasium environments of mbtsr, registered on ``import envs``: ``mbtsr/TwoLinkArm-v0``
(:mod:`envs.two_link_arm`) and ``mbtsr/LinearSystem-v0`` (:mod:`envs.linear_system`).

``MUJOCO_GL=egl`` (unless already set) for headless rendering: import ``envs`` before ``mujoco``
(docs/environments.md).
"""

import os

os.environ.setdefault("MUJOCO_GL", "egl")

from gymnasium.envs.registration import register, registry  # noqa: E402

__all__ = ["ARM_ID", "LINEAR_ID"]

ARM_ID = "mbtsr/TwoLinkArm-v0"
LINEAR_ID = "mbtsr/LinearSystem-v0"

# The envs truncate themselves at ``episode_steps``; no TimeLimit wrapper is registered, so that
# ``gymnasium.make(ARM_ID, episode_steps=200)`` is not cut short by a registered limit.
if ARM_ID not in registry:
    register(id=ARM_ID, entry_point="envs.two_link_arm:TwoLinkArmEnv")
if LINEAR_ID not in registry:
    register(id=LINEAR_ID, entry_point="envs.linear_system:LinearSystemEnv")
