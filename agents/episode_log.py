"""Per-episode log of the agent: an in-memory list of rows, a CSV file and TensorBoard scalars.

The CSV is rewritten atomically after every episode from the rows in memory, so after a resume
(rows restored from the checkpoint) it holds exactly the episodes of the checkpoint, never a
half-written line or the rows of an episode that was lost to a crash. TensorBoard events of lost
episodes are dropped with ``SummaryWriter(purge_step=...)``.
"""

from __future__ import annotations

import csv
import io
import math
from collections.abc import Iterable, Sequence
from pathlib import Path
from typing import Any

from agents.checkpoint import atomic_write_text

__all__ = ["EpisodeLog", "LOG_COLUMNS", "TIMING_COLUMNS"]

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

            # events at steps >= purge_step (episodes lost to a crash) are discarded
            self._writer = SummaryWriter(
                log_dir=str(self.run_dir / "tb"), purge_step=len(self.rows)
            )

    def append(self, row: dict[str, Any]) -> None:
        """Add one episode's row (keys from :data:`LOG_COLUMNS`) and write it out."""
        unknown = sorted(set(row) - set(LOG_COLUMNS))
        if unknown:
            raise ValueError(f"unknown log column(s): {unknown}")
        self.rows.append(dict(row))
        self._write_csv()
        if self._writer is not None:
            step = int(row["episode"])
            for key, value in row.items():
                if key in ("episode", "phase") or value is None or isinstance(value, str | list):
                    continue
                v = float(value)
                if math.isfinite(v):
                    group = "time" if key.startswith("time_") else "agent"
                    self._writer.add_scalar(f"{group}/{key}", v, global_step=step)
            self._writer.flush()

    def _write_csv(self) -> None:
        atomic_write_text(self.run_dir / "episodes.csv", rows_to_csv(self.rows, LOG_COLUMNS))

    def close(self) -> None:
        if self._writer is not None:
            self._writer.close()
            self._writer = None


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
