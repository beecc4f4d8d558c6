"""Which model lowers the planning error on the agent's OWN data? A diagnostic for a plateau.

``bench_model_sizes.py`` measures sizes on open-loop excitation, which on Pusher almost never
pushes the object. This script takes the trajectories an agent run stored (``data.npz`` of a
checkpoint folder written by ``bench_suite.py --checkpoints``), trains fresh ensembles of each
size on the first episodes and scores them on the last ones (the agent's late, closed-loop
episodes) the way a planner uses them:

* ``median_dim``: the median over moving dimensions of the one-step RMSE over the training
  std of the step (as ``bench_model_sizes``);
* ``cost_err``: from every ``stride``-th state of a held-out episode, the episode's own actions
  are rolled out ``horizon`` steps open loop on the ensemble mean; the median absolute
  difference between the predicted and the true summed task cost;
* ``cost_rank``: the Spearman rank correlation of predicted and true costs over those windows
  (how well the model orders plans).

Every size is trained from several initialisations (``--inits``): on Pusher the spread
over initialisations exceeds the differences between sizes (docs/benchmark.md).

    python scripts/diag_closed_loop_models.py --task pusher \
        --checkpoints runs/ckpt/pusher_cem-ilqr_none_seed0 --json runs/diag.json
"""

import os

for _var in ("OMP_NUM_THREADS", "OPENBLAS_NUM_THREADS", "MKL_NUM_THREADS"):
    os.environ.setdefault(_var, "1")

import json  # noqa: E402
import time  # noqa: E402
from dataclasses import asdict, dataclass  # noqa: E402

import casadi as ca  # noqa: E402
import numpy as np  # noqa: E402
import torch  # noqa: E402
from tqdm import tqdm  # noqa: E402

from agents import tasks  # noqa: E402
from agents.experiments.bench_model_sizes import model_config  # noqa: E402
from mbtsr.cli import parse  # noqa: E402
from mbtsr.io import write_json_atomic  # noqa: E402
from mbtsr.training import TrainConfig, train_ensemble  # noqa: E402
from mbtsr.trajectory import Trajectory  # noqa: E402


@dataclass
class Args:
    """Held-out planning error of ensemble sizes on an agent run's own trajectories."""

    task: str = "pusher"
    """a task of ``agents.tasks`` (its cost scores the rollouts)"""
    checkpoints: tuple[str, ...] = ()
    """checkpoint folders holding ``data.npz`` (one agent run each)"""
    sizes: tuple[str, ...] = ("rule", "4x200", "7m:rule")
    """``rule``, ``LxW`` or ``paper``; a ``7m:`` prefix sets 7 members (default 4)"""
    inits: tuple[int, ...] = (1, 2, 3)
    """weight-initialisation (and minibatch) seeds per size"""
    steps: int = 4000
    """gradient-step budget (the agent's optimizer, 10 % hold-out, patience 20)"""
    test_episodes: int = 5
    """the last episodes of each run, held out"""
    horizon: int = 30
    stride: int = 10
    json: str = "runs/diag_closed_loop_models.json"


args = parse(Args, outputs=("json",))
torch.set_num_threads(1)
task = getattr(tasks, args.task.replace("-", "_"))()
env = task.make_env()
n_obs, n_act = env.observation_space.shape[0], env.action_space.shape[0]
env.close()
o, a = ca.SX.sym("o", n_obs), ca.SX.sym("a", n_act)
cost = ca.Function("cost", [o, a], [task.observation_cost()(o, a)])


def cost_of(x_next: np.ndarray, u: np.ndarray) -> np.ndarray:
    """``[N]`` task costs of ``x_next [N, n]`` after actions ``u [N, m]``."""
    return np.asarray(cost.map(len(u))(x_next.T, u.T)).ravel()


def scores(frozen, train: list[Trajectory], test: list[Trajectory]) -> dict:
    dx = np.concatenate([t.x[1:] - t.x[:-1] for t in train])
    std = dx.std(0)
    moving = std > 1e-9 * (1.0 + np.abs(dx).max(0))
    x, u = np.concatenate([t.x[:-1] for t in test]), np.concatenate([t.u for t in test])
    err = frozen.step(x, u) - np.concatenate([t.x[1:] for t in test])
    per_dim = np.sqrt(np.mean((err[:, moving] / std[moving]) ** 2, 0))
    H = args.horizon
    starts = [(t, s) for t in test for s in range(0, len(t.u) - H + 1, args.stride)]
    xs = np.stack([t.x[s] for t, s in starts])
    predicted, true = np.zeros(len(starts)), np.zeros(len(starts))
    for k in range(H):  # all windows at once, one batched step per time step
        uk = np.stack([t.u[s + k] for t, s in starts])
        xs = frozen.step(xs, uk)
        predicted += cost_of(xs, uk)
        true += cost_of(np.stack([t.x[s + k + 1] for t, s in starts]), uk)
    rank = np.corrcoef(np.argsort(np.argsort(predicted)), np.argsort(np.argsort(true)))[0, 1]
    return {"median_dim": float(np.median(per_dim)),
            "cost_err": float(np.median(np.abs(predicted - true))),
            "cost_true_median": float(np.median(true)), "cost_rank": float(rank)}


rows = []
jobs = [(c, s, i) for c in args.checkpoints for s in args.sizes for i in args.inits]
for ckpt, size, init in tqdm(jobs, desc="models"):
    d = np.load(os.path.join(ckpt, "data.npz"))
    trajs = [Trajectory(x=d[f"x{i}"], u=d[f"u{i}"], dt=float(d[f"dt{i}"]))
             for i in range(int(d["count"]))]
    train, test = trajs[:-args.test_episodes], trajs[-args.test_episodes:]
    members, name = (7, size[3:]) if size.startswith("7m:") else (4, size)
    model = model_config(name, members).build(n_obs, n_act, seed=init)
    tic = time.process_time()
    hist = train_ensemble(model, train, TrainConfig(
        steps=args.steps, lr=1e-3, batch=256, holdout=0.1, eval_every=50, patience=20,
        early_stopping="member", member_data="order", progress=False, seed=init))
    rows.append({"checkpoint": ckpt, "size": size, "init": init, "steps": hist.steps,
                 "cpu_s": time.process_time() - tic, **scores(model.freeze(), train, test)})
    write_json_atomic(args.json, {"args": asdict(args), "rows": rows})
for size in args.sizes:
    got = [r for r in rows if r["size"] == size]
    print(f"{size:>10}: cost_err median {np.median([r['cost_err'] for r in got]):.2f}, "
          f"median_dim {np.median([r['median_dim'] for r in got]):.3f}, "
          f"cost_rank {np.median([r['cost_rank'] for r in got]):.2f} ({len(got)} models)")
print(json.dumps({"json": args.json}))
