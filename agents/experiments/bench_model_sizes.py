"""Model sizing and training measurements on standard MuJoCo tasks (issue 21, items 1-2).

What it measures and how to run it: docs/experiments.md, section ``bench_model_sizes``.
"""

from __future__ import annotations

import dataclasses
import json
import os
import time
from collections.abc import Callable
from dataclasses import dataclass
from typing import Literal

import numpy as np
import torch

from agents.cli import main as command
from agents.experiments.paper_common import machine_info, pyplot, save_figure, write_result
from agents.tasks import make_task
from mbtsr import Trajectory
from mbtsr.ensemble import DynamicsEnsemble, ModelConfig
from mbtsr.excitation import unit_filtered_gaussian
from mbtsr.training import TrainConfig, train_ensemble


@dataclass(frozen=True)
class Args:
    """Held-out one-step error and wall time of ensemble sizes and training designs."""

    out: str = ""
    """write the results to this JSON file"""
    smoke: bool = False
    """tiny CI size: the options not given take SMOKE's values"""
    task: str = "reacher"
    """a task of the registry (agents.tasks.TASKS)"""
    study: Literal["sizes", "training", "agent", "scaling", "plot"] = "sizes"
    """sizes (ensembles of several sizes at fixed budgets), training (designs at one size),
    agent (whole agent runs), scaling (update time as data grows) or plot (the sizes figure)"""
    sizes: str = "paper,paper@0.003,2x64,2x128,3x128,3x200,4x200"
    """comma-separated sizes LxW (swish), rule (the default size of the task's dimensions) or
    paper (4 x 1 x 20, mixed activations), each
    optionally with its own Adam step size (``paper@0.003``; default ``lr``)"""
    size: str = "3x200"
    """the size of the training study"""
    budgets: str = "1000,4000"
    """comma-separated gradient-step budgets (the sizes study trains to the largest and
    records the error at each)"""
    n_train: int = 3000
    """training transitions"""
    n_test: int = 1000
    """held-out transitions (other episodes)"""
    batch: int = 256
    """minibatch size"""
    lr: float = 1e-3
    """Adam step size"""
    members: int = 4
    """ensemble size"""
    eval_every: int = 250
    """steps between held-out evaluations"""
    seed: int = 0
    """seed of the data and the models"""
    threads: int = 1
    """torch threads"""
    episodes: int = 40
    """episodes of the agent study"""
    agent_overrides: str = "{}"
    """JSON of AgentConfig changes by dotted field for the agent study"""
    plot: str = ""
    """study plot: write the figure of the sizes JSONs given in plot_from to this PNG"""
    plot_from: str = ""
    """study plot: comma-separated JSON files of the sizes study (one per task)"""


#: --smoke: the tiny CI size (options given on the command line win)
SMOKE = {"smoke": True, "sizes": "2x16", "size": "2x16", "budgets": "20", "n_train": 200,
         "n_test": 50, "eval_every": 10, "episodes": 2}


def main(argv: list[str] | None = None) -> dict:
    """The command line (``--help``: the options)."""
    from agents.experiments.paper_common import blas_threads_from_env

    blas_threads_from_env()  # one BLAS thread unless OMP_NUM_THREADS says otherwise
    return command(Args, run, args=argv, outputs=("out", "plot"), presets={"--smoke": SMOKE})


def collect(task_name: str, n: int, seed: int, *, episode_steps: int | None = None,
            states: bool = False) -> list[Trajectory]:
    """``n`` transitions of open-loop excitation (episodes alternate random and smooth).

    :param episode_steps: cap on an episode's length (default: the env's own limit).
    :param states: also record the MuJoCo state ``concat(qpos, qvel)`` of every observation in
        ``meta["state"]`` (``[T + 1, nq + nv]``, for the true model's Jacobians).
    """
    task = make_task(task_name)
    env = task.make_env()
    lo, hi = env.action_space.low.astype(float), env.action_space.high.astype(float)
    mid, half = 0.5 * (lo + hi), 0.5 * (hi - lo)
    rng = np.random.default_rng(seed)
    if states:
        from envs.mujoco_model import state_of
    trajs, total, episode = [], 0, 0
    while total < n:
        T = min(env.spec.max_episode_steps or 1000, episode_steps or np.inf)
        if episode % 2 == 0:
            U = rng.uniform(lo, hi, size=(T, lo.size))
        else:
            sig = unit_filtered_gaussian(T, lo.size, window=8, seed=int(rng.integers(2**31)))
            U = np.clip(mid + 0.5 * half * sig, lo, hi)
        obs, _ = env.reset(seed=int(rng.integers(2**31)))
        xs, us = [np.asarray(obs, float)], []
        qs = [state_of(env)] if states else None
        for t in range(min(T, n - total)):
            obs, _, terminated, truncated, _ = env.step(U[t])
            xs.append(np.asarray(obs, float))
            us.append(U[t])
            if states:
                qs.append(state_of(env))
            if terminated or truncated:
                break
        if us:
            meta = {"excitation": "random" if episode % 2 == 0 else "smooth"}
            if states:
                meta["state"] = np.array(qs)
            trajs.append(Trajectory(np.array(xs), np.array(us), env.unwrapped.dt, meta=meta))
            total += len(us)
        episode += 1
    env.close()
    return trajs


def errors(step: Callable[[np.ndarray, np.ndarray], np.ndarray], train: list[Trajectory],
           test: list[Trajectory]) -> dict:
    """Held-out errors on ``test`` of a model ``step(x [N, n], u [N, m]) -> [N, n]`` (e.g. the
    frozen ensemble mean's): ``nrmse``, ``nrmse_median_dim``, ``nrmse_per_dim`` and
    ``rel_step`` (docs/experiments.md, ``bench_model_sizes``, says what each measures)."""
    std, moving = _moving(train)
    x = np.concatenate([t.x[:-1] for t in test])
    u = np.concatenate([t.u for t in test])
    x_next = np.concatenate([t.x[1:] for t in test])
    err = step(x, u) - x_next
    per_dim = np.sqrt(np.mean((err[:, moving] / std[moving]) ** 2, 0))
    return {
        "nrmse": float(np.sqrt(np.mean(per_dim**2))),
        "nrmse_median_dim": float(np.median(per_dim)),
        "nrmse_per_dim": dict(zip(np.flatnonzero(moving).tolist(), per_dim.tolist())),
        "rel_step": float(np.sqrt(np.sum(err**2) / np.sum((x_next - x) ** 2))),
    }


def _moving(train: list[Trajectory]) -> tuple[np.ndarray, np.ndarray]:
    """``(std, moving)`` of each dimension's one-step change in ``train`` (a goal: not moving)."""
    dx = np.concatenate([t.x[1:] - t.x[:-1] for t in train])
    return dx.std(0), dx.std(0) > 1e-9 * (1.0 + np.abs(dx).max(0))


def model_config(size: str, members: int, **kw) -> ModelConfig:
    """``paper``, ``rule`` (:func:`mbtsr.ensemble.default_size`) or ``LxW`` (swish)."""
    if size == "paper":
        return ModelConfig.paper(ensemble_size=members, **kw)
    if size == "rule":
        return ModelConfig(ensemble_size=members, **kw)
    layers, width = (int(v) for v in size.lower().split("x"))
    return ModelConfig(ensemble_size=members, hidden_layers=layers, hidden_width=width, **kw)


def planning_cost(model: DynamicsEnsemble, seed: int) -> dict:
    """ms of the frozen ensemble-mean step at 1 and 200 rows and of its Jacobians at 30 points
    (best of 5, :func:`~agents.experiments.bench_env.best_rate`)."""
    from agents.experiments.bench_env import best_rate

    frozen = model.freeze()
    rng = np.random.default_rng(seed)
    n, m = frozen.state_dim, frozen.action_dim
    out = {}
    for name, fn, reps in (
        ("step_1_ms", lambda a, b: frozen.step(a[:1], b[:1]), 200),
        ("step_200_ms", lambda a, b: frozen.step(a, b), 20),
        ("jacobians_30_ms", lambda a, b: frozen.jacobians(a[:30], b[:30]), 20),
    ):
        x, u = rng.normal(size=(200, n)), rng.normal(size=(200, m))
        fn(x, u)
        out[name] = 1e3 / best_rate(lambda f=fn, x=x, u=u, k=reps: [f(x, u) for _ in range(k)],
                                    reps, 5)
    return out


def train_one(cfg: ModelConfig, train, test, n, m, seed, tcfg: TrainConfig) -> dict:
    model = cfg.build(n, m, seed=seed)
    wall, cpu = time.perf_counter(), time.process_time()
    hist = train_ensemble(model, train, tcfg, validation=test)
    wall, cpu = time.perf_counter() - wall, time.process_time() - cpu
    return {"model": model, "hist": hist, "wall_s": wall, "cpu_s": cpu,
            "ms_per_step": wall / max(hist.steps, 1) * 1e3,
            "cpu_ms_per_step": cpu / max(hist.steps, 1) * 1e3}


def ltv_fit(t: Trajectory, lam: float = 10.0):
    """The smooth LTV fit of ``t`` (:func:`mbtsr.ltv.fit_ltv`, smoothness ``lam``) with the
    agent's fallback for degenerate regressors (a constant goal): a weak prior on the first
    Jacobian; ``None`` for a trajectory of fewer than 2 transitions."""
    from mbtsr.ltv import fit_ltv

    if t.T < 2:
        return None
    try:
        return fit_ltv(t, lam)
    except ValueError:
        phi = np.concatenate(t.inputs, axis=1)
        return fit_ltv(t, lam, P0=1.0 / (1e-6 * float(np.mean(np.sum(phi**2, 1))) * t.T
                                         + 1e-12))


def scaling_study(args: Args) -> dict:
    """Seconds of one update (the agent's training config as recorded in scaling_reacher.json:
    500 steps without early stopping, sampled JacProp) against the number of training
    transitions."""
    from agents.config import AgentConfig

    data = collect(args.task, args.n_train, args.seed)
    ltvs = [ltv_fit(t) for t in data]
    keep = [i for i, lm in enumerate(ltvs) if lm is not None]
    data, ltvs = [data[i] for i in keep], [ltvs[i] for i in keep]
    counts = np.cumsum([t.T for t in data])
    tcfg = dataclasses.replace(AgentConfig().training, steps=500, patience=None, seed=args.seed)
    reg = AgentConfig(regularization="sampled").regularization
    model = ModelConfig().build(data[0].n, data[0].m, seed=args.seed)
    sizes = [n for n in (250, 1000, args.n_train) if n <= counts[-1]]
    times: dict[int, list[float]] = {n: [] for n in sizes}
    for _ in range(3):
        for n in sizes:
            k = int(np.searchsorted(counts, n)) + 1
            tic = time.perf_counter()
            train_ensemble(model, data[:k], tcfg, reg, ltv_models=ltvs[:k])
            times[n].append(time.perf_counter() - tic)
            print(f"{args.task}: {int(counts[k - 1])} transitions: {times[n][-1]:.2f} s",
                  flush=True)
    return {"steps": tcfg.steps, "seconds": {str(n): float(np.median(v)) for n, v in times.items()},
            "all_seconds": {str(n): v for n, v in times.items()},
            "ratio_largest_over_smallest": float(np.median(times[sizes[-1]])
                                                 / np.median(times[sizes[0]]))}


def agent_study(args: Args) -> dict:
    """The agent on the task: per-episode phase times, the update-time ratio, the returns."""
    from agents.config import AgentConfig
    from agents.jacprop_agent import JacPropAgent

    task = make_task(args.task)
    changes = json.loads(args.agent_overrides)
    cfg = AgentConfig.default(changes, seed=args.seed, progress=False, tensorboard=False,
                              checkpoint=False, torch_threads=args.threads)
    agent = JacPropAgent(task.make_env(), cfg, **task.agent_kwargs())
    def show(info: dict) -> None:
        r = info["row"]
        print(f"{args.task} episode {r['episode']:3d}: update {r['time_training']:6.2f} s, "
              f"planning {r['time_planning']:6.2f} s, eval {r['time_eval']:6.2f} s, "
              f"return {r.get('eval_return')}", flush=True)

    tic = time.perf_counter()
    agent.learn(episodes=args.episodes, callback=show, progress_bar=False)
    wall = time.perf_counter() - tic
    log = agent.logger_rows
    upd = np.array([r["time_training"] for r in log])
    out = {"config": cfg.to_dict(),
           "model": [int(v) for v in cfg.model.size(agent.state_dim, agent.spec.act_dim)],
           "env_steps": agent.env_steps, "wall_s": wall,
           "per_episode": [{k: r[k] for k in ("episode", "env_steps", "time_training",
                                              "time_planning", "time_ltv", "time_eval",
                                              "time_oracle", "time_total", "eval_return",
                                              "one_step_rms")} for r in log],
           "summary": agent.summary()}
    if len(upd) >= 21:
        out["update_s_episode_5"] = float(np.median(upd[3:6]))
        out["update_s_episode_20"] = float(np.median(upd[18:21]))
        out["update_ratio_20_over_5"] = out["update_s_episode_20"] / out["update_s_episode_5"]
        print(f"update time: episode 5 {out['update_s_episode_5']:.2f} s, episode 20 "
              f"{out['update_s_episode_20']:.2f} s, ratio {out['update_ratio_20_over_5']:.2f}")
    print(f"{args.task}: {agent.env_steps} env steps in {wall:.0f} s")
    return out


def plot_sizes(paths: list[str], out: str) -> None:
    """Held-out error (median over dimensions, relative to the paper's 4 x 1 x 20 on the same
    task) and CPU milliseconds per gradient step against the size, one line per task."""
    plt = pyplot()

    fig, (ax_err, ax_time) = plt.subplots(1, 2, figsize=(10, 3.8))
    for path in paths:
        d = json.loads(open(path).read())
        rows = {k: v for k, v in d["results"].items() if "@" not in k}
        if "paper@0.003" in d["results"]:  # the paper's model at its own step size
            rows = {"paper": d["results"]["paper@0.003"],
                    **{k: v for k, v in rows.items() if k != "paper"}}
        key = "nrmse_median_dim" if "nrmse_median_dim" in rows["paper"] else "nrmse"
        ref = rows["paper"][key]
        labels = list(rows)
        name = f"{d['args']['task']} (n+m={d['n'] + d['m']})"
        ax_err.plot(labels, [rows[k][key] / ref for k in labels], "o-", label=name)
        ax_time.plot(labels, [rows[k]["cpu_ms_per_step"] for k in labels], "o-", label=name)
    ax_err.set(yscale="log", ylabel="held-out one-step error / paper's",
               title=f"after {d['args']['budgets'].split(',')[-1]} steps (median over dims)")
    ax_time.set(yscale="log", ylabel="CPU ms per gradient step (batch 256)",
                title="training cost, 4 members")
    for ax in (ax_err, ax_time):
        ax.set_xlabel("hidden layers x width (paper: 1 x 20, Adam 3e-3)")
        ax.grid(True, which="both", alpha=0.3)
    ax_err.legend(fontsize=8)
    save_figure(fig, out, dpi=120)
    print(f"wrote {out}")


def run(args: Args) -> dict:
    torch.set_num_threads(args.threads)
    t_start = time.perf_counter()
    load_start = os.getloadavg()
    if args.study == "plot":
        plot_sizes([p for p in args.plot_from.split(",") if p], args.plot)
        return {}
    if args.study in ("scaling", "agent"):
        study = scaling_study if args.study == "scaling" else agent_study
        result = {"args": dataclasses.asdict(args), "results": study(args)}
        if args.study == "agent":
            result["machine"] = machine_info(load_start)
        write_result(args.out, result)
        return result
    train = collect(args.task, args.n_train, args.seed)
    test = collect(args.task, args.n_test, args.seed + 1000)
    n, m = train[0].n, train[0].m
    budgets = sorted(int(b) for b in args.budgets.split(","))
    result: dict = {"args": dataclasses.asdict(args), "n": n, "m": m,
                    "episodes_train": len(train), "episodes_test": len(test)}
    # the normalized validation loss of train_ensemble is sum_d (err_d / out_std_d)^2 with
    # out_std the residual std of the training data: nrmse^2 * n_moving for the g model
    n_moving = int(np.sum(_moving(train)[1]))
    result["n_moving"] = n_moving
    rows = {}
    if args.study == "sizes":
        for label in args.sizes.split(","):
            size, _, lr = label.partition("@")
            cfg = model_config(size, args.members)
            tcfg = TrainConfig(steps=budgets[-1], batch=args.batch, lr=float(lr or args.lr),
                               eval_every=args.eval_every, seed=args.seed, progress=False)
            r = train_one(cfg, train, test, n, m, args.seed, tcfg)
            hist = r["hist"]
            curve = np.sqrt(hist.val_ensemble_loss / n_moving)
            at = {str(b): float(curve[list(hist.eval_steps).index(b)]) for b in budgets
                  if b in hist.eval_steps}
            rows[label] = {
                "lr": tcfg.lr,
                "layers_x_width": [int(v) for v in cfg.size(n, m)],
                "parameters": int(sum(p.numel() for p in r["model"].parameters())),
                "nrmse_at_budget": at,
                "nrmse_curve": {"steps": hist.eval_steps.tolist(), "nrmse": curve.tolist()},
                "best_nrmse": float(curve.min()),
                "best_step": int(hist.eval_steps[int(curve.argmin())]),
                **errors(r["model"].freeze("float64").step, train, test),
                "ms_per_step": r["ms_per_step"], "cpu_ms_per_step": r["cpu_ms_per_step"],
                "train_wall_s": r["wall_s"],
                "planning": planning_cost(r["model"], args.seed),
            }
            row = rows[label]
            print(f"{args.task} {label:12s}: nrmse {at} (best {row['best_nrmse']:.3f} at "
                  f"{row['best_step']}), median-dim {row['nrmse_median_dim']:.3f}, "
                  f"rel_step {row['rel_step']:.3f}, "
                  f"{r['ms_per_step']:.1f} ms/step (CPU {r['cpu_ms_per_step']:.1f})", flush=True)
    elif args.study == "training":
        budget = budgets[-1]
        base = {"steps": budget, "batch": args.batch, "lr": args.lr, "seed": args.seed,
                "progress": False}
        es = {"holdout": 0.1, "patience": 5, "eval_every": 100}
        designs = {
            "budget": ({}, {}),
            "es_member": ({**es, "early_stopping": "member"}, {}),
            "es_ensemble": ({**es, "early_stopping": "ensemble"}, {}),
            "es_member_order": ({**es, "member_data": "order"}, {}),
            "es_member_bootstrap": ({**es, "member_data": "bootstrap"}, {}),
            "es_member_order_probabilistic": ({**es, "member_data": "order"},
                                              {"probabilistic": True}),
        }
        for name, (tkw, mkw) in designs.items():
            cfg = model_config(args.size, args.members, **mkw)
            r = train_one(cfg, train, test, n, m, args.seed,
                          TrainConfig(**{**base, **tkw}))
            hist = r["hist"]
            rows[name] = {**errors(r["model"].freeze("float64").step, train, test),
                          "steps": hist.steps,
                          "stopped_early": hist.stopped_early,
                          "best_steps": None if hist.best_steps is None
                          else hist.best_steps.tolist(),
                          "train_wall_s": r["wall_s"], "cpu_s": r["cpu_s"]}
            print(f"{args.task} {name:30s}: nrmse {rows[name]['nrmse']:.4f} median-dim "
                  f"{rows[name]['nrmse_median_dim']:.4f} rel_step "
                  f"{rows[name]['rel_step']:.4f} steps {hist.steps} "
                  f"({r['wall_s']:.1f} s)", flush=True)
    result["results"] = rows
    result["machine"] = machine_info(load_start)
    result["total_time_s"] = time.perf_counter() - t_start
    write_result(args.out, result)
    return result


if __name__ == "__main__":
    main()
