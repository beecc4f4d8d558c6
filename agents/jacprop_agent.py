"""The Algorithm-1 agent (Bagge Carlson, Johansson and Robertsson, arXiv:1806.09919): episodic
model learning with tangent-space regularization and MPC, behind Stable-Baselines3's surface
(``learn``, ``predict``, ``save``, ``load``). It only wires its parts (built by
:func:`agents.task_setup.build_agent`); docs/agent.md ("Public API", "The agent as parts",
"Checkpoints and exact resume").
"""

from __future__ import annotations

import functools
import json
import time
import warnings
from collections.abc import Callable
from pathlib import Path
from typing import Any, Literal

import gymnasium as gym
import numpy as np
import threadpoolctl
import torch
from stable_baselines3.common.logger import Logger

from agents.callbacks import Callbacks
from agents.checkpoint import agent_payload, load_agent, save_checkpoint
from agents.collection import save_video
from agents.config import AgentConfig
from agents.episode_log import EpisodeLog, check_budget, end_episode, make_progress_bar, summarize
from agents.evaluation import NOT_EVALUATED, EpisodeRecord, run_episode
from agents.model_training import model_errors
from agents.planning import SB3Predictor, make_policy, planner_cost
from agents.task_setup import LearnedTask, build_agent, build_parts
from agents.tasks import StateMap, angle_pairs, env_spec, gym_make

__all__ = ["JacPropAgent"]

CostFn = Callable[[Any, Any], Any]


def _part(path: str, doc: str) -> property:
    """A read-only property forwarding to ``self.<path>`` (the state of one of the parts)."""
    return property(lambda self: functools.reduce(getattr, path.split("."), self), doc=doc)


class JacPropAgent(SB3Predictor):
    """Model-based agent of the paper's Algorithm 1 (learned NN ensemble + iLQR MPC).

    :param env: a Gymnasium env (or its id, for ``gym.make``) with 1-D ``Box`` observation and
        action spaces, a bounded action space and a ``TimeLimit`` (or
        ``config.collection.episode_steps``).
    :param config: :class:`agents.config.AgentConfig`.
    :param cost_fn: stage cost ``cost_fn(obs, action) -> scalar`` written with CasADi
        operations. ``None``: the registry's task for the env's id, else the env's own cost,
        else a learned reward; ``"learned"``: a learned reward (docs/agent.md, "The cost").
    :param state_fn: ``obs -> model state`` (numpy); with ``obs_fn``.
    :param obs_fn: ``(state, obs_ref) -> obs`` (CasADi-compatible), the inverse map for the cost.
    :param terminal_cost_fn: ``obs -> scalar`` (CasADi) of a plan's last predicted observation.
    :param termination_fn: ``obs [..., obs_dim] -> bool [...]`` (numpy): where the env would
        terminate; the planner adds no cost after a predicted termination.
    :raises ValueError: at construction for non-Box spaces, an unbounded action space, a cost
        or maps that do not fit the env's dimensions, a bad config.
    """

    def __init__(
        self,
        env: gym.Env | str,
        config: AgentConfig | None = None,
        cost_fn: CostFn | Literal["learned"] | None = None,
        state_fn: Callable[[np.ndarray], np.ndarray] | None = None,
        obs_fn: CostFn | None = None,
        *,
        terminal_cost_fn: Callable[[Any], Any] | None = None,
        termination_fn: Callable[[np.ndarray], np.ndarray] | None = None,
    ) -> None:
        config = AgentConfig() if config is None else config
        if not isinstance(config, AgentConfig):
            raise TypeError(f"config must be an AgentConfig, got {type(config).__name__}")
        if isinstance(env, str):
            env = gym_make(env, **({"render_mode": "rgb_array"} if config.video else {}))
        spec = env_spec(env, config.collection.episode_steps)
        if (config.collection.rollout_steps or 0) >= spec.episode_steps:
            warnings.warn(f"collection.rollout_steps={config.collection.rollout_steps} has no "
                          f"effect: the episode is {spec.episode_steps} steps long",
                          stacklevel=2)
        if config.video and getattr(env, "render_mode", None) != "rgb_array":
            raise ValueError("config.video needs an env created with render_mode='rgb_array', got "
                             f"render_mode={getattr(env, 'render_mode', None)!r}")
        if config.checkpoint and config.run_dir is None:
            config = config.replace(checkpoint=False)
        build_agent(self, env, config, spec, {
            "cost_fn": cost_fn, "state_fn": state_fn, "obs_fn": obs_fn,
            "terminal_cost_fn": terminal_cost_fn, "termination_fn": termination_fn})

    def freeze(self) -> None:
        """A frozen numpy copy of the ensemble (after each update, construction, load) and the
        planners on it (:func:`agents.planning.make_policy`): ``actor`` (evaluation, ``predict``)
        and ``explorer`` (training rollouts, with ``collection.explore_weight``)."""
        cfg = self.config
        self.planning_model = self.model.freeze()
        model = self.planning_model
        if isinstance(self.task_cost, LearnedTask):  # the reward learned so far
            self.planner_cost = planner_cost(self.task_cost, cfg.planner.terminal_weight)
        if cfg.planner.propagation == "ts":
            model = self.planning_model.trajectory_sampling(seed=cfg.seed)
        common = {"seed": cfg.seed, "cost": self.planner_cost,
                  "termination_fn": self.termination_fn}
        self.actor = make_policy(cfg.planner, model, self.task_cost, **common)
        self.explorer = self.actor if cfg.collection.explore_weight <= 0 else make_policy(
            cfg.planner, model, self.task_cost, explore_weight=cfg.collection.explore_weight,
            explore_on=cfg.collection.explore_on, **common)

    # ------------------------------------------------------------------ the parts' state
    policy = _part("actor.policy", "The MPC policy that :meth:`predict` solves.")
    ltv_lambdas = _part("labeler.lambdas", "The LTV smoothness weight of each episode (NaN: none).")
    ltv_models = _part("labeler.models", "The JacProp labels (LTV models), one per episode.")
    optimizer_state = _part("trainer.optimizer_state", "Adam's state, carried between updates.")
    eval_targets = _part("evaluator.eval_targets", "The evaluation targets (``None``: none yet).")
    oracle_costs = _part("evaluator.oracle_costs", "The oracle's costs per episode (or None).")

    @property
    def oracle_mean(self) -> float | None:
        return None if self.oracle_costs is None else float(np.mean(self.oracle_costs))

    # ------------------------------------------------------------------ public surface
    def learn(
        self,
        total_timesteps: int | None = None,
        callback: Any = None,
        log_interval: int | None = None,
        *,
        progress_bar: bool | None = None,
        episodes: int | None = None,
    ) -> JacPropAgent:
        """Run Algorithm 1 for a budget of env steps (as SB3) or of episodes, logging and
        checkpointing after every episode.

        :param total_timesteps: env steps to run now (a loaded agent continues its count); the
            last episode is cut short (truncated) so that the budget is exact.
        :param callback: SB3 callbacks and/or functions of ``{"agent", "row"}`` called after
            every episode (:mod:`agents.callbacks`).
        :param log_interval: print SB3's table of the logged scalars every this many episodes
            (``None``: never; SB3's ``verbose=1`` tables).
        :param progress_bar: show a tqdm progress bar (``None``: ``config.progress``).
        :param episodes: a budget of episodes (with ``total_timesteps``: the first reached).
        :return: ``self``.
        """
        check_budget(total_timesteps, episodes, self.env, log_interval)
        callbacks = Callbacks(callback)
        if self.config.torch_threads:
            torch.set_num_threads(self.config.torch_threads)
            # numpy's BLAS too: the frozen model's small products on 2 BLAS threads on a busy
            # machine were measured 10x slower than on one
            threadpoolctl.threadpool_limits(self.config.torch_threads, user_api="blas")
        if self.config.run_dir is not None and self._log is None:
            if not self.logger_rows and (Path(self.config.run_dir) / "checkpoint.pt").exists():
                raise ValueError(f"run_dir {self.config.run_dir} holds another run's checkpoint: "
                                 "continue it with JacPropAgent.load(run_dir, env), or give "
                                 "another run_dir")
            self._log = EpisodeLog(
                self.config.run_dir, tensorboard=self.config.tensorboard, rows=self.logger_rows
            )
        self.collector.forget()  # the env may have been used since: a learn call starts anew
        step_end = None if total_timesteps is None else self.env_steps + int(total_timesteps)
        bar = make_progress_bar(episodes, total_timesteps,
                                self.config.progress if progress_bar is None else progress_bar)
        since = (self.env_steps, time.perf_counter())
        callbacks.start(self, total_timesteps)
        try:
            done = 0

            def last() -> bool:  # the budget is spent (asked after each rollout): final score
                return callbacks.stopped or (episodes is not None and done >= episodes) or (
                    step_end is not None and self.env_steps >= step_end)

            while not last():
                done += 1
                before = self.env_steps
                callbacks.rollout_start(self.episodes_done)
                row = self._episode(
                    max_steps=None if step_end is None else step_end - self.env_steps,
                    stop=callbacks.step_hook(self._count_step), last=last)
                end_episode(self, row, self._log, fps_since=since, bar=bar,
                            bar_step=1 if episodes is not None else self.env_steps - before,
                            log_interval=log_interval)
                if not callbacks.episode_end(self, row):
                    break
                if self.config.evaluation.stop_when_solved and row.get("solved"):
                    break
        finally:
            callbacks.end()
            if bar is not None:
                bar.close()
            if self._log is not None:
                self._log.close()
                self._log = None
        return self

    # ------------------------------------------------------------------ what SB3 callbacks read
    @property
    def num_timesteps(self) -> int:
        """Env steps so far, the current rollout's included (SB3's ``num_timesteps``)."""
        return self.env_steps + self._rollout_steps

    def _count_step(self) -> None:
        self._rollout_steps += 1

    def get_env(self) -> gym.Env | None:
        """The training env (SB3's ``get_env``; a plain Gymnasium env, not a ``VecEnv``)."""
        return self.env

    @property
    def logger(self) -> Logger:
        """An SB3 ``Logger`` for callbacks: their records go to TensorBoard at the episode's end."""
        if self._sb3_logger is None:
            self._sb3_logger = Logger(folder=None, output_formats=[])
        return self._sb3_logger

    def _act(self, observation: Any, state: Any) -> tuple[np.ndarray, Any]:
        """Action of the MPC controller on the learned model (Algorithm 1, step (e)); ``state``:
        the previous call's plan (``None``: a cold full-horizon plan)."""
        return self.actor.predict(observation, state)

    def _explore(self, action: np.ndarray) -> np.ndarray:
        """``predict(..., deterministic=False)``'s noise (docs/agent.md, ``predict``)."""
        spec = self.spec
        std = self.config.collection.exploration_std * 0.5 * (spec.u_max - spec.u_min)
        return np.clip(action + std * self.predict_rng.standard_normal(action.shape),
                       spec.u_min, spec.u_max)

    def save(self, path: str | Path) -> Path:
        """Save everything needed to continue learning or to act (one atomic file)."""
        return save_checkpoint(path, agent_payload(self))

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
        :param env: the env to continue learning in, of the same spaces (``None``: act only).
        :param cost_fn: / ``state_fn``, ``obs_fn``, ``terminal_cost_fn``, ``termination_fn``:
            the task's functions, which a checkpoint cannot hold (not needed for a registry task
            or the env's built-in cost; a missing one is named in a ``ValueError``).
        :param run_dir: where :meth:`learn` writes from now on (default: the saved config's).
        """
        return load_agent(cls, path, env, {
            "cost_fn": cost_fn, "state_fn": state_fn, "obs_fn": obs_fn,
            "terminal_cost_fn": terminal_cost_fn, "termination_fn": termination_fn},
            run_dir=run_dir)

    # ------------------------------------------------------------------ one episode
    def _episode(self, max_steps: int | None = None, stop: Callable | None = None,
                 last: Callable[[], bool] = lambda: False) -> dict[str, Any]:
        """One episode of Algorithm 1; returns its log row. ``last()`` (asked after the rollout):
        the last episode of ``learn``, whose evaluation is the final score (every episode)."""
        cfg, ep = self.config, self.episodes_done
        t_start = time.perf_counter()
        # every random draw of this episode derives from the agent's generator
        reset_seed, signal_seed, train_seed, torch_seed = (
            int(s) for s in self.rng.integers(0, 2**31 - 1, size=4)
        )
        # anything that draws from torch's global generator is reproducible per episode
        torch.manual_seed(torch_seed)
        excitation = ep < cfg.collection.n_excitation_episodes
        render = cfg.video and cfg.run_dir is not None and ep % cfg.video_every == 0

        # (a) rollout in the real env
        rec, traj = self.collector.rollout(
            None if excitation else self.explorer, episode=ep, reset_seed=reset_seed,
            signal_seed=signal_seed, max_steps=max_steps, render=render, stop=stop)
        time_rollout = time.perf_counter() - t_start - rec.time_policy
        self.env_steps += traj.T
        self._rollout_steps = 0
        if render:
            save_video(rec.frames, cfg.run_dir, ep, self.spec.dt)
        if ep == 0 and rec.terminated and self.state_map.identity and (
                pairs := angle_pairs(rec.obs)):
            build_parts(self, StateMap(angles=pairs))  # angles in the model state (docs/agent.md)
            traj = type(traj)(self.state_map.state(rec.obs), traj.u, traj.dt, meta=traj.meta)
        # model quality on the NEW data, before the update (generalisation)
        one_step, jac = model_errors(self.model, traj,
                                     self.env.unwrapped if cfg.jacobian_error else None)

        # (b) the JacProp labels: an LTV model of the new trajectory
        tic = time.perf_counter()
        lam, ltv_note = self.labeler.add(traj, self.model, self.trajectories, ep)
        traj.meta["rewards"] = np.asarray(rec.rewards, dtype=float).tolist()  # r_t of (x_t, u_t)
        self.trajectories.append(traj)
        time_ltv = time.perf_counter() - tic

        # (c) + (d) regularised warm-started update on all data, then (e) a new planner
        tic = time.perf_counter()
        history = self.trainer.train(self.trajectories, self.labeler.models, train_seed)
        if isinstance(self.task_cost, LearnedTask):  # the reward, warm-started on all data
            self.task_cost.fit(self.trajectories)
        self.freeze()
        time_training = time.perf_counter() - tic

        # evaluation: the MPC policy on the updated model vs the oracle
        tic = time.perf_counter()
        ev, final = NOT_EVALUATED, last()
        if self.evaluator.due(ep, self.env_steps, steps=len(rec.actions), last=final):
            ev = self.evaluator.evaluate(self, complete=final)
        time_oracle = self.evaluator.take_oracle_seconds()
        time_eval = time.perf_counter() - tic - time_oracle
        return {
            "episode": ep,
            "phase": "excitation" if excitation else "mpc",
            "env_steps": self.env_steps,
            "episode_cost": rec.cost,
            "model_cost": float(np.sum(self.task_cost.on_observations(rec.obs[:-1], rec.actions))),
            "one_step_rms": one_step,
            "jacobian_error": jac,
            "train_loss": _last(history.train_loss),
            "val_loss": _last(history.val_loss),
            "train_steps": history.steps,
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

    # ------------------------------------------------------------------ evaluation
    def compute_oracle(self) -> float | None:
        """Compute (or fetch from ``oracle_cache_dir``) the oracle's evaluation costs now;
        return their mean (``None`` if the env offers no true model)."""
        return self.evaluator.compute_oracle()

    def rollout_policy(
        self, env: gym.Env | None = None, *, seed: int = 0, options: dict | None = None
    ) -> EpisodeRecord:
        """One episode of :meth:`predict` (no exploration noise) in ``env``."""
        env = self.env if env is None else env
        if env is self.env:
            self.collector.forget()  # the next training rollout cannot continue this episode
        return run_episode(env, self, seed=seed, options=options,
                           max_steps=self.spec.episode_steps)

    def summary(self) -> dict[str, Any]:
        """Benchmark numbers of the run so far (:func:`agents.episode_log.summarize`)."""
        return summarize(self.logger_rows, self.config, env_id=self.env_id,
                         episodes_done=self.episodes_done, env_steps=self.env_steps,
                         oracle_cost=self.oracle_mean)

    def resolved_config(self) -> dict[str, Any]:
        """The agent config tree and what it resolves to with the env (for ``config.json``):
        the ensemble's :class:`~mbtsr.ensemble.EnsembleConfig` and the env spec."""
        return {
            "agent": self.config.to_dict(),
            "ensemble": json.loads(self.ensemble_config.to_json()),
            "env_spec": self.spec.to_dict(),
        }


def _last(values: Any) -> float | None:
    return float(values[-1]) if len(values) else None
