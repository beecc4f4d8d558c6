"""The Algorithm-1 agent: episodic model learning with tangent-space regularization and iLQR.

Bagge Carlson, Johansson and Robertsson, "Tangent-Space Regularization for Neural-Network Models
of Dynamical Systems" (arXiv:1806.09919), Algorithm 1, run in an episodic loop. Every episode:

(a) **rollout** in the real env: the first ``n_excitation_episodes`` with a low-pass filtered
    Gaussian (or multisine) excitation, then MPC (iLQR re-solved every step) on the learned
    model plus Gaussian exploration noise;
(b) **LTV fit** ``l_i`` to the new trajectory (:func:`mbtsr.ltv.fit_ltv`, smoothness weight
    fixed or chosen by :func:`mbtsr.ltv.select_lambda`);
(c) **perturbed trajectories** ``x~ = x + eps_x, u~ = u + eps_u`` labelled by ``l_i``
    (resampled every epoch inside :func:`mbtsr.training.train_ensemble`);
(d) **model update**: the ensemble is trained further (warm start: weights and Adam state
    carried over) on ALL data so far, with the chosen regularization (``sampled`` Jacobian
    propagation, the ``exact`` Jacobian-smoothness penalty, or ``none``), by default a budget
    of gradient steps with early stopping on a hold-out (its cost does not grow with the data);
(e) **planning**: the next rollout is optimised by iLQR on the learned model's Jacobians
    (full-horizon plan at the first step, then receding horizon).

The surface follows Stable-Baselines3: :meth:`JacPropAgent.learn`, :meth:`~JacPropAgent.predict`,
:meth:`~JacPropAgent.save`, :meth:`JacPropAgent.load`. After every episode the agent writes an
atomic checkpoint (data, model, Adam state, RNG states, config, log) from which
:meth:`JacPropAgent.load` + :meth:`~JacPropAgent.learn` continue bit-identically (except with
``collection.continue_rollouts``: the env's running episode is not saved, so it restarts).
"""

from __future__ import annotations

import dataclasses
import json
import math
import time
import warnings
from collections.abc import Callable
from pathlib import Path
from typing import Any

import gymnasium as gym
import numpy as np
import threadpoolctl
import torch

from agents.checkpoint import (
    atomic_write_text,
    check_same,
    env_fingerprint,
    load_checkpoint,
    numpy_rng_state,
    save_checkpoint,
    set_numpy_rng_state,
)
from agents.config import AgentConfig
from agents.episode_log import TIMING_COLUMNS, EpisodeLog
from agents.evaluation import (
    EpisodeRecord,
    SB3Predictor,
    _is_mujoco_env,
    cached_costs,
    evaluate_policy_costs,
    evaluation_targets,
    has_true_model,
    mpc_policy,
    oracle_cache_key,
    oracle_policy,
    planner_cost,
    run_episode,
)
from agents.tasks import (
    EnvSpec,
    ObservationCost,
    QuadraticTargetCost,
    StateMap,
    default_task_for_env,
    env_spec,
)
from mbtsr.ensemble import DynamicsEnsemble, save_model
from mbtsr.ltv import LTVModel, fit_ltv, fuse_prior, select_lambda
from mbtsr.trajectory import Trajectory, save_trajectories
from mbtsr.validation import as_array, call_user_fn, check_callable, check_finite

__all__ = ["JacPropAgent"]

CostFn = Callable[[Any, Any], Any]

#: bytes an LTV fit may use for its posterior covariance (longer episodes are fitted in segments)
LTV_MEMORY_BUDGET = 256e6
#: construction refuses LTV regularization when even a 2-step fit would need more than this
LTV_MEMORY_MAX = 2e9


class JacPropAgent(SB3Predictor):
    """Model-based agent of the paper's Algorithm 1 (learned NN ensemble + iLQR MPC).

    :param env: a Gymnasium env with 1-D ``Box`` observation and action spaces, a bounded action
        space and a ``TimeLimit`` (or ``config.collection.episode_steps``).
    :param config: :class:`agents.config.AgentConfig`.
    :param cost_fn: stage cost ``cost_fn(obs, action) -> scalar`` written with CasADi
        operations (see :mod:`agents.tasks`). ``None``: the env's own quadratic cost
        (``env.unwrapped.cost_Q/cost_R``, as ``mbtsr/TwoLinkArm-v0`` provides).
    :param state_fn: ``obs -> model state`` (numpy); with ``obs_fn``.
    :param obs_fn: ``(state, obs_ref) -> obs`` (CasADi-compatible), the inverse map used to
        evaluate ``cost_fn`` on predicted states.
    :param terminal_cost_fn: ``obs -> scalar`` (CasADi), the cost of a plan's last predicted
        observation (x ``config.planner.terminal_weight``; default: the stage cost at zero action).
    :param termination_fn: ``obs [..., obs_dim] -> bool [...]`` (numpy): where the env would
        terminate; the planner (iLQR or CEM) adds no cost after a predicted termination.
    :raises ValueError: at construction for non-Box spaces, an unbounded action space, a cost
        or maps that do not fit the env's dimensions, a bad config.
    """

    def __init__(
        self,
        env: gym.Env,
        config: AgentConfig | None = None,
        cost_fn: CostFn | None = None,
        state_fn: Callable[[np.ndarray], np.ndarray] | None = None,
        obs_fn: CostFn | None = None,
        *,
        terminal_cost_fn: Callable[[Any], Any] | None = None,
        termination_fn: Callable[[np.ndarray], np.ndarray] | None = None,
    ) -> None:
        config = AgentConfig() if config is None else config
        if not isinstance(config, AgentConfig):
            raise TypeError(f"config must be an AgentConfig, got {type(config).__name__}")
        spec = env_spec(env, config.collection.episode_steps)
        if (config.collection.rollout_steps or 0) >= spec.episode_steps:
            warnings.warn(f"collection.rollout_steps={config.collection.rollout_steps} has no "
                          f"effect: the episode is {spec.episode_steps} steps long",
                          stacklevel=2)
        if config.video and getattr(env, "render_mode", None) != "rgb_array":
            raise ValueError(
                "config.video needs an env created with render_mode='rgb_array', got "
                f"render_mode={getattr(env, 'render_mode', None)!r}"
            )
        if config.checkpoint and config.run_dir is None:
            config = config.replace(checkpoint=False)
        self._setup(env, config, spec, cost_fn, state_fn, obs_fn,
                    terminal_cost_fn=terminal_cost_fn, termination_fn=termination_fn)

    # ------------------------------------------------------------------ construction
    def _setup(
        self,
        env: gym.Env | None,
        config: AgentConfig,
        spec: EnvSpec,
        cost_fn: CostFn | None,
        state_fn: Callable | None,
        obs_fn: CostFn | None,
        *,
        saved_task: dict | None = None,
        terminal_cost_fn: Callable[[Any], Any] | None = None,
        termination_fn: Callable[[np.ndarray], np.ndarray] | None = None,
    ) -> None:
        self.env = env
        self.config = config
        self.spec = spec
        self.env_id = getattr(getattr(env, "spec", None), "id", None) if env is not None else None
        # the task: cost on (obs, action) and the obs <-> model-state maps
        if cost_fn is None and saved_task is not None and saved_task.get("cost") is not None:
            cost_fn = QuadraticTargetCost.from_dict(saved_task["cost"])
            if state_fn is None and saved_task.get("state_map") is not None:
                state_map = StateMap.from_dict(saved_task["state_map"])
            else:
                state_map = StateMap(state_fn, obs_fn)
        elif cost_fn is None:
            default = default_task_for_env(env) if env is not None else None
            if default is None:
                where = "the saved agent" if env is None else f"env {self.env_id or env!r}"
                raise ValueError(
                    f"cost_fn is required: {where} has no built-in cost (env.unwrapped.cost_Q "
                    "and cost_R); pass cost_fn(obs, action) written with casadi operations"
                )
            cost_fn, default_map = default
            state_map = default_map if state_fn is None else StateMap(state_fn, obs_fn)
        else:
            state_map = StateMap(state_fn, obs_fn)
        self.cost_fn = cost_fn
        self.state_map = state_map
        s = self._check_state_fn(env, spec)
        self.state_dim = int(s.size)
        p = self.state_dim + spec.act_dim
        if config.regularization.needs_ltv and 8 * 4 * 2 * self.state_dim * p**2 > LTV_MEMORY_MAX:
            raise ValueError(
                f"regularization={config.regularization.kind!r} fits LTV models whose covariance "
                "holds "
                f"n (n+m)^2 = {self.state_dim * p**2:.3g} numbers per time step for this model "
                f"state (n={self.state_dim}, m={spec.act_dim}), more than this machine should "
                "hold; pass a smaller model state with state_fn/obs_fn, or choose "
                "AgentConfig(regularization='smooth') or 'none'"
            )
        self.task_cost = ObservationCost(
            cost_fn, state_map, spec, self.state_dim, terminal_cost_fn=terminal_cost_fn)
        self.terminal_cost_fn = terminal_cost_fn
        self.termination_fn = _checked_termination_fn(termination_fn, env, spec)
        self.planner_cost = planner_cost(self.task_cost, config.planner.terminal_weight)
        # the model: an ensemble of small networks, Objective 1 (f) or 2 (g)
        self.ensemble_config = config.model.ensemble_config(self.state_dim, spec.act_dim,
                                                            config.seed)
        self.model = DynamicsEnsemble(self.ensemble_config)
        self._freeze()
        self.has_linearize = env is not None and (
            hasattr(env.unwrapped, "linearize_trajectory") or hasattr(env.unwrapped, "linearize")
        )
        # the learning state (all of it goes into the checkpoint)
        self.rng = np.random.default_rng(config.seed)
        self.trajectories: list[Trajectory] = []
        self.ltv_lambdas: list[float] = []
        self.ltv_models: list = []
        self.optimizer_state: dict | None = None
        self.episodes_done = 0
        self.env_steps = 0
        self.logger_rows: list[dict[str, Any]] = []
        self.eval_targets: list[np.ndarray] | None = None
        self.oracle_costs: np.ndarray | None = None
        self._eval_env: gym.Env | None = None
        self._log: EpisodeLog | None = None
        self._oracle_seconds = 0.0  # computing the oracle (once), booked apart from evaluation
        # collection.continue_rollouts: ((obs, info), steps so far, the TimeLimit's step count)
        # of the env's running episode
        self._handover: tuple[tuple[np.ndarray, dict], int, int | None] | None = None

    def _freeze(self) -> None:
        """Train -> freeze -> plan: the controller plans with an immutable float64 copy of the
        ensemble, taken after each training round (and at construction / load). One MPC
        (:class:`mbtsr.mpc.MPC`) with iLQR or CEM (``config.planner.kind``) on the ensemble
        mean, or CEM on its trajectory-sampling view (``config.planner.propagation="ts"``)."""
        cfg = self.config
        self.planning_model = self.model.freeze()
        model = self.planning_model
        if cfg.planner.propagation == "ts":
            model = self.planning_model.trajectory_sampling(seed=cfg.seed)

        def actor(explore_weight: float) -> tuple[Any, ReplanEvery]:
            optimizer, options, iterations = cfg.planner.optimizer(
                cfg.seed, explore_weight, cfg.collection.explore_on)
            policy = mpc_policy(
                model,
                self.task_cost,
                horizon=cfg.planner.horizon,
                iterations=iterations,
                first_plan_iterations=cfg.planner.first_plan_iterations,
                cost=self.planner_cost,
                optimizer=optimizer,
                optimizer_options=options,
                termination_fn=self.termination_fn,
            )
            return policy, ReplanEvery(policy, cfg.planner.replan_every,
                                       cfg.planner.replan_feedback)

        self.policy, self.actor = actor(0.0)
        # training rollouts: directed exploration (collection.explore_weight), else the same
        self.explorer = (actor(cfg.collection.explore_weight)[1]
                         if cfg.collection.explore_weight > 0 else self.actor)

    def _check_state_fn(self, env: gym.Env | None, spec: EnvSpec) -> np.ndarray:
        """Call the state map on one observation and on a batch of three (it is called on
        whole episodes ``[T+1, obs_dim]`` during :meth:`learn`) and check that the batch gives
        the rows of the single calls. :return: the state of the first probe ``[n]``."""
        probe = _probe_observations(env, (3, spec.obs_dim))
        single = call_user_fn(
            lambda: [self.state_map.state(o) for o in probe],
            failure=f"state_fn failed on one observation [{spec.obs_dim}]",
        )
        s = single[0]
        if s.ndim != 1 or s.size < 1:
            raise ValueError(f"state_fn(obs) must return a 1-D state, got shape {list(s.shape)}")
        batch = call_user_fn(
            self.state_map.state, probe,
            failure="state_fn must also accept a batch of observations [B, obs_dim] and return "
            f"[B, n] (it is applied to whole episodes); it failed on [3, {spec.obs_dim}]",
        )
        if batch.shape != (3, s.size) or not np.allclose(batch, np.stack(single), equal_nan=True):
            raise ValueError(
                "state_fn must map a batch of observations [B, obs_dim] row by row to "
                f"[B, n={s.size}] (it is applied to whole episodes); for a batch of 3 it "
                f"returned shape {list(batch.shape)}"
                + ("" if batch.shape != (3, s.size) else " with rows that differ from "
                   "state_fn applied to each observation")
                + " -- use obs[..., i] indexing (numpy) instead of obs[i]"
            )
        return s

    # ------------------------------------------------------------------ public surface
    def learn(
        self,
        episodes: int | None = None,
        callback: Callable[[dict[str, Any]], bool | None] | None = None,
        progress_bar: bool | None = None,
        *,
        total_env_steps: int | None = None,
    ) -> JacPropAgent:
        """Run Algorithm 1 (rollout, LTV fit, perturbed data, regularised warm-started model
        update, planning) for a budget of episodes or env steps, logging and checkpointing
        after every episode.

        :param episodes: number of episodes to run now (a loaded agent continues its count).
        :param callback: called after every episode with ``{"agent", "row"}``; returning
            ``False`` stops learning (as in Stable-Baselines3).
        :param progress_bar: show a tqdm progress bar (``None``: ``config.progress``).
        :param total_env_steps: budget of env steps for this call (as SB3's
            ``learn(total_timesteps)``); the last episode is cut short (truncated) so that the
            budget is exact. With ``episodes`` too, whichever is reached first stops.
        :return: ``self``.
        """
        if episodes is None and total_env_steps is None:
            raise ValueError("give episodes or total_env_steps")
        if episodes is not None and (
            isinstance(episodes, bool) or not isinstance(episodes, int | np.integer) or episodes < 0
        ):
            raise ValueError(f"episodes must be an integer >= 0, got {episodes!r}")
        if total_env_steps is not None and (
            isinstance(total_env_steps, bool)
            or not isinstance(total_env_steps, int | np.integer) or total_env_steps < 0
        ):
            raise ValueError(f"total_env_steps must be an integer >= 0, got {total_env_steps!r}")
        if self.env is None:
            raise ValueError("this agent was loaded without an env; load(path, env=...) to learn")
        if self.config.torch_threads:
            torch.set_num_threads(self.config.torch_threads)
            # numpy's BLAS too: the frozen model's small products on 2 BLAS threads on a busy
            # machine were measured 10x slower than on one
            threadpoolctl.threadpool_limits(self.config.torch_threads, user_api="blas")
        if self.config.run_dir is not None and self._log is None:
            self._log = EpisodeLog(
                self.config.run_dir, tensorboard=self.config.tensorboard, rows=self.logger_rows
            )
        bar = None
        self._handover = None  # the env may have been used since: a learn call starts from a reset
        step_end = None if total_env_steps is None else self.env_steps + int(total_env_steps)
        if progress_bar is None:
            progress_bar = self.config.progress
        if progress_bar and (episodes or total_env_steps):
            from tqdm.auto import tqdm

            if episodes is not None:
                bar = tqdm(total=episodes, desc="JacProp agent", unit="episode")
            else:
                bar = tqdm(total=total_env_steps, desc="JacProp agent", unit="step")
        try:
            done = 0
            while (episodes is None or done < episodes) and (
                step_end is None or self.env_steps < step_end
            ):
                done += 1
                before = self.env_steps
                cap = None if step_end is None else step_end - self.env_steps
                row = self._episode(max_steps=cap)
                ends = (episodes is not None and done >= episodes) or (
                    step_end is not None and self.env_steps >= step_end)
                if ends and row["eval_returns"] is None and self._should_evaluate(
                        self.episodes_done, last=True):
                    tic = time.perf_counter()  # the final score of this learn call
                    row.update(self._evaluate())
                    dt = time.perf_counter() - tic
                    row["time_oracle"] += self._oracle_seconds
                    row["time_eval"] += dt - self._oracle_seconds
                    row["time_total"] += dt
                    self._oracle_seconds = 0.0
                self.logger_rows.append(row)
                self.episodes_done += 1
                if self.config.checkpoint:
                    self._write_checkpoint()
                if self._log is not None:
                    self._log.append(row)
                if bar is not None:
                    bar.update(1 if episodes is not None else self.env_steps - before)
                    bar.set_postfix(cost=f"{row['episode_cost']:.3g}",
                                    ratio=_fmt(row.get("cost_ratio")))
                if callback is not None and callback({"agent": self, "row": row}) is False:
                    break
                if self.config.evaluation.stop_when_solved and row.get("solved"):
                    break
        finally:
            if bar is not None:
                bar.close()
            if self._log is not None:
                self._log.close()
                self._log = None
        return self

    def _act(self, observation: Any, state: np.ndarray | None) -> tuple[np.ndarray, np.ndarray]:
        """Action of the MPC controller on the learned model (Algorithm 1, step (e)); ``state``
        is the warm-start plan ``[H, m]`` of the previous call (with
        ``AgentConfig.planner.replan_every > 1`` a :class:`ReplanEvery` state: one more row
        counts the steps since the plan), ``None`` a cold full-horizon plan. Exploration noise
        is only added in :meth:`learn`."""
        return self.actor.predict(observation, state)

    def save(self, path: str | Path) -> Path:
        """Save everything needed to continue learning or to act (one atomic file)."""
        path = Path(path)
        save_checkpoint(path, self._payload())
        return path

    @classmethod
    def load(
        cls,
        path: str | Path,
        env: gym.Env | None = None,
        cost_fn: CostFn | None = None,
        state_fn: Callable | None = None,
        obs_fn: CostFn | None = None,
        *,
        run_dir: str | None = None,
        terminal_cost_fn: Callable[[Any], Any] | None = None,
        termination_fn: Callable[[np.ndarray], np.ndarray] | None = None,
    ) -> JacPropAgent:
        """Restore an agent saved by :meth:`save` (or a run's ``checkpoint.pt``).

        :param path: the file (or a run folder holding ``checkpoint.pt``).
        :param env: the env to continue learning in (``None``: act only, via :meth:`predict`).
            Its spaces must match the saved ones.
        :param cost_fn: needed again if the agent was built with a custom ``cost_fn``
            (functions are not serialised; the built-in env cost is).
        :param state_fn: with ``obs_fn``, needed again if the agent was built with them.
        :param run_dir: where :meth:`learn` writes from now on (default: the saved config's).
        :param terminal_cost_fn: / ``termination_fn``: as at construction (not serialised).
        """
        path = Path(path)
        if path.is_dir():
            path = path / "checkpoint.pt"
        payload = load_checkpoint(path)
        cfg = json.loads(payload["agent_config"])
        if run_dir is not None:
            cfg["run_dir"] = str(run_dir)
        config = AgentConfig.from_dict(cfg)
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
        if env is not None and payload.get("env_fingerprint"):
            check_same(json.loads(payload["env_fingerprint"]), env_fingerprint(env),
                       what="env", path=path)
        task = json.loads(payload["task"])
        saved_n = json.loads(payload["ensemble_config"])["state_dim"]
        if task.get("state_map") is None and state_fn is None:
            raise ValueError(
                f"the agent was saved with a custom state_fn/obs_fn (model state of dimension "
                f"{saved_n}); functions are not saved: pass the same state_fn= and obs_fn= to "
                "load (with the task's other functions: for a task of agents.tasks, "
                "JacPropAgent.load(path, env, **task.agent_kwargs()))"
            )
        if task.get("cost") is None and cost_fn is None and (
            env is None or default_task_for_env(env) is None
        ):
            raise ValueError("the agent was built with a custom cost_fn: pass cost_fn= to load")
        agent = cls.__new__(cls)
        agent._setup(env, config, spec, cost_fn, state_fn, obs_fn, saved_task=task,
                     terminal_cost_fn=terminal_cost_fn, termination_fn=termination_fn)
        if agent.state_dim != saved_n:
            raise ValueError(
                f"state_fn gives a model state of dimension {agent.state_dim}, but the saved "
                f"agent's model was trained on dimension {saved_n}: pass the state_fn/obs_fn it "
                "was built with"
            )
        agent._restore(payload)
        return agent

    # ------------------------------------------------------------------ one episode
    def _episode(self, max_steps: int | None = None) -> dict[str, Any]:
        cfg, spec = self.config, self.spec
        ep = self.episodes_done
        t_start = time.perf_counter()
        # every random draw of this episode derives from the agent's generator
        reset_seed, signal_seed, train_seed, torch_seed = (
            int(s) for s in self.rng.integers(0, 2**31 - 1, size=4)
        )
        # anything that draws from torch's global generator is reproducible per episode
        torch.manual_seed(torch_seed)
        excitation = ep < cfg.collection.n_excitation_episodes
        start, done_steps, elapsed = self._handover or (None, 0, None)  # continue_rollouts
        self._handover = None
        if start is not None and _elapsed_steps(self.env) != elapsed:
            warnings.warn("collection.continue_rollouts: the env was stepped or reset since the "
                          "last training rollout, so this one starts from a reset", stacklevel=3)
            start, done_steps = None, 0
        T = min(cfg.collection.rollout_steps or spec.episode_steps, spec.episode_steps - done_steps)
        if max_steps is not None:
            T = min(T, max_steps)
        render = cfg.video and cfg.run_dir is not None and ep % cfg.video_every == 0

        # (a) rollout in the real env --------------------------------------------------------
        if excitation:
            U_exc = self._excitation_signal(T, signal_seed)

            def act(obs: np.ndarray, t: int) -> np.ndarray:
                return U_exc[t]
        else:
            noise = self._exploration_noise(T, signal_seed)
            plan: dict[str, Any] = {"U": None}

            def act(obs: np.ndarray, t: int) -> np.ndarray:
                a, plan["U"] = self.explorer.predict(obs, plan["U"], episode_start=t == 0)
                return a + noise[t]

        rec = run_episode(self.env, act, seed=reset_seed, max_steps=T, render=render, start=start)
        time_rollout = time.perf_counter() - t_start - rec.time_policy
        traj = Trajectory(
            self.state_map.state(rec.obs), rec.actions, spec.dt,
            meta={"episode": ep, "seed": None if start is not None else reset_seed},
        )
        if (cfg.collection.continue_rollouts and not (rec.terminated or rec.truncated)
                and done_steps + rec.T < spec.episode_steps):
            self._handover = ((rec.obs[-1].copy(), dict(rec.info)), done_steps + rec.T,
                              _elapsed_steps(self.env))
        self.env_steps += traj.T
        if render:
            self._save_video(rec.frames, ep)

        # model quality on the NEW data, before the update (generalisation) -------------------
        one_step, jac = self._model_errors(traj)

        # (b) LTV model of the new trajectory ------------------------------------------------
        tic = time.perf_counter()
        lam = math.nan
        ltv_note = ""
        if cfg.regularization.needs_ltv:
            ltv, lam, ltv_note = self._ltv_for(traj)
            self.ltv_models.append(ltv)
        self.ltv_lambdas.append(lam)
        self.trajectories.append(traj)
        time_ltv = time.perf_counter() - tic

        # (c) + (d) regularised warm-started update on all data --------------------------------
        tic = time.perf_counter()
        history = self._train(train_seed)
        self._freeze()
        time_training = time.perf_counter() - tic

        # evaluation: the MPC policy on the updated model vs the oracle ------------------------
        tic = time.perf_counter()
        ev: dict[str, Any] = {"eval_cost": None, "eval_return": None, "eval_returns": None,
                              "oracle_cost": None, "cost_ratio": None, "eval_episodes_run": 0,
                              "solved": False}
        if self._should_evaluate(ep, steps=len(rec.actions)):
            ev = self._evaluate()
        time_oracle, self._oracle_seconds = self._oracle_seconds, 0.0
        time_eval = time.perf_counter() - tic - time_oracle

        return {
            "episode": ep,
            "phase": "excitation" if excitation else "mpc",
            "env_steps": self.env_steps,
            "episode_cost": rec.cost,
            "model_cost": float(np.sum(self.task_cost.on_observations(rec.obs[:-1], rec.actions))),
            "one_step_rms": one_step,
            "jacobian_error": jac,
            "train_loss": _last(getattr(history, "train_loss", None)),
            "val_loss": _last(getattr(history, "val_loss", None)),
            "train_steps": getattr(history, "steps", None),
            "ltv_lambda": lam,
            "ltv_fallback": ltv_note,
            **ev,
            "time_rollout": time_rollout,
            "time_planning": rec.time_policy,
            "time_ltv": time_ltv,
            "time_training": time_training,
            "time_eval": time_eval,
            "time_oracle": time_oracle,
            "time_total": time.perf_counter() - t_start,
        }

    def _exploration_noise(self, T: int, seed: int) -> np.ndarray:
        """``[T, m]`` noise added to the planned actions of a training rollout: Gaussian with
        std ``exploration_std`` x the half-range, white or a moving average of
        ``exploration_window`` steps (by its stationary std)."""
        from mbtsr import excitation

        col, spec = self.config.collection, self.spec
        half = 0.5 * (spec.u_max - spec.u_min)
        unit = excitation.unit_filtered_gaussian(T, spec.act_dim, window=col.exploration_window,
                                                 seed=seed)
        return col.exploration_std * half * unit

    def _excitation_signal(self, T: int, seed: int) -> np.ndarray:
        """``[T, m]`` excitation in env units: a unit-std signal (by its stationary std)
        scaled to ``excitation_scale`` x the half-range around the middle of the action box."""
        from mbtsr import excitation

        cfg, spec = self.config, self.spec
        if cfg.collection.excitation == "filtered_gaussian":
            sig = excitation.unit_filtered_gaussian(
                T, spec.act_dim, window=cfg.collection.excitation_window, seed=seed)
        else:
            sig = excitation.multisine(T, spec.act_dim, seed=seed) / excitation.multisine_std(
                5, 1.0
            )
        mid, half = 0.5 * (spec.u_max + spec.u_min), 0.5 * (spec.u_max - spec.u_min)
        return np.clip(mid + half * cfg.collection.excitation_scale * sig, spec.u_min, spec.u_max)

    def _ltv_for(self, traj: Trajectory) -> tuple[LTVModel, float, str]:
        """The LTV model ``l_i`` of a new trajectory, with documented fallbacks instead of an
        error when the data cannot support the fit (see ``docs/agent.md``, "LTV fallbacks"):

        1. ``regularization.ltv_lambda=None`` (automatic) needs more transitions than
           regressors (``T > n + m``); a shorter episode (early termination) reuses the median
           of the earlier selections, or the regressor scale for the very first episode.
        2. Regressors that do not span their space (observation coordinates that are constant
           within the episode, such as a goal position, or an unexcited input) make the
           smooth fit singular: it is repeated with a weak Gaussian prior on the first
           Jacobian (``fit_ltv(..., P0=...)``, 1e-6 of the data's scale), which fixes the
           unidentified directions at zero and leaves the identified ones unchanged.
        3. A trajectory of one transition has no smoothness to exploit: it is labelled by the
           model's own Jacobians once the model is trained, else by one time-invariant
           ridge least-squares fit pooled over all episodes so far.

        Every fallback is logged as a ``RuntimeWarning`` and in the episode's ``ltv_fallback``
        column. :return: ``(model, lam, note)`` (``note`` empty when nothing fell back).
        """
        notes: list[str] = []
        n, m = self.state_dim, self.spec.act_dim
        lam = math.nan
        ltv = None
        if traj.T >= 2:
            lam = self._ltv_lambda(traj, notes)
            # the fit's posterior covariance holds T n (n+m)^2 numbers: long episodes of
            # high-dimensional envs are fitted in consecutive segments that fit the memory
            # budget (smoothness is then not enforced across segment boundaries)
            seg = max(2, int(LTV_MEMORY_BUDGET // (8 * 4 * n * (n + m) ** 2)))
            bounds = list(range(0, traj.T, seg))
            if len(bounds) > 1 and traj.T - bounds[-1] < 2:
                bounds.pop()
            if len(bounds) > 1:
                notes.append(f"{len(bounds)} segments of <= {seg} steps (memory)")
            parts = []
            for a, b in zip(bounds, bounds[1:] + [traj.T]):
                part = self._fit_segment(
                    Trajectory(traj.x[a : b + 1], traj.u[a:b], traj.dt), lam, notes)
                if part is None:
                    parts = None
                    break
                parts.append(part)
            if parts is not None:
                ltv = _light_ltv(np.concatenate([p_[0] for p_ in parts]),
                                 np.concatenate([p_[1] for p_ in parts]), lam)
        if ltv is None:
            if self.model.is_normalized:
                x, u = traj.inputs
                A, B = self.model.member_jacobians(x, u)
                ltv = _light_ltv(A.mean(0), B.mean(0), lam)
                notes.append(f"episode of {traj.T} transition(s): labelled by the model's "
                             "Jacobians")
            else:
                ltv = _pooled_linear_fit(self.trajectories + [traj], traj.T, n, m)
                notes.append(f"episode of {traj.T} transition(s): time-invariant least-squares "
                             "fit pooled over all episodes")
        return self._warn_fallback(ltv, lam, list(dict.fromkeys(notes)))

    def _fit_segment(
        self, traj: Trajectory, lam: float, notes: list[str]
    ) -> tuple[np.ndarray, np.ndarray] | None:
        """``(A [T, n, n], B [T, n, m])`` of the smooth LTV fit of ``traj`` (weak prior on the
        first Jacobian if the regressors are degenerate), fused with the model's Jacobians
        (``AgentConfig.ltv_prior``); ``None`` if even the weak prior cannot make it solvable."""
        n = self.state_dim
        try:
            ltv = fit_ltv(traj, lam)
        except ValueError:
            x, u = traj.inputs
            phi = np.concatenate([x, u], axis=1)
            scale = float(np.mean(np.sum(phi**2, axis=1))) * traj.T + lam**2 + 1e-12
            try:
                ltv = fit_ltv(traj, lam, P0=1.0 / (1e-6 * scale))
            except ValueError:
                return None
            notes.append("degenerate regressors (constant or unexcited observation/action "
                         "dimensions): weak prior on the first Jacobian")
        q = n + self.spec.act_dim
        if self.config.ltv_prior > 0 and self.model.is_normalized and n * q**3 > 1e7:
            notes.append("model prior (ltv_prior) skipped: n (n+m)^3 too large for the fusion")
        elif self.config.ltv_prior > 0 and self.model.is_normalized:
            x, u = traj.inputs
            A, B = self.model.member_jacobians(x, u)  # [K, T, n, n], [K, T, n, m]
            J = np.concatenate([A, B], axis=-1)
            mean, var = J.mean(0), J.var(0) + self.config.ltv_prior
            ltv = fuse_prior(ltv, mean[..., :n], mean[..., n:], var)
        return np.asarray(ltv.A), np.asarray(ltv.B)

    def _warn_fallback(
        self, ltv: LTVModel, lam: float, notes: list[str]
    ) -> tuple[LTVModel, float, str]:
        note = "; ".join(notes)
        if note:
            warnings.warn(
                f"episode {self.episodes_done}: LTV fit fallback: {note}", RuntimeWarning,
                stacklevel=3,
            )
        return ltv, lam, note

    def _ltv_lambda(self, traj: Trajectory, notes: list[str] | None = None) -> float:
        """``AgentConfig.regularization.ltv_lambda``, or its automatic choice (see
        :meth:`_ltv_for`)."""
        if self.config.regularization.ltv_lambda is not None:
            return float(self.config.regularization.ltv_lambda)
        # constant state coordinates (a goal in the observation) carry no information on the
        # smoothness and make the criterion singular: select on the varying ones
        varying = np.ptp(traj.x, axis=0) > 1e-9 * (1.0 + np.abs(traj.x).max(axis=0))
        sub = traj if varying.all() or not varying.any() else Trajectory(
            traj.x[:, varying], traj.u, traj.dt)
        try:
            with warnings.catch_warnings():
                warnings.simplefilter("ignore", RuntimeWarning)  # a boundary optimum is fine
                lam, _ = select_lambda(sub)
            return float(lam)
        except ValueError as err:
            reason = ("too few transitions" if "more measurements" in str(err)
                      else "degenerate regressors")
            earlier = [v for v in self.ltv_lambdas if math.isfinite(v)]
            if earlier:
                lam = float(np.median(earlier))
                what = "the median of the earlier selections"
            else:
                x, u = traj.inputs
                phi = np.concatenate([x, u], axis=1)
                lam = float(np.sqrt(np.mean(np.sum(phi**2, axis=1)) / phi.shape[1])) or 1.0
                what = "the regressor scale"
            if notes is not None:
                notes.append(f"ltv_lambda='auto' cannot be selected ({reason}, {traj.T} "
                             f"transitions): using {what} ({lam:.3g})")
            return lam

    def _train(self, train_seed: int):
        from mbtsr.training import train_ensemble

        tcfg, reg = self._train_configs(train_seed)
        if self.config.renormalize:
            self.model.refit_normalization(self.trajectories)
        history = train_ensemble(
            self.model,
            self.trajectories,
            tcfg,
            reg,
            ltv_models=self.ltv_models if self.ltv_models else None,
            optimizer_state=self.optimizer_state,
        )
        self.optimizer_state = history.optimizer_state
        return history

    def _train_configs(self, train_seed: int = 0):
        """The :class:`~mbtsr.training.TrainConfig` (its seed drives batch order and the
        perturbation draws) and :class:`~mbtsr.training.RegularizationConfig` of an update."""
        cfg = self.config
        return dataclasses.replace(cfg.training, seed=train_seed), cfg.regularization

    def _model_errors(self, traj: Trajectory) -> tuple[float, float]:
        """One-step RMS of the ensemble mean on the new trajectory and the paper's Jacobian
        error (eq. jacerr) against ``env.unwrapped.linearize_trajectory`` (NaN before the model
        has seen data, or without ``linearize``)."""
        from mbtsr.metrics import jacobian_error, prediction_rms

        if not self.model.is_normalized:
            return math.nan, math.nan
        one_step = float(prediction_rms(self.model, traj))
        jac = math.nan
        if self.config.jacobian_error and self.has_linearize:
            x, u = traj.inputs
            true = self.env.unwrapped
            if hasattr(true, "linearize_trajectory"):
                J_true = true.linearize_trajectory(x, u)
            else:
                pairs = [true.linearize(xt, ut) for xt, ut in zip(x, u)]
                J_true = (np.stack([p[0] for p in pairs]), np.stack([p[1] for p in pairs]))
            jac = float(jacobian_error(J_true, self.model.jacobians(x, u)))
        return one_step, jac

    # ------------------------------------------------------------------ evaluation
    def _should_evaluate(self, ep: int, last: bool = False, steps: int = 0) -> bool:
        """Every ``evaluation.every``-th episode from the last excitation episode on, every
        episode that crossed a multiple of ``evaluation.every_steps`` env steps (its ``steps``
        env steps ended at ``self.env_steps``), and the last episode of every :meth:`learn`
        call (the final score)."""
        ev, first = self.config.evaluation, self.config.collection.n_excitation_episodes - 1
        if (ev.every == 0 and ev.every_steps == 0) or ep < first:
            return False
        k = ev.every_steps
        return (last or (ev.every > 0 and (ep - first) % ev.every == 0)
                or (k > 0 and self.env_steps // k > (self.env_steps - steps) // k))

    def _eval_env_instance(self) -> gym.Env:
        if self._eval_env is None:
            spec = getattr(self.env, "spec", None)
            if spec is None:
                raise ValueError("evaluation needs an env made by gym.make (env.spec is None)")
            self._eval_env = gym.make(spec)
        return self._eval_env

    def evaluation_problem(self, i: int) -> tuple[np.ndarray | None, int]:
        """``(target or None, reset seed)`` of evaluation episode ``i``."""
        self._ensure_eval_targets()
        target = None if self.eval_targets is None else self.eval_targets[i]
        return target, self.config.evaluation.seed + i

    def _ensure_eval_targets(self) -> None:
        if self.eval_targets is not None:
            return
        env = self._eval_env_instance()
        _, info = env.reset(seed=self.config.evaluation.seed)
        if "target" in info:
            self.eval_targets = evaluation_targets(
                self.config.evaluation.episodes, self.config.evaluation.seed, env
            )

    def _evaluate(self) -> dict[str, Any]:
        """Evaluate :meth:`predict` on the fixed evaluation episodes.

        :return: the log fields ``eval_cost`` (mean cost, ``None`` if stopped early),
            ``eval_return`` (mean return) and ``eval_returns`` (per episode), ``oracle_cost``,
            ``cost_ratio`` (``sum(agent) / sum(oracle)`` over the oracle's episodes, a lower
            bound when the evaluation stopped early), ``eval_episodes_run`` and ``solved``.
        """
        cfg = self.config
        env, kwargs = self._eval_setup()
        ev = cfg.evaluation
        oracle = None if ev.solved_return is not None else self._oracle_costs(env, kwargs)
        stop_above = None
        if oracle is not None and cfg.evaluation.early_exit and np.all(oracle >= 0):
            stop_above = cfg.evaluation.solved_ratio * float(np.sum(oracle))
        costs = evaluate_policy_costs(
            self, env, self.eval_targets, cfg.evaluation.seed, stop_above=stop_above, **kwargs
        )
        complete = len(costs) == cfg.evaluation.episodes
        returns = [float(-c) for c in costs]
        out: dict[str, Any] = {
            "eval_cost": float(np.mean(costs)) if complete else None,
            "eval_return": float(np.mean(returns)) if complete else None,
            "eval_returns": returns,
            "oracle_cost": None,
            "cost_ratio": None,
            "eval_episodes_run": len(costs),
            "solved": False,
        }
        if cfg.evaluation.solved_return is not None:
            out["solved"] = bool(complete and out["eval_return"] >= cfg.evaluation.solved_return)
            return out
        if oracle is None:
            return out
        total = float(np.sum(oracle))
        ratio = float(np.sum(costs)) / total if total > 0 else math.inf
        out.update(oracle_cost=float(np.mean(oracle)), cost_ratio=ratio,
                   solved=bool(complete and ratio <= cfg.evaluation.solved_ratio))
        return out

    def oracle_policy(self, env: gym.Env) -> Any:
        """The oracle's controller on ``env``: this agent's planner (kind, horizon, iterations,
        terminal weight, ``replan_every``, seeded from ``config.seed``) and task functions on the
        TRUE model of ``env`` (:func:`agents.evaluation.oracle_policy`; CEM's particles set to 1,
        since one true model would repeat the same rollout). SB3-style ``predict``."""
        cfg = self.config
        optimizer, options, iterations = cfg.planner.optimizer(cfg.seed)
        if getattr(options, "particles", 1) > 1:
            options = dataclasses.replace(options, particles=1)
        return ReplanEvery(oracle_policy(
            env,
            cfg.planner.horizon,
            iterations=iterations,
            optimizer=optimizer,
            optimizer_options=options,
            first_plan_iterations=cfg.planner.first_plan_iterations,
            terminal_weight=cfg.planner.terminal_weight,
            cost_fn=self.cost_fn,
            state_map=self.state_map,
            terminal_cost_fn=self.terminal_cost_fn,
            termination_fn=self.termination_fn,
        ), cfg.planner.replan_every, cfg.planner.replan_feedback)

    def _oracle_costs(self, env: gym.Env, kwargs: dict[str, Any]) -> np.ndarray | None:
        """Per-episode costs of MPC with the TRUE model (computed once, then kept)."""
        if self.oracle_costs is not None or not has_true_model(env):
            return self.oracle_costs  # None: no true model (not MuJoCo, no dynamics_model())
        cfg = self.config

        def compute() -> np.ndarray:
            tic = time.perf_counter()
            try:
                return evaluate_policy_costs(self.oracle_policy(env), env, self.eval_targets,
                                             cfg.evaluation.seed, **kwargs)
            finally:
                self._oracle_seconds += time.perf_counter() - tic

        key: dict[str, Any] = {}
        cache_dir = cfg.evaluation.oracle_cache_dir
        if not (isinstance(self.cost_fn, QuadraticTargetCost) and self.state_map.serializable
                and self.terminal_cost_fn is None and self.termination_fn is None
                and _is_mujoco_env(env)):
            cache_dir = None  # user functions (or non-MuJoCo physics) cannot be part of a key
        if cache_dir is not None:
            key = oracle_cache_key(
                env, {"cost": self.cost_fn.to_dict(), "state_map": self.state_map.to_dict()},
                self.eval_targets, cfg.evaluation.seed, n_episodes=cfg.evaluation.episodes,
                episode_steps=self.spec.episode_steps,
                planner={**dataclasses.asdict(cfg.planner), "seed": cfg.seed},
            )
        self.oracle_costs = cached_costs(cache_dir, key, compute)
        return self.oracle_costs

    def compute_oracle(self) -> float | None:
        """Compute (or fetch from ``oracle_cache_dir``) the oracle's evaluation costs now;
        return their mean (``None`` if the env offers no true model)."""
        env, kwargs = self._eval_setup()
        pending = self._oracle_seconds
        self._oracle_costs(env, kwargs)
        self._oracle_seconds = pending  # computed outside learn: no episode's time_oracle
        return self.oracle_mean

    def _eval_setup(self) -> tuple[gym.Env, dict[str, Any]]:
        env = self._eval_env_instance()
        self._ensure_eval_targets()
        kwargs: dict[str, Any] = {"max_steps": self.spec.episode_steps}
        if self.eval_targets is None:
            kwargs["n_episodes"] = self.config.evaluation.episodes
        return env, kwargs

    @property
    def oracle_mean(self) -> float | None:
        return None if self.oracle_costs is None else float(np.mean(self.oracle_costs))

    def rollout_policy(
        self, env: gym.Env | None = None, *, seed: int = 0, options: dict | None = None
    ) -> EpisodeRecord:
        """One episode of :meth:`predict` (no exploration noise) in ``env``."""
        env = self.env if env is None else env
        if env is self.env:
            self._handover = None  # the next training rollout cannot continue this env's episode
        plan: dict[str, Any] = {"U": None}

        def act(obs: np.ndarray, t: int) -> np.ndarray:
            a, plan["U"] = self.predict(obs, plan["U"], episode_start=t == 0)
            return a

        return run_episode(env, act, seed=seed, options=options, max_steps=self.spec.episode_steps)

    def summary(self) -> dict[str, Any]:
        """Benchmark numbers of the run so far: episodes/env steps to the first solved
        evaluation, the last cost ratio to the oracle, wall seconds per phase."""
        rows = self.logger_rows
        solved = [r for r in rows if r.get("solved")]
        evals = [r for r in rows if r.get("cost_ratio") is not None]
        rets = [r for r in rows if r.get("eval_return") is not None]
        phases = {c[len("time_"):]: float(sum(r.get(c, 0.0) for r in rows))
                  for c in TIMING_COLUMNS}
        return {
            "env_id": self.env_id,
            "episodes_done": self.episodes_done,
            "env_steps": self.env_steps,
            "episodes_to_solve": solved[0]["episode"] + 1 if solved else None,
            "env_steps_to_solve": solved[0]["env_steps"] if solved else None,
            "final_cost_ratio": evals[-1]["cost_ratio"] if evals else None,
            "best_cost_ratio": min(r["cost_ratio"] for r in evals) if evals else None,
            "final_eval_cost": evals[-1]["eval_cost"] if evals else None,
            "final_eval_return": rets[-1]["eval_return"] if rets else None,
            "final_eval_returns": rets[-1]["eval_returns"] if rets else None,
            "best_eval_return": max(r["eval_return"] for r in rets) if rets else None,
            "eval_curve": [
                {"episode": r["episode"], "env_steps": r["env_steps"],
                 "eval_return": r.get("eval_return"), "eval_returns": r.get("eval_returns"),
                 "cost_ratio": r.get("cost_ratio")}
                for r in rows if r.get("eval_returns") is not None
            ],
            "solved_return": self.config.evaluation.solved_return,
            "solved_criterion": (
                "mean_return" if self.config.evaluation.solved_return is not None
                else "oracle_ratio" if self.oracle_costs is not None else None),
            "oracle_cost": self.oracle_mean,
            "solved_ratio": self.config.evaluation.solved_ratio,
            "wall_seconds_per_phase": phases,
            "eval_fraction_of_wall": (
                phases["eval"] / phases["total"] if phases.get("total") else None),
            "config": self.config.to_dict(),
        }

    def resolved_config(self) -> dict[str, Any]:
        """The agent config tree and what it resolves to with the env (for ``config.json``):
        the ensemble's :class:`~mbtsr.ensemble.EnsembleConfig` and the env spec."""
        return {
            "agent": self.config.to_dict(),
            "ensemble": json.loads(self.ensemble_config.to_json()),
            "env_spec": self.spec.to_dict(),
        }

    # ------------------------------------------------------------------ checkpointing
    def _payload(self) -> dict[str, Any]:
        task: dict[str, Any] = {"cost": None, "state_map": None}
        if isinstance(self.cost_fn, QuadraticTargetCost):
            task["cost"] = self.cost_fn.to_dict()
        if self.state_map.serializable:
            task["state_map"] = self.state_map.to_dict()
        return {
            "agent_config": json.dumps(self.config.to_dict()),
            "env_spec": json.dumps(self.spec.to_dict()),
            "env_fingerprint": None if self.env is None else json.dumps(env_fingerprint(self.env)),
            "task": json.dumps(task),
            "ensemble_config": self.ensemble_config.to_json(),
            "model_state": {k: v.detach().clone() for k, v in self.model.state_dict().items()},
            "optimizer_state": self.optimizer_state,
            "trajectories": [
                {"x": t.x, "u": t.u, "meta": json.dumps(t.meta)} for t in self.trajectories
            ],
            "ltv_lambdas": list(self.ltv_lambdas),
            # stored, not refitted: a fit fused with the model prior depends on the model of
            # its episode
            "ltv_models": [
                {"A": m.A, "B": m.B, "lam": m.lam}
                for m in self.ltv_models
            ],
            "episodes_done": self.episodes_done,
            "env_steps": self.env_steps,
            "rng": numpy_rng_state(self.rng),
            "torch_rng": torch.get_rng_state(),
            "log": json.dumps(self.logger_rows),
            "eval_targets": None if self.eval_targets is None else [
                np.asarray(t) for t in self.eval_targets
            ],
            "oracle_costs": None if self.oracle_costs is None else np.asarray(self.oracle_costs),
        }

    def _restore(self, p: dict[str, Any]) -> None:
        self.model.load_state_dict(p["model_state"])
        self._freeze()
        self.optimizer_state = p["optimizer_state"]
        self.trajectories = [
            Trajectory(d["x"].numpy(), d["u"].numpy(), self.spec.dt, meta=json.loads(d["meta"]))
            for d in p["trajectories"]
        ]
        self.ltv_lambdas = [float(v) for v in p["ltv_lambdas"]]
        self.ltv_models = [
            _light_ltv(d["A"].numpy(), d["B"].numpy(), float(d["lam"]))
            for d in p["ltv_models"]
        ]
        self.episodes_done = int(p["episodes_done"])
        self.env_steps = int(p["env_steps"])
        set_numpy_rng_state(self.rng, p["rng"])
        torch.set_rng_state(p["torch_rng"])
        self.logger_rows = json.loads(p["log"])
        self.eval_targets = None if p["eval_targets"] is None else [
            t.numpy() for t in p["eval_targets"]
        ]
        self.oracle_costs = None if p["oracle_costs"] is None else p["oracle_costs"].numpy()

    def _write_checkpoint(self) -> None:
        run_dir = Path(self.config.run_dir)
        run_dir.mkdir(parents=True, exist_ok=True)
        # the checkpoint is the source of truth; the exports below are conveniences
        self.save(run_dir / "checkpoint.pt")
        save_model(self.model, run_dir / "model.pt")  # atomic
        save_trajectories(run_dir / "data.npz", self.trajectories)
        atomic_write_text(run_dir / "summary.json", json.dumps(self.summary(), indent=2))

    def _save_video(self, frames: list, ep: int) -> None:
        """``videos/episode_<ep>.mp4`` (:func:`envs.rendering.save_video` writes a ``.gif``
        instead, with a warning, when no ffmpeg is available)."""
        if not frames:
            return
        from envs.rendering import save_video

        folder = Path(self.config.run_dir) / "videos"
        folder.mkdir(parents=True, exist_ok=True)
        fps = 1.0 / self.spec.dt if self.spec.dt else 30.0
        save_video(frames, folder / f"episode_{ep:04d}.mp4", fps=fps)


class ReplanEvery(SB3Predictor):
    """Feedback-limited MPC: each plan of ``policy`` is executed for ``k`` steps before the
    next solve (warm-started with the rest of the plan). ``k = 1`` is ``policy`` itself.

    Between solves the plan's controls ``U_t`` are played open loop or, with ``feedback``,
    through iLQR's local policy ``u_t = clip(U_t + K_t (x_t - X_t))``: ``x_t`` is the
    planner's start state for the observation (``policy.model_state``: the learned model's
    state, or the oracle's true state), ``X`` and ``K`` are the last solve's: ``K`` from its
    last backward pass, linearized about the trajectory before its final line search, ``X``
    the accepted trajectory. A solve without gains (CEM) or with a non-finite ``X`` or ``K``
    (a failed solve) plays open loop, and so does a correction that comes out non-finite
    (a model state far off the plan). The SB3 ``state`` is ``[H+1, m]``: the remaining plan and
    one row holding the number of steps since the last solve; with ``feedback`` each plan row
    also holds ``X_t`` and ``K_t`` (``[H+1, m + n + m n]``)."""

    def __init__(self, policy: Any, k: int, feedback: bool = False) -> None:
        self.policy, self.k, self.feedback = policy, int(k), bool(feedback)

    def _act(self, observation: Any, state: np.ndarray | None) -> tuple[np.ndarray, np.ndarray]:
        if self.k == 1:
            return self.policy.predict(observation, state)
        spec = self.policy.spec
        m = spec.act_dim
        plan, age = None, 0
        if state is not None:
            state = np.asarray(state, dtype=float)
            H = self.policy.mpc.horizon
            # with feedback the width m + n + m n is checked where n is known (a replay step)
            fits = state.ndim == 2 and state.shape[0] == H + 1 and (
                state.shape[1] > m if self.feedback else state.shape[1] == m)
            if not fits:
                raise ValueError(f"state must be the [H+1={H + 1}, "
                                 f"{'m + n + m n' if self.feedback else 'm'}] array (m={m}) the "
                                 f"previous call returned, got shape {list(state.shape)}")
            check_finite("state", state)
            plan, age = state[:-1], int(state[-1, 0])
        if plan is None or age >= self.k:
            action, rest = self.policy.predict(observation, None if plan is None else plan[:, :m])
            if self.feedback:
                rest = np.concatenate([rest, self._reference()], axis=1)
            age = 1
        else:
            u = plan[0, :m]
            obs = as_array("observation", observation, (spec.obs_dim,))
            if plan.shape[1] > m and np.any(plan[0, m:]):
                x = self.policy.model_state(obs)
                n = x.shape[0]
                if plan.shape[1] != m + n + m * n:
                    raise ValueError(f"state must hold n={n} model states and [{m}, {n}] gains "
                                     f"per row (width {m + n + m * n}), got width "
                                     f"{plan.shape[1]}")
                corrected = u + plan[0, m + n:].reshape(m, n) @ (x - plan[0, m:m + n])
                if np.all(np.isfinite(corrected)):
                    u = corrected
            action = np.clip(u, spec.u_min, spec.u_max)
            rest = np.concatenate([plan[1:], plan[-1:]], axis=0)
            age += 1
        return action, np.concatenate([rest, np.full((1, rest.shape[1]), float(age))], axis=0)

    def _reference(self) -> np.ndarray:
        """``[H, n + m n]``: the last solve's states ``X_t`` and gains ``K_t`` for the steps
        after the first, shifted as the plan (the last row repeated); zeros, which play open
        loop, when the solve has no gains (CEM) or its ``X`` or ``K`` is not finite."""
        res = self.policy.last_result
        X, K = np.asarray(res.X, dtype=float), getattr(res, "K", None)
        H = X.shape[0] - 1
        if K is not None:
            K = np.asarray(K, dtype=float).reshape(H, -1)
        if K is None or not (np.all(np.isfinite(X)) and np.all(np.isfinite(K))):
            return np.zeros((H, X.shape[1] * (1 + self.policy.spec.act_dim)))
        return np.concatenate([X[1:], np.concatenate([K[1:], K[-1:]], axis=0)], axis=1)


def _elapsed_steps(env: gym.Env | None) -> int | None:
    """The step count of ``env``'s ``TimeLimit`` since its last reset (``None`` without one)."""
    try:
        return int(env.get_wrapper_attr("_elapsed_steps"))
    except (AttributeError, TypeError, ValueError):
        return None


def _probe_observations(env: gym.Env | None, shape: tuple[int, ...]) -> np.ndarray:
    """Seeded test observations ``shape = [..., obs_dim]`` in ``[-1, 1]``, clipped to the
    env's observation space when there is an env."""
    probe = np.random.default_rng(0).uniform(-1.0, 1.0, shape)
    if env is not None:
        probe = np.clip(probe, env.observation_space.low, env.observation_space.high)
    return probe


def _checked_termination_fn(
    fn: Callable[[np.ndarray], np.ndarray] | None, env: gym.Env | None, spec: EnvSpec
) -> Callable[[np.ndarray], np.ndarray] | None:
    """Check ``termination_fn`` on a batch of observations ``[2, 3, obs_dim] -> bool [2, 3]``."""
    if fn is None:
        return None
    check_callable("termination_fn", fn, "obs -> bool")
    out = np.asarray(call_user_fn(
        fn, _probe_observations(env, (2, 3, spec.obs_dim)),
        failure=f"termination_fn must accept a batch of observations [..., "
        f"obs_dim={spec.obs_dim}]; it failed on [2, 3, {spec.obs_dim}]",
    ))
    if out.shape != (2, 3):
        raise ValueError(
            f"termination_fn(obs [..., obs_dim]) must return one bool per observation [...]; for "
            f"[2, 3, {spec.obs_dim}] it returned shape {list(out.shape)}")
    return fn


def _light_ltv(A: np.ndarray, B: np.ndarray, lam: float = math.nan) -> LTVModel:
    """An LTV model that keeps ``A``, ``B`` only (what the perturbed data need); its ``cov`` is
    a zero-memory view of zeros (the posterior covariance is used once, for the prior fusion,
    and would cost ``T n (n+m)^2`` numbers per episode to keep)."""
    T, n, m = B.shape
    cov = np.broadcast_to(np.zeros((), dtype=float), (T, n, n + m, n + m))
    return LTVModel(A, B, None, cov, lam=0.0 if not math.isfinite(lam) else lam)


def _pooled_linear_fit(trajs: list[Trajectory], T: int, n: int, m: int) -> LTVModel:
    """``x+ = A x + B u`` by ridge least squares over all transitions of ``trajs`` (ridge 1e-6 of
    the regressor scale), repeated over ``T`` steps, with the residual covariance."""
    phi = np.concatenate([np.concatenate([t.x[:-1], t.u], axis=1) for t in trajs])
    y = np.concatenate([t.x[1:] for t in trajs])
    G = phi.T @ phi
    ridge = 1e-6 * (np.trace(G) / G.shape[0] + 1e-12)
    H = G + ridge * np.eye(n + m)
    K = np.linalg.solve(H, phi.T @ y).T  # [n, n+m]
    return _light_ltv(
        np.broadcast_to(K[:, :n], (T, n, n)).copy(), np.broadcast_to(K[:, n:], (T, n, m)).copy()
    )


def _last(values: Any) -> float | None:
    if values is None:
        return None
    values = list(values)
    return float(values[-1]) if values else None


def _fmt(v: Any) -> str:
    return "-" if v is None else f"{float(v):.3g}"
