"""Crash-safe, checksummed, atomic checkpoint files for the agent, loaded without unpickling
arbitrary objects, and the checks that a resumed run continues under the same conditions
(docs/agent.md, "Checkpoints and exact resume").
"""

from __future__ import annotations

import json
import math
import os
from collections.abc import Mapping
from pathlib import Path
from typing import Any

import numpy as np
import torch

from agents.config import AgentConfig
from agents.task_setup import LearnedTask, build_agent
from agents.task_setup import registry_task as registry_task_on
from agents.tasks import FUNCTION_NAMES, EnvSpec, QuadraticTargetCost, env_spec, make_task
from mbtsr.ensemble import save_model
from mbtsr.fileformat import (
    CheckpointError,
    torch_load_verified,
    torch_save_verified,
)
from mbtsr.io import atomic_write_text, remove_stale_temp_files
from mbtsr.reward import RewardModel
from mbtsr.trajectory import Trajectory, save_trajectories

__all__ = [
    "CheckpointError",
    "agent_payload",
    "restore_agent",
    "load_agent",
    "write_run",
    "atomic_write_text",
    "check_resumable",
    "check_same",
    "env_fingerprint",
    "save_checkpoint",
    "load_checkpoint",
    "numpy_rng_state",
    "set_numpy_rng_state",
    "CHECKPOINT_FORMAT",
]

#: bumped when the payload layout changes incompatibly (2: checksummed file with a header)
CHECKPOINT_FORMAT = 2
_KIND = "agent-checkpoint"


def numpy_rng_state(rng: np.random.Generator) -> str:
    """The full state of a numpy ``Generator`` as a JSON string (``bit_generator.state``)."""
    return json.dumps(rng.bit_generator.state)


def set_numpy_rng_state(rng: np.random.Generator, state: str) -> np.random.Generator:
    """Restore a state produced by :func:`numpy_rng_state` into ``rng`` (in place)."""
    decoded = json.loads(state)
    if decoded.get("bit_generator") != type(rng.bit_generator).__name__:
        raise ValueError(
            f"RNG state is for {decoded.get('bit_generator')!r}, generator uses "
            f"{type(rng.bit_generator).__name__!r}"
        )
    rng.bit_generator.state = decoded
    return rng


def save_checkpoint(path: str | os.PathLike, payload: dict[str, Any]) -> Path:
    """Atomically save a checkpoint ``payload`` (a dict of tensors, numbers, strings, lists,
    dicts; numpy arrays are converted to tensors) to ``path``, with its format version and a
    content checksum."""
    if not isinstance(payload, dict):
        raise TypeError(f"payload must be a dict, got {type(payload).__name__}")
    return torch_save_verified({"format": CHECKPOINT_FORMAT, **_to_torch(payload)}, path,
                               kind=_KIND, version=CHECKPOINT_FORMAT)


def load_checkpoint(path: str | os.PathLike) -> dict[str, Any]:
    """Load a checkpoint written by :func:`save_checkpoint` (checksum verified, then
    ``weights_only=True``). Stale temporary files of interrupted writes next to it are removed.

    :raises FileNotFoundError: no file at ``path``.
    :raises CheckpointError: truncated, corrupted, another format or not a checkpoint.
    """
    path = Path(path)
    remove_stale_temp_files(path)
    payload, _ = torch_load_verified(path, kind=_KIND, versions=(CHECKPOINT_FORMAT,),
                                     what="an agent checkpoint")
    if not isinstance(payload, dict) or payload.get("format") != CHECKPOINT_FORMAT:
        raise CheckpointError(f"{path} is not an agent checkpoint of format {CHECKPOINT_FORMAT}")
    return payload


def agent_payload(agent: Any) -> dict[str, Any]:
    """Everything a :class:`agents.jacprop_agent.JacPropAgent` needs to continue learning
    bit-identically or to act (a dict for :func:`save_checkpoint`; docs/agent.md,
    "Checkpoints and exact resume")."""
    learned = isinstance(agent.task_cost, LearnedTask)
    task: dict[str, Any] = {
        "cost": agent.cost_fn.to_dict() if isinstance(agent.cost_fn, QuadraticTargetCost) else None,
        "state_map": agent.state_map.to_dict() if agent.state_map.serializable else None,
        "learned": learned}
    fns = user_functions(agent)
    task["functions"] = sorted(k for k, f in fns.items() if f is not None)
    # a task of agents.tasks.TASKS on this env id with exactly these functions (the same
    # objects) is saved by name
    known = registry_task_on(agent.env_id)
    same = known is not None and all(fns[k] is f for k, f in known.agent_kwargs().items())
    task["registry"] = known.name if same else None
    task["env_id"] = agent.env_id
    ev = agent.evaluator
    return {
        "agent_config": json.dumps(agent.config.to_dict()),
        "env_spec": json.dumps(agent.spec.to_dict()),
        "env_fingerprint": None if agent.env is None else json.dumps(env_fingerprint(agent.env)),
        "task": json.dumps(task),
        "ensemble_config": agent.ensemble_config.to_json(),
        "model_state": {k: v.detach().clone() for k, v in agent.model.state_dict().items()},
        "optimizer_state": agent.trainer.optimizer_state,
        "trajectories": [
            {"x": t.x, "u": t.u, "meta": json.dumps(t.meta)} for t in agent.trajectories
        ],
        **agent.labeler.state_dict(),
        "episodes_done": agent.episodes_done,
        "env_steps": agent.env_steps,
        "rng": numpy_rng_state(agent.rng),
        "predict_rng": numpy_rng_state(agent.predict_rng),
        "torch_rng": torch.get_rng_state(),
        "log": json.dumps(agent.logger_rows),
        "eval_targets": None if ev.eval_targets is None else [
            np.asarray(t) for t in ev.eval_targets],
        "oracle_costs": None if ev.oracle_costs is None else np.asarray(ev.oracle_costs),
        "reward_model": agent.task_cost.model.state_dict() if learned else None,
    }


def restore_agent(agent: Any, p: dict[str, Any]) -> None:
    """Load :func:`agent_payload`'s fields (as :func:`load_checkpoint` returns them) into a
    freshly constructed agent of the same config and task, the RNGs included."""
    agent.model.load_state_dict(p["model_state"])
    if p.get("reward_model") is not None:
        agent.task_cost.model = RewardModel.from_state_dict(p["reward_model"])
    agent.freeze()
    agent.trainer.optimizer_state = p["optimizer_state"]
    agent.trajectories = [
        Trajectory(d["x"].numpy(), d["u"].numpy(), agent.spec.dt, meta=json.loads(d["meta"]))
        for d in p["trajectories"]
    ]
    agent.labeler.load_state_dict(p)
    agent.episodes_done = int(p["episodes_done"])
    agent.env_steps = int(p["env_steps"])
    set_numpy_rng_state(agent.rng, p["rng"])
    if "predict_rng" in p:  # checkpoints from before predict(deterministic=False) had none
        set_numpy_rng_state(agent.predict_rng, p["predict_rng"])
    torch.set_rng_state(p["torch_rng"])
    agent.logger_rows = json.loads(p["log"])
    ev = agent.evaluator
    ev.eval_targets = None if p["eval_targets"] is None else [
        t.numpy() for t in p["eval_targets"]]
    ev.oracle_costs = None if p["oracle_costs"] is None else p["oracle_costs"].numpy()


def user_functions(agent: Any) -> dict[str, Any]:
    """The agent's task functions that a checkpoint cannot hold (``None`` for those it does
    not have or that are saved as data: the env's quadratic cost, a prefix state map)."""
    custom_map = not agent.state_map.serializable
    return {
        "cost_fn": None if isinstance(agent.cost_fn, QuadraticTargetCost) else agent.cost_fn,
        "terminal_cost_fn": agent.terminal_cost_fn,
        "termination_fn": agent.termination_fn,
        "state_fn": agent.state_map._state_fn if custom_map else None,
        "obs_fn": agent.state_map._obs_fn if custom_map else None,
    }


def check_resumable(
    payload: dict[str, Any], path: str | os.PathLike, config: Any, env: Any,
    fns: dict[str, Any],
) -> tuple[EnvSpec, dict[str, Any]]:
    """Check that a loaded checkpoint can be restored with ``env`` and the task functions (a
    registry task's come from :data:`agents.tasks.TASKS`).

    :param config: the checkpoint's :class:`agents.config.AgentConfig` (episode length).
    :param env: the env to continue in, or ``None`` (act only).
    :param fns: the task functions given to ``load`` by name (:data:`agents.tasks.FUNCTION_NAMES`).
    :return: ``(spec, task)``: the saved :class:`agents.tasks.EnvSpec` and task.
    :raises ValueError: the env's sizes or bounds differ, or a function is missing (named).
    :raises CheckpointError: the env's fingerprint differs (naming the field).
    """
    spec = EnvSpec.from_dict(json.loads(payload["env_spec"]))
    if env is not None:
        got = env_spec(env, config.collection.episode_steps)
        if (got.obs_dim, got.act_dim) != (spec.obs_dim, spec.act_dim) or not (
            np.array_equal(got.u_min, spec.u_min) and np.array_equal(got.u_max, spec.u_max)
        ):
            raise ValueError(
                f"env does not match the saved agent: obs_dim/act_dim/bounds "
                f"{(got.obs_dim, got.act_dim, got.u_min, got.u_max)} vs "
                f"{(spec.obs_dim, spec.act_dim, spec.u_min, spec.u_max)}"
            )
        if payload.get("env_fingerprint"):
            check_same(json.loads(payload["env_fingerprint"]), env_fingerprint(env),
                       what="env", path=path)
    task = json.loads(payload["task"])
    needed = task.get("functions")
    if needed is None:  # a checkpoint from before the list was saved
        needed = (["cost_fn"] if task.get("cost") is None else []) + (
            ["state_fn", "obs_fn"] if task.get("state_map") is None else [])
    # a registry task's functions come from the registry (agents.task_setup.resolve_task), as
    # do a learned reward's termination and state maps on a known env
    known = task.get("registry") or (task.get("learned") and getattr(
        registry_task_on(task.get("env_id")), "name", None))
    saved = make_task(known).agent_kwargs() if known else {}
    missing = [k for k in FUNCTION_NAMES
               if k in needed and fns[k] is None and saved.get(k) is None]
    if missing:
        raise ValueError(
            f"the agent was built with its own {', '.join(missing)}, which a checkpoint cannot "
            f"hold: pass {', '.join(f'{k}=' for k in missing)} to load (for a task of "
            "agents.tasks: JacPropAgent.load(path, env, **task.agent_kwargs()))")
    return spec, task


def write_run(agent: Any, run_dir: str | os.PathLike) -> None:
    """The run folder after an episode: ``checkpoint.pt`` (the source of truth) and its
    conveniences ``model.pt``, ``data.npz`` and ``summary.json`` (each written atomically)."""
    run_dir = Path(run_dir)
    run_dir.mkdir(parents=True, exist_ok=True)
    agent.save(run_dir / "checkpoint.pt")
    save_model(agent.model, run_dir / "model.pt")
    save_trajectories(run_dir / "data.npz", agent.trajectories)
    atomic_write_text(run_dir / "summary.json", json.dumps(agent.summary(), indent=2))


def env_fingerprint(env: Any) -> dict[str, Any]:
    """What must not change when a run resumes in ``env``: its id, its constructor arguments
    (``dt``, a preset, ...), its time step and its observation and action spaces (JSON)."""
    spec = getattr(env, "spec", None)
    kwargs = {}
    for k, v in (getattr(spec, "kwargs", None) or {}).items():
        try:
            kwargs[k] = json.loads(json.dumps(v))
        except (TypeError, ValueError):
            kwargs[k] = repr(v)
    out: dict[str, Any] = {"id": getattr(spec, "id", None), "kwargs": kwargs}
    dt = getattr(getattr(env, "unwrapped", env), "dt", None)
    out["dt"] = float(dt) if isinstance(dt, int | float | np.floating) else None
    for name in ("observation_space", "action_space"):
        space = getattr(env, name, None)
        out[name] = None if space is None else {
            "type": type(space).__name__,
            "shape": list(getattr(space, "shape", None) or []),
            "low": np.asarray(getattr(space, "low", [])).tolist(),
            "high": np.asarray(getattr(space, "high", [])).tolist(),
        }
    return json.loads(json.dumps(out, default=str))


def _first_difference(saved: Any, now: Any, where: str) -> tuple[str, Any, Any] | None:
    """``(field, saved value, value now)`` of the first difference (``None``: equal)."""
    if isinstance(saved, Mapping) and isinstance(now, Mapping):
        pairs = [(f"{where}.{k}", saved.get(k, "<absent>"), now.get(k, "<absent>"))
                 for k in sorted(set(saved) | set(now), key=str)]
    elif isinstance(saved, list | tuple) and isinstance(now, list | tuple) \
            and len(saved) == len(now):
        pairs = [(f"{where}[{i}]", a, b) for i, (a, b) in enumerate(zip(saved, now))]
    else:
        nan = all(isinstance(v, float) and math.isnan(v) for v in (saved, now))
        return None if nan or saved == now else (where.lstrip(".") or "value", saved, now)
    return next((d for w, a, b in pairs if (d := _first_difference(a, b, w))), None)


def check_same(saved: Mapping, now: Mapping, *, what: str, path: str | os.PathLike) -> None:
    """Raise :class:`CheckpointError` naming the first field where ``now`` differs from
    ``saved`` (nested dicts and lists are compared field by field).

    :param what: what is compared, for the message ("env", "config").
    :param path: the checkpoint, for the message.
    """
    d = _first_difference(dict(saved), dict(now), "")
    if d is not None:
        field, a, b = d
        raise CheckpointError(
            f"cannot resume {path}: the {what} differs in {field!r} (checkpoint: {a!r}, "
            f"now: {b!r}); resume with the same {what} or start a new run")


def _to_torch(obj: Any) -> Any:
    """Recursively turn numpy arrays into tensors so that ``weights_only`` loading works."""
    if isinstance(obj, np.ndarray):
        return torch.from_numpy(np.array(obj, copy=True, order="C"))
    if isinstance(obj, np.generic):
        return obj.item()
    if isinstance(obj, dict):
        return {k: _to_torch(v) for k, v in obj.items()}
    if isinstance(obj, (list, tuple)):
        return type(obj)(_to_torch(v) for v in obj)
    return obj


def load_agent(cls: type, path: str | os.PathLike, env: Any, fns: dict[str, Any], *,
               run_dir: str | os.PathLike | None = None) -> Any:
    """The body of :meth:`agents.jacprop_agent.JacPropAgent.load`: read the checkpoint at
    ``path`` (a file or a run folder), check it (:func:`check_resumable`), build an agent of
    class ``cls`` and restore its state (:func:`restore_agent`).

    :param run_dir: overrides the saved config's ``run_dir``.
    :raises ValueError: as :func:`check_resumable`, or ``state_fn`` gives a model state of
        another dimension than the saved model's.
    """
    path = Path(path)
    if path.is_dir():
        path = path / "checkpoint.pt"
    payload = load_checkpoint(path)
    cfg = json.loads(payload["agent_config"])
    if run_dir is not None:
        cfg["run_dir"] = str(run_dir)
    config = AgentConfig.from_dict(cfg)
    spec, task = check_resumable(payload, path, config, env, fns)
    saved_n = json.loads(payload["ensemble_config"])["state_dim"]
    agent = cls.__new__(cls)
    build_agent(agent, env, config, spec, fns, saved_task=task)
    if agent.state_dim != saved_n:
        raise ValueError(
            f"state_fn gives a model state of dimension {agent.state_dim}, but the saved "
            f"agent's model was trained on dimension {saved_n}: pass the state_fn/obs_fn it "
            "was built with"
        )
    restore_agent(agent, payload)
    agent.env_id = agent.env_id or task.get("env_id")  # an act-only agent keeps its task's
    return agent
