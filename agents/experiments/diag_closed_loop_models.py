"""Which model lowers the planning error on the agent's OWN data? A diagnostic for a plateau.

``bench_model_sizes`` measures sizes on open-loop excitation, which on Pusher almost never
pushes the object. This takes the trajectories an agent run stored (``data.npz`` of a checkpoint
folder written by ``bench_suite.py --checkpoints``), trains fresh ensembles of each size on the
first episodes and scores them on the last ones (the agent's late, closed-loop episodes) the way
a planner uses them (:func:`planning_errors`):

* ``median_dim``: the median over moving dimensions of the one-step RMSE over the training
  std of the step (as ``bench_model_sizes``);
* ``cost_err``: from every ``stride``-th state of a held-out episode, the episode's own actions
  are rolled out ``horizon`` steps open loop on the model; the median absolute difference
  between the predicted and the true summed task cost;
* ``cost_true_median``: the median true summed cost of those windows (the scale of
  ``cost_err``);
* ``cost_rank``: the Spearman rank correlation of predicted and true costs over those windows
  (how well the model orders plans; NaN when either is constant);
* with ``track`` (observation dimensions, e.g. Pusher's object position ``17 18``), over the
  windows in which those dimensions truly move more than ``move`` (their displacement's norm
  over the window): ``moved_windows``, the medians ``disp_true`` and ``disp_pred`` of the true
  and predicted displacement's norm, ``disp_err`` of the error's norm, and ``disp_cos`` of the
  cosine between them (does the model see a push, and which way it goes);
* with ``track``, the data itself (``coverage``, per run, before any training): over the run's
  episodes after ``skip`` (the agent's excitation episodes), how many moved the tracked
  dimensions more than ``move`` from start to end (``episodes_moved``), the median of that
  displacement, and with ``near`` (as many dimensions as ``track``, e.g. Pusher's fingertip
  ``14 15 16`` for the object ``17 18 19``) the median over episodes of the closest distance
  between the two (``closest_near``): did the training rollouts touch the object at all.
  ``--sizes`` with no size reports only this.

The model state must be the observation (a task without ``state_fn``: the task's cost is
written on the observation).

Every size is trained from several initialisations (``inits``): on Pusher the spread over
initialisations exceeds the differences between sizes (docs/benchmark.md, "Does a larger model
lift Pusher's plateau?").

    python scripts/diag_closed_loop_models.py --task pusher \
        --checkpoints runs/ckpt/pusher_cem-ilqr_none_seed0 --out runs/diag.json
"""

from __future__ import annotations

import dataclasses
import os
import time
from collections.abc import Callable, Sequence
from dataclasses import asdict, dataclass
from typing import Any

import casadi as ca
import numpy as np
import torch
from scipy.stats import spearmanr
from tqdm import tqdm

from agents.cli import main as command
from agents.config import AgentConfig
from agents.experiments.bench_model_sizes import errors, model_config
from agents.tasks import TASKS, make_task
from mbtsr.io import write_json_atomic
from mbtsr.training import TrainConfig, train_ensemble
from mbtsr.trajectory import Trajectory, load_trajectories
from mbtsr.validation import check_int


@dataclass(frozen=True)
class Args:
    """Held-out planning error of ensemble sizes on an agent run's own trajectories."""

    out: str = "runs/diag_closed_loop_models.json"
    """output JSON"""
    smoke: bool = False
    """tiny CI size: the options not given take SMOKE's values"""
    task: str = "pusher"
    """a task of agents.tasks (its cost scores the rollouts)"""
    checkpoints: tuple[str, ...] = ()
    """checkpoint folders holding data.npz (one agent run each)"""
    sizes: tuple[str, ...] = ("rule", "4x200", "7m:rule")
    """rule, LxW or paper; a 7m: prefix sets 7 members (default 4)"""
    inits: tuple[int, ...] = (1, 2, 3)
    """weight-initialisation (and minibatch) seeds per size"""
    steps: int = 4000
    """gradient-step budget per model (the agent's optimizer)"""
    patience: int | None = 20
    """early stopping on the hold-out after this many evaluations without progress; None: the
    whole budget"""
    holdout: float = 0.1
    """fraction of the training transitions held out (0: train on all; needs patience None)"""
    test_episodes: int = 5
    """the last episodes of each run, held out"""
    horizon: int = 30
    """open-loop rollout length of a scored window"""
    stride: int = 10
    """steps between the starts of scored windows"""
    track: tuple[int, ...] = ()
    """observation dimensions whose displacement over a window is scored (module docstring)"""
    move: float = 0.005
    """a window counts as moving when the tracked displacement's norm exceeds this"""
    near: tuple[int, ...] = ()
    """observation dimensions whose closest distance to the tracked ones is reported"""
    skip: int = 2
    """first episodes of a run left out of the coverage (the agent's excitation)"""

    def __post_init__(self) -> None:
        if self.task not in TASKS:
            raise ValueError(f"task must be one of {sorted(TASKS)}, got {self.task!r}")
        for name in ("steps", "test_episodes", "horizon", "stride"):
            check_int(name, getattr(self, name), 1)
        if not (self.move > 0 and np.isfinite(self.move)):
            raise ValueError(f"move must be a finite number > 0, got {self.move!r}")
        for i in self.track:
            check_int("track entries", i, 0)
        if len(set(self.track)) != len(self.track):
            raise ValueError(f"track: each dimension once, got {list(self.track)}")
        if self.near and len(self.near) != len(self.track):
            raise ValueError(f"near needs as many dimensions as track ({len(self.track)}), got "
                             f"{list(self.near)}")
        for i in self.near:
            check_int("near entries", i, 0)
        check_int("skip", self.skip, 0)
        self.training()  # the library's checks of steps, patience and holdout
        if self.patience is not None and self.holdout == 0:
            raise ValueError("patience needs held-out data: holdout > 0, or patience None")
        if not self.inits:
            raise ValueError("inits: give at least one initialisation seed")
        for size in self.sizes:
            members_and_size(size)

    def training(self, seed: int = 0) -> TrainConfig:
        """The agent's optimizer with this study's budget, patience and hold-out."""
        return dataclasses.replace(AgentConfig().training, steps=self.steps,
                                   patience=self.patience, holdout=self.holdout, seed=seed)


#: --smoke: the tiny CI size (options given on the command line win)
SMOKE = {"smoke": True, "sizes": ("2x16",), "inits": (1,), "steps": 20, "test_episodes": 1,
         "horizon": 5, "stride": 5}


def main(argv: list[str] | None = None) -> dict:
    """The command line (``--help``: the options)."""
    from agents.experiments.paper_common import blas_threads_from_env

    blas_threads_from_env()  # one BLAS thread unless OMP_NUM_THREADS says otherwise
    return command(Args, run, args=argv, outputs=("out",), presets={"--smoke": SMOKE})


def members_and_size(size: str) -> tuple[int, str]:
    """``(members, size)`` of a ``sizes`` entry (``7m:`` prefix: 7 members, else 4).

    :raises ValueError: naming the entry, if :func:`model_config` does not read its size.
    """
    members, name = (7, size[3:]) if size.startswith("7m:") else (4, size)
    try:
        model_config(name, members)
    except (TypeError, ValueError) as e:
        raise ValueError(f"sizes: {size!r} is not rule, paper or LxW (optionally after "
                         f"'7m:'): {e}") from None
    return members, name


def task_cost(task_name: str) -> tuple[Callable[[np.ndarray, np.ndarray], np.ndarray], int, int]:
    """``(cost_of, obs_dim, act_dim)`` of a task of :mod:`agents.tasks`: ``cost_of(x_next [N,
    n], u [N, m]) -> [N]``, its CasADi cost evaluated on a batch.

    :raises ValueError: for a task whose model state is not the observation (``state_fn``).
    """
    task = make_task(task_name)
    if task.state_fn is not None:
        raise ValueError(f"task {task_name!r} models a state_fn's state, not the observation "
                         "its cost is written on; this diagnostic needs the observation")
    env = task.make_env()
    n, m = env.observation_space.shape[0], env.action_space.shape[0]
    env.close()
    o, a = ca.SX.sym("o", n), ca.SX.sym("a", m)
    cost = ca.Function("cost", [o, a], [task.observation_cost()(o, a)])
    return (lambda x, u: np.asarray(cost.map(len(u))(x.T, u.T)).ravel()), n, m


def planning_errors(step: Callable[[np.ndarray, np.ndarray], np.ndarray],
                    cost_of: Callable[[np.ndarray, np.ndarray], np.ndarray],
                    train: Sequence[Trajectory], test: Sequence[Trajectory], *,
                    horizon: int, stride: int, track: Sequence[int] = (),
                    move: float = 0.005) -> dict[str, float]:
    """The module docstring's scores of a model ``step(x [N, n], u [N, m]) -> [N, n]`` on
    ``test`` (``train`` gives each dimension's step std; ``track``, ``move``: the displacement
    scores, none without ``track``)."""
    starts = [(t, s) for t in test for s in range(0, len(t.u) - horizon + 1, stride)]
    if len(starts) < 2:
        raise ValueError(f"the held-out episodes hold {len(starts)} windows of {horizon} steps; "
                         "need at least 2 (lower horizon or stride)")
    U = np.stack([t.u[s:s + horizon] for t, s in starts])  # [W, H, m]
    X = np.stack([t.x[s:s + horizon + 1] for t, s in starts])  # [W, H+1, n] true states
    W, m, n = len(starts), U.shape[2], X.shape[2]
    true = cost_of(X[:, 1:].reshape(-1, n), U.reshape(-1, m)).reshape(W, horizon).sum(1)
    xs, predicted = X[:, 0], np.zeros(W)
    for k in range(horizon):  # all windows at once, one batched model step per time step
        xs = step(xs, U[:, k])
        predicted += cost_of(xs, U[:, k])
    rank = spearmanr(predicted, true).statistic if np.ptp(predicted) and np.ptp(true) else np.nan
    scores = {"median_dim": errors(step, train, test)["nrmse_median_dim"],
              "cost_err": float(np.median(np.abs(predicted - true))),
              "cost_true_median": float(np.median(true)), "cost_rank": float(rank)}
    if len(track):
        idx = list(track)
        if min(idx) < 0 or max(idx) >= n:
            raise ValueError(f"track: dimensions {idx} out of range for states of {n} numbers")
        d_true, d_pred = X[:, -1, idx] - X[:, 0, idx], xs[:, idx] - X[:, 0, idx]
        norm_true = np.linalg.norm(d_true, axis=1)
        moved = norm_true > move
        norm_pred = np.linalg.norm(d_pred[moved], axis=1)
        cos = np.sum(d_pred[moved] * d_true[moved], 1) / np.maximum(
            norm_pred * norm_true[moved], 1e-300)

        def med(v: np.ndarray) -> float:
            return float(np.median(v)) if v.size else float("nan")

        scores.update({"moved_windows": int(moved.sum()), "disp_true": med(norm_true[moved]),
                       "disp_pred": med(norm_pred),
                       "disp_err": med(np.linalg.norm(d_pred[moved] - d_true[moved], axis=1)),
                       "disp_cos": med(cos)})
    return scores


def coverage(trajs: Sequence[Trajectory], track: Sequence[int], move: float,
             near: Sequence[int] = ()) -> dict[str, Any]:
    """How the tracked dimensions moved in ``trajs`` (module docstring, ``coverage``)."""
    idx = list(track)
    disp = np.array([np.linalg.norm(t.x[-1, idx] - t.x[0, idx]) for t in trajs])
    out = {"episodes": len(trajs), "episodes_moved": int(np.sum(disp > move)),
           "median_displacement": float(np.median(disp)) if disp.size else float("nan"),
           "displacement": disp.tolist()}
    if len(near):
        closest = [float(np.min(np.linalg.norm(t.x[:, list(near)] - t.x[:, idx], axis=1)))
                   for t in trajs]
        out.update({"closest_near": float(np.median(closest)) if closest else float("nan"),
                    "closest": closest})
    return out


def load_run(folder: str) -> list[Trajectory]:
    """The trajectories of an agent's checkpoint folder (``data.npz``)."""
    path = os.path.join(folder, "data.npz")
    if not os.path.isfile(path):
        raise ValueError(f"{folder!r} holds no data.npz (a folder of bench_suite --checkpoints)")
    return load_trajectories(path)


def run(args: Args) -> dict[str, Any]:
    """Train every size from every initialisation on every run; the JSON is rewritten after
    each model, so an interrupted study keeps what it measured."""
    if not args.checkpoints:
        raise ValueError("--checkpoints: give at least one checkpoint folder")
    torch.set_num_threads(1)
    cost_of, n, m = task_cost(args.task)
    for name in ("track", "near"):
        dims = getattr(args, name)
        if dims and max(dims) >= n:
            raise ValueError(f"{name}: dimensions {list(dims)} out of range for task "
                             f"{args.task!r}'s {n} observations")
    if not args.sizes and not args.track:
        raise ValueError("nothing to do: give --sizes to train, or --track for the coverage")
    runs = {c: load_run(c) for c in args.checkpoints}
    for c, trajs in runs.items():
        if args.track and len(trajs) <= args.skip:
            raise ValueError(f"{c!r} holds {len(trajs)} episodes; --skip {args.skip} leaves "
                             "none for the coverage")
        if args.sizes and len(trajs) <= args.test_episodes:
            raise ValueError(f"{c!r} holds {len(trajs)} episodes; --test-episodes "
                             f"{args.test_episodes} leaves none to train on")
        if (trajs[0].x.shape[1], trajs[0].u.shape[1]) != (n, m):
            raise ValueError(f"{c!r} holds states of {trajs[0].x.shape[1]} and actions of "
                             f"{trajs[0].u.shape[1]} numbers; task {args.task!r} has {n} and {m}")
    data = {c: coverage(trajs[args.skip:], args.track, args.move, args.near)
            for c, trajs in runs.items()} if args.track else {}
    for c, cov in data.items():
        print(f"{c}: {cov['episodes_moved']} of {cov['episodes']} episodes moved the tracked "
              f"dimensions > {args.move}, median {cov['median_displacement']:.4f}"
              + (f"; median closest distance to near {cov['closest_near']:.4f}"
                 if args.near else ""))
    rows: list[dict[str, Any]] = []
    write_json_atomic(args.out, {"args": asdict(args), "coverage": data, "rows": rows})
    jobs = [(c, s, i) for c in args.checkpoints for s in args.sizes for i in args.inits]
    for ckpt, size, init in tqdm(jobs, desc="models"):
        train, test = runs[ckpt][:-args.test_episodes], runs[ckpt][-args.test_episodes:]
        members, name = members_and_size(size)
        model = model_config(name, members).build(n, m, seed=init)
        tic = time.process_time()
        hist = train_ensemble(model, train, args.training(init))
        rows.append({"checkpoint": ckpt, "size": size, "init": init, "steps": hist.steps,
                     "n_holdout": hist.n_holdout, "stopped_early": hist.stopped_early,
                     "cpu_s": time.process_time() - tic,
                     **planning_errors(model.freeze().step, cost_of, train, test,
                                       horizon=args.horizon, stride=args.stride,
                                       track=args.track, move=args.move)})
        write_json_atomic(args.out, {"args": asdict(args), "coverage": data, "rows": rows})
    for size in args.sizes:
        got = [r for r in rows if r["size"] == size]
        print(f"{size:>10}: cost_err median {np.median([r['cost_err'] for r in got]):.2f}, "
              f"median_dim {np.median([r['median_dim'] for r in got]):.3f}, "
              f"cost_rank {np.median([r['cost_rank'] for r in got]):.2f} ({len(got)} models)"
              + (f", displacement predicted {np.median([r['disp_pred'] for r in got]):.4f} of "
                 f"{np.median([r['disp_true'] for r in got]):.4f}" if args.track else ""))
    return {"args": asdict(args), "coverage": data, "rows": rows}


if __name__ == "__main__":
    main()
