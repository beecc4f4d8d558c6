"""Per-episode log of the agent: rows in memory, ``episodes.csv`` rewritten atomically after every
episode, TensorBoard scalars under Stable-Baselines3's tags by env step (events of episodes lost
to a crash purged); docs/agent.md, "What a run writes".
"""

from __future__ import annotations

import csv
import io
import math
import sys
import time
from collections.abc import Iterable, Sequence
from pathlib import Path
from typing import Any

import numpy as np
from stable_baselines3.common.logger import HumanOutputFormat

from agents.checkpoint import atomic_write_text, write_run
from mbtsr.validation import check_int

__all__ = ["EpisodeLog", "LOG_COLUMNS", "TIMING_COLUMNS", "check_budget", "end_episode",
           "make_progress_bar", "sb3_scalars", "summarize"]

#: columns of the per-episode CSV, in order
LOG_COLUMNS: tuple[str, ...] = (
    "episode",
    "phase",
    "env_steps",
    "episode_cost",
    "model_cost",
    "one_step_rms",
    "jacobian_error",
    "eval_episodes_run",
    "train_loss",
    "val_loss",
    "train_steps",
    "ltv_lambda",
    "ltv_fallback",
    "eval_cost",
    "eval_return",
    "eval_returns",
    "oracle_cost",
    "cost_ratio",
    "solved",
    "time_rollout",
    "time_planning",
    "time_ltv",
    "time_training",
    "time_eval",
    "time_oracle",
    "time_total",
)

#: columns that are wall-clock times (they differ between otherwise identical runs)
TIMING_COLUMNS: tuple[str, ...] = tuple(c for c in LOG_COLUMNS if c.startswith("time_"))


class EpisodeLog:
    """Rows of per-episode scalars, mirrored to ``<run_dir>/episodes.csv`` and TensorBoard.

    :param run_dir: folder for ``episodes.csv`` and ``tb/``.
    :param tensorboard: write TensorBoard scalars under ``<run_dir>/tb``.
    :param rows: rows restored from a checkpoint (a resumed run).
    """

    def __init__(
        self,
        run_dir: str | Path,
        *,
        tensorboard: bool = False,
        rows: Iterable[dict[str, Any]] = (),
    ) -> None:
        self.run_dir = Path(run_dir)
        self.rows: list[dict[str, Any]] = [dict(r) for r in rows]
        self._writer = None
        self.run_dir.mkdir(parents=True, exist_ok=True)
        self._write_csv()
        if tensorboard:
            from torch.utils.tensorboard import SummaryWriter

            # events at env steps >= purge_step (episodes lost to a crash) are discarded
            done = int(self.rows[-1]["env_steps"]) if self.rows else 0
            self._writer = SummaryWriter(log_dir=str(self.run_dir / "tb"), purge_step=done + 1)

    def append(self, row: dict[str, Any], extra: dict[str, float] | None = None) -> None:
        """Add one episode's row (keys from :data:`LOG_COLUMNS`) and write it out; TensorBoard
        gets :func:`sb3_scalars` of the rows and ``extra`` (more ``tag: value`` pairs, e.g. what
        SB3 callbacks recorded) at the row's env step."""
        unknown = sorted(set(row) - set(LOG_COLUMNS))
        if unknown:
            raise ValueError(f"unknown log column(s): {unknown}")
        self.rows.append(dict(row))
        self._write_csv()
        if self._writer is not None:
            step = int(row["env_steps"])
            for tag, value in {**sb3_scalars(self.rows), **(extra or {})}.items():
                if isinstance(value, int | float) and math.isfinite(float(value)):
                    self._writer.add_scalar(tag, float(value), global_step=step)
            self._writer.flush()

    def _write_csv(self) -> None:
        atomic_write_text(self.run_dir / "episodes.csv", rows_to_csv(self.rows, LOG_COLUMNS))

    def close(self) -> None:
        if self._writer is not None:
            self._writer.close()
            self._writer = None


#: TensorBoard groups of the row's columns under Stable-Baselines3's names (``time/...`` for the
#: timing columns)
_TRAIN = ("train_loss", "val_loss", "train_steps", "one_step_rms", "jacobian_error",
          "ltv_lambda", "model_cost")
_EVAL = ("eval_cost", "oracle_cost", "cost_ratio", "eval_episodes_run")


def sb3_scalars(rows: Sequence[dict[str, Any]], window: int = 100) -> dict[str, Any]:
    """The scalars of the last row under Stable-Baselines3's tags, so that the agent's curves
    and an SB3 run's overlay in TensorBoard by env step (``rollout/ep_rew_mean`` over the last
    ``window`` episodes, ``eval/mean_reward``, ``train/<column>``, ``time/<column>``, ...).

    :param rows: the log rows so far (``[episodes]``; the last one is reported).
    """
    last, recent = rows[-1], rows[-window:]
    first = len(rows) - len(recent)
    starts = [rows[first - 1]["env_steps"] if first else 0] + [r["env_steps"] for r in recent]
    out = {
        "rollout/ep_rew_mean": -float(np.mean([r["episode_cost"] for r in recent])),
        "rollout/ep_len_mean": float(np.mean(np.diff(starts))),
        "rollout/episodes": len(rows),
        "time/total_timesteps": last["env_steps"],
        "eval/mean_reward": last.get("eval_return"),
        **{f"train/{k}": last.get(k) for k in _TRAIN},
        **{f"eval/{k}": last.get(k) for k in _EVAL if last.get("eval_episodes_run")},
        **{f"time/{k}": last.get(k) for k in TIMING_COLUMNS},
    }
    return {k: v for k, v in out.items() if v is not None}


def summarize(rows: Sequence[dict[str, Any]], config: Any, *, env_id: str | None,
              episodes_done: int, env_steps: int, oracle_cost: float | None) -> dict[str, Any]:
    """Benchmark numbers of a run from its rows (docs/agent.md, the ``summary()`` row).

    :param config: the run's :class:`agents.config.AgentConfig` (its ``evaluation`` criteria).
    :param oracle_cost: the oracle's mean evaluation cost (``None``: no oracle).
    """
    ev = config.evaluation
    solved = [r for r in rows if r.get("solved")]
    evals = [r for r in rows if r.get("cost_ratio") is not None]
    rets = [r for r in rows if r.get("eval_return") is not None]
    phases = {c[len("time_"):]: float(sum(r.get(c, 0.0) for r in rows)) for c in TIMING_COLUMNS}
    return {
        "env_id": env_id,
        "episodes_done": episodes_done,
        "env_steps": env_steps,
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
        "solved_return": ev.solved_return,
        "solved_criterion": ("mean_return" if ev.solved_return is not None
                             else "oracle_ratio" if oracle_cost is not None else None),
        "oracle_cost": oracle_cost,
        "solved_ratio": ev.solved_ratio,
        "wall_seconds_per_phase": phases,
        "eval_fraction_of_wall": phases["eval"] / phases["total"] if phases.get("total") else None,
        "config": config.to_dict(),
    }


def rows_to_csv(rows: Sequence[dict[str, Any]], columns: Sequence[str]) -> str:
    """CSV text with a header; floats written with ``repr`` so they round-trip exactly."""
    buf = io.StringIO()
    w = csv.writer(buf, lineterminator="\n")
    w.writerow(columns)
    for r in rows:
        w.writerow([_fmt(r.get(c)) for c in columns])
    return buf.getvalue()


def _fmt(v: Any) -> str:
    if v is None:
        return ""
    if isinstance(v, bool):
        return str(int(v))
    if isinstance(v, float):
        return repr(v)
    return str(v)


# ---------------------------------------------------------------------- JacPropAgent.learn's loop
def check_budget(total_timesteps: Any, episodes: Any, env: Any, log_interval: Any) -> None:
    """Check :meth:`agents.jacprop_agent.JacPropAgent.learn`'s budget, log interval and env.

    :raises ValueError: a budget that is not an integer >= 0, no budget at all, a log interval
        that is not an integer >= 1, or no env (an act-only loaded agent)."""
    for name, value, low in (("total_timesteps", total_timesteps, 0),
                             ("episodes", episodes, 0), ("log_interval", log_interval, 1)):
        if value is not None:
            check_int(name, value, low)
    if episodes is None and total_timesteps is None:
        raise ValueError("give total_timesteps (env steps) or episodes=")
    if env is None:
        raise ValueError("this agent was loaded without an env; load(path, env=...) to learn")


def make_progress_bar(episodes: int | None, steps: int | None, show: bool) -> Any:
    """A tqdm bar over ``episodes`` (else env ``steps``), or ``None``."""
    if not show or not (episodes or steps):
        return None
    from tqdm.auto import tqdm

    by_episode = episodes is not None
    return tqdm(total=episodes if by_episode else steps, desc="JacProp agent",
                unit="episode" if by_episode else "step")


def end_episode(agent: Any, row: dict[str, Any], log: EpisodeLog | None, *,
                fps_since: tuple[int, float], bar: Any = None, bar_step: int = 1,
                log_interval: int | None = None) -> None:
    """The agent's bookkeeping after an episode of ``learn``: the row logged and counted, the
    run folder written, the SB3 logger's records (with ``time/fps``) to ``log`` and, every
    ``log_interval`` episodes, to stdout as SB3's table; the progress ``bar`` advanced by
    ``bar_step``.

    :param fps_since: ``(env_steps, perf_counter time)`` at the start of ``learn``.
    """
    agent.logger_rows.append(row)
    agent.episodes_done += 1
    if agent.config.checkpoint:
        write_run(agent, agent.config.run_dir)
    fps = (agent.env_steps - fps_since[0]) / max(time.perf_counter() - fps_since[1], 1e-9)
    extra = {**agent.logger.name_to_value, "time/fps": fps}
    if log is not None:
        log.append(row, extra=extra)
    if log_interval and agent.episodes_done % log_interval == 0:
        values = {**sb3_scalars(agent.logger_rows), **extra}
        HumanOutputFormat(sys.stdout).write(values, {k: agent.logger.name_to_excluded.get(
            k, ()) for k in values}, agent.env_steps)  # a callback's exclude= kept
    agent.logger.dump(agent.env_steps)
    if bar is not None:
        bar.update(bar_step)
        ratio = row.get("cost_ratio")
        bar.set_postfix(cost=f"{row['episode_cost']:.3g}",
                        ratio="-" if ratio is None else f"{float(ratio):.3g}")
