"""The small-data regime on purpose (issue 21, item 4): wide ensembles trained on the first few
episodes of each suite task, without and with tangent-space regularization.

What it measures and how to run it: docs/experiments.md, section ``exp_small_data``; data,
model, training, metrics and aggregates: docs/small_data.md, "What was run".
"""

from __future__ import annotations

import dataclasses
import os
import time
from dataclasses import dataclass, field

import numpy as np
import torch

from agents.cli import main as command
from agents.experiments import paper_common as pc
from agents.experiments.bench_model_sizes import collect, errors, ltv_fit
from agents.tasks import make_task
from mbtsr.ensemble import ModelConfig
from mbtsr.io import write_json_atomic
from mbtsr.metrics import jacobian_error
from mbtsr.training import RegularizationConfig, TrainConfig, train_ensemble

TASKS = "inverted-pendulum,inverted-double-pendulum,reacher,half-cheetah,pusher"  # cheap first


@dataclass(frozen=True)
class Args:
    """Wide ensembles on 1, 2 and 5 episodes: held-out and Jacobian error, none vs sampled vs
    exact."""

    tasks: str = field(default=TASKS, metadata={
        "help": "comma-separated tasks of the registry (agents.tasks.TASKS, MuJoCo envs)"})
    episodes: str = field(default="1,2,5", metadata={
        "help": "comma-separated numbers of first episodes to train on"})
    episode_steps: int = field(default=200, metadata={
        "help": "cap on an episode's length (HalfCheetah's 1000; the others end earlier)"})
    n_test: int = field(default=500, metadata={"help": "held-out transitions (other episodes)"})
    jac_points: int = field(default=100, metadata={
        "help": "held-out points of the Jacobian error"})
    regularizations: str = field(default="none,sampled,exact", metadata={
        "help": "comma-separated regularizers (RegularizationConfig.named, default weights)"})
    ltv_lambda: float = field(default=10.0, metadata={
        "help": "smoothness of the LTV fits that label sampled and exact"})
    seeds: int = field(default=3, metadata={
        "help": "seeds 0..seeds-1 (data, initialization, minibatches, perturbations)"})
    steps: int = field(default=400, metadata={
        "help": "Adam steps of every training (equal for all regularizations)"})
    batch: int = field(default=64, metadata={
        "help": "minibatch size (all transitions when there are fewer; exact's double "
                "backprop costs 0.1-0.15 s a step at 64 on the suite tasks)"})
    lr: float = field(default=1e-3, metadata={"help": "Adam step size"})
    members: int = field(default=4, metadata={"help": "ensemble members"})
    layers: int = field(default=3, metadata={"help": "hidden layers per member"})
    width: int = field(default=200, metadata={"help": "hidden units per layer"})
    threads: int = field(default=1, metadata={"help": "torch threads"})
    out: str = field(default="docs/results/small_data.json", metadata={
        "help": "write the results to this JSON file ('' for none)"})
    plot: str = field(default="docs/figures/small_data.png", metadata={
        "help": "write the figure to this PNG ('' for none)"})
    study: str = field(default="models", metadata={
        "help": "models (train and measure) or labels (the LTV labels' Jacobian error only)"})
    smoke: bool = field(default=False, metadata={
        "help": "tiny settings for tests (set by --smoke)"})


#: what --smoke changes (seconds; nothing to conclude); options given on the command line win
SMOKE = {"smoke": True, "tasks": "inverted-pendulum", "episodes": "1,2", "n_test": 40,
         "jac_points": 8, "seeds": 1, "steps": 5, "width": 16, "layers": 2, "members": 2,
         "out": "runs/small_data_smoke.json", "plot": ""}


def main(argv: list[str] | None = None) -> dict:
    """The command line (``--help``: the options)."""
    pc.blas_threads_from_env()  # one BLAS thread unless OMP_NUM_THREADS says otherwise
    return command(Args, run, args=argv, outputs=("out", "plot"), presets={"--smoke": SMOKE})


def true_jacobians(task_name: str, x: np.ndarray, u: np.ndarray
                   ) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    """The true ``d(next obs)/d obs`` on the tangent space and ``d(next obs)/du`` at the MuJoCo
    states ``x [T, nq+nv]`` and actions ``u [T, m]`` (docs/small_data.md, "What was run"):
    ``(A [T, d, d], B [T, d, m], P [T, d, d])``, ``P`` the projector on the tangent space."""
    from envs.mujoco_model import MujocoDynamics, ObservedDynamics

    env = make_task(task_name).make_env()
    env.reset(seed=0)
    od = ObservedDynamics(MujocoDynamics(env), env)
    n = od.n  # jacobians read only the state part of z = [x, obs]
    Az, Bz = od.jacobians(np.concatenate([x, np.zeros((len(x), od.obs_dim))], 1), u)
    CA, CB = Az[:, n:, :n], Bz[:, n:]  # C(x+) A_x, C(x+) B_x
    C = np.asarray(od.observation_jacobian(x))
    C_pinv = np.linalg.pinv(C, rcond=1e-8)  # [T, n, d]
    env.close()
    return CA @ C_pinv, CB, C @ C_pinv


def jacobian_rel_error(A: np.ndarray, B: np.ndarray, P: np.ndarray, A_hat: np.ndarray,
                       B_hat: np.ndarray) -> dict:
    """Relative Frobenius errors of model Jacobians ``A_hat, B_hat`` against the true ``A, B``
    with tangent projector ``P`` (docs/small_data.md, "What was run"): ``jac_rel`` (median over
    the points), ``jac_rel_pooled`` (sums over the points), ``jac_rel_A``, ``jac_rel_B`` (each
    block alone, median)."""
    D_A, D_B = A_hat @ P - A, B_hat - B
    zero_A, zero_B = np.zeros_like(A), np.zeros_like(B)

    def norms(X, Y=None):
        return np.sqrt(np.sum(X * X, (-1, -2)) + (0.0 if Y is None else np.sum(Y * Y, (-1, -2))))

    return {
        "jac_rel": float(np.median(norms(D_A, D_B) / norms(A, B))),
        "jac_rel_pooled": jacobian_error((A, B), (A_hat @ P, B_hat))
        / jacobian_error((A, B), (zero_A, zero_B)),
        "jac_rel_A": float(np.median(norms(D_A) / norms(A))),
        "jac_rel_B": float(np.median(norms(D_B) / norms(B))),
    }


def wins_total(method: dict[int, float], none: dict[int, float]) -> tuple[int, int]:
    """Seeds (in both) where ``method``'s error is strictly below ``none``'s, and how many."""
    seeds = sorted(set(method) & set(none))
    return sum(method[s] < none[s] for s in seeds), len(seeds)


METRICS = ("rel_step", "jac_rel")


def aggregate(records: list[dict], regs: list[str]) -> list[dict]:
    """Per (task, episodes): medians over seeds, median per-seed ratio to none, wins/total."""
    cells = list(dict.fromkeys((r["task"], r["episodes"]) for r in records))
    out = []
    for task, k in cells:
        rows = [r for r in records if r["task"] == task and r["episodes"] == k]
        by = {reg: {r["seed"]: r for r in rows if r["reg"] == reg} for reg in regs}
        cell = {"task": task, "episodes": k,
                "transitions": int(np.median([r["transitions"] for r in rows]))}
        for key in METRICS:
            vals = {reg: {s: r[key] for s, r in by[reg].items()} for reg in regs}
            cell[key] = {reg: float(np.median(list(v.values()))) for reg, v in vals.items() if v}
            for reg in regs:
                if reg == "none" or not vals[reg] or not vals.get("none"):
                    continue
                w, tot = wins_total(vals[reg], vals["none"])
                ratios = [vals[reg][s] / vals["none"][s] for s in vals[reg] if s in vals["none"]]
                cell[f"{key}_{reg}_over_none"] = float(np.median(ratios))
                cell[f"{key}_{reg}_wins"] = [w, tot]
        out.append(cell)
    return out


def markdown_table(cells: list[dict], regs: list[str]) -> str:
    """The doc's table: medians and ratio (wins/total) per task and episode count."""
    others = [r for r in regs if r != "none"]
    head = ["task", "episodes (transitions)"]
    for name in ("Jacobian error", "held-out error"):
        head += [f"{name}: {reg}" for reg in regs]
        head += [f"{name}: {reg}/none (wins)" for reg in others]
    lines = ["| " + " | ".join(head) + " |", "|" + "---|" * len(head)]
    for c in cells:
        row = [c["task"], f"{c['episodes']} ({c['transitions']})"]
        for key in ("jac_rel", "rel_step"):
            row += [f"{c[key][reg]:.3g}" for reg in regs]
            row += [f"{c[f'{key}_{reg}_over_none']:.2f} ({c[f'{key}_{reg}_wins'][0]}/"
                    f"{c[f'{key}_{reg}_wins'][1]})" for reg in others]
        lines.append("| " + " | ".join(row) + " |")
    return "\n".join(lines)


def plot(cells: list[dict], records: list[dict], regs: list[str], out: str) -> None:
    """Per task: Jacobian error (top) and held-out error (bottom) against the episodes, median
    line and per-seed points per regularization, log y."""
    plt = pc.pyplot()

    tasks = list(dict.fromkeys(c["task"] for c in cells))
    fig, axes = plt.subplots(2, len(tasks), figsize=(3.2 * len(tasks), 5.6), squeeze=False)
    colors = {"none": "tab:gray", "sampled": "tab:blue", "exact": "tab:orange"}
    for j, task in enumerate(tasks):
        tc = [c for c in cells if c["task"] == task]
        ks = [c["episodes"] for c in tc]
        for i, (key, label) in enumerate((("jac_rel", "Jacobian error (rel. Frobenius)"),
                                          ("rel_step", "held-out error / true step"))):
            ax = axes[i, j]
            for o, reg in enumerate(regs):
                col = colors.get(reg)
                ax.plot(ks, [c[key][reg] for c in tc], "o-", color=col, label=reg)
                pts = [(r["episodes"], r[key]) for r in records
                       if r["task"] == task and r["reg"] == reg]
                ax.scatter([p[0] * (1 + 0.04 * (o - 1)) for p in pts], [p[1] for p in pts],
                           s=8, color=col, alpha=0.4)
            ax.set(xscale="log", yscale="log", xticks=ks, xticklabels=[str(k) for k in ks])
            ax.set_xticks([], minor=True)
            ax.grid(True, which="both", alpha=0.3)
            if i == 0:
                ax.set_title(task)
            else:
                ax.set_xlabel("training episodes")
            if j == 0:
                ax.set_ylabel(label)
    axes[0, 0].legend(fontsize=8)
    pc.save_figure(fig, out)
    print(f"wrote {out}")


def training_episodes(task: str, seed: int, k: int, args: Args) -> tuple[list, list]:
    """The first ``k`` training episodes of ``task`` for ``seed`` (with their MuJoCo states)
    and the smooth LTV fit of each (the labels of sampled and exact)."""
    env = make_task(task).make_env()
    T_max = min(env.spec.max_episode_steps or 1000, args.episode_steps)
    env.close()
    episodes = collect(task, k * T_max, seed, episode_steps=args.episode_steps,
                       states=True)[:k]
    ltvs = [ltv_fit(t, args.ltv_lambda) for t in episodes]
    if any(lm is None for lm in ltvs):
        raise ValueError(f"{task} seed {seed}: an episode of < 2 transitions")
    return episodes, ltvs


def true_at_points(task: str, seed: int, trajs: list, n_points: int) -> tuple:
    """``(pts, u, A, B, P)``: a seeded draw of at most ``n_points`` of the trajectories'
    transitions (sorted indices), all their actions and the true Jacobians (:func:`true_jacobians`)
    at the drawn ones."""
    x = np.concatenate([t.meta["state"][:-1] for t in trajs])
    u = np.concatenate([t.u for t in trajs])
    pts = np.sort(np.random.default_rng(seed).choice(len(u), min(n_points, len(u)),
                                                     replace=False))
    return pts, u, *true_jacobians(task, x[pts], u[pts])


def label_study(args: Args) -> dict:
    """The Jacobian error of the LTV labels themselves (what sampled and exact pull the model
    towards) against the true model at the training points of the first k episodes
    (``jac_points`` of them at most), same metric as the models'."""
    t0 = time.perf_counter()
    ks = sorted(int(k) for k in args.episodes.split(","))
    records = []
    for seed in range(args.seeds):
        for task in [t for t in args.tasks.split(",") if t]:
            episodes, ltvs = training_episodes(task, seed, ks[-1], args)
            for k in ks:
                pts, u, A, B, P = true_at_points(task, seed, episodes[:k], args.jac_points)
                A_l, B_l = pc.label_jacobians(ltvs, episodes[:k])
                rec = {"task": task, "episodes": k, "seed": seed, "transitions": len(u),
                       **jacobian_rel_error(A, B, P, A_l[pts], B_l[pts])}
                records.append(rec)
                print(f"{task} seed {seed} {k} ep: LTV label jac {rec['jac_rel']:.3f}",
                      flush=True)
    cells = {}
    for r in records:
        cells.setdefault(f"{r['task']} {r['episodes']}", []).append(r["jac_rel"])
    result = {"args": dataclasses.asdict(args), "records": records,
              "median_jac_rel": {c: float(np.median(v)) for c, v in cells.items()},
              "wall_s": time.perf_counter() - t0}
    pc.write_result(args.out, result)
    return result


def run(args: Args) -> dict:
    """The study (``--study labels``: :func:`label_study`); returns the JSON it writes."""
    if args.study == "labels":
        return label_study(args)
    torch.set_num_threads(args.threads)
    t0 = time.perf_counter()
    load_start = os.getloadavg()
    tasks = [t for t in args.tasks.split(",") if t]
    ks = sorted(int(k) for k in args.episodes.split(","))
    regs = [r for r in args.regularizations.split(",") if r]
    mcfg = ModelConfig(ensemble_size=args.members, hidden_layers=args.layers,
                       hidden_width=args.width)
    records: list[dict] = []
    data_info: dict = {}

    def summary() -> dict:
        """The JSON: settings, every record, the aggregates and their table, wall time, machine."""
        cells = aggregate(records, regs)
        return {"args": dataclasses.asdict(args),
                "model": {"members": args.members, "layers": args.layers, "width": args.width,
                          "activation": mcfg.activations[0], "formulation": mcfg.formulation},
                "data": data_info, "records": records, "aggregate": cells,
                "table_markdown": markdown_table(cells, regs), "wall_s": time.perf_counter() - t0,
                "machine": pc.machine_info(load_start)}

    for seed in range(args.seeds):  # seeds outermost: a run cut short keeps whole seeds
        for task in tasks:
            tic = time.perf_counter()
            episodes, ltvs = training_episodes(task, seed, ks[-1], args)
            test = collect(task, args.n_test, seed + 10_000, episode_steps=args.episode_steps,
                           states=True)
            pts, u, A, B, P = true_at_points(task, seed, test, args.jac_points)
            obs = np.concatenate([t.x[:-1] for t in test])
            data_info.setdefault(task, {})[seed] = {
                "episode_lengths": [t.T for t in episodes[:ks[-1]]],
                "test_transitions": len(u), "test_episodes": len(test)}
            for k in ks:
                train = episodes[:k]
                N = sum(t.T for t in train)
                tcfg = TrainConfig(steps=args.steps, batch=min(args.batch, N), lr=args.lr,
                                   eval_every=args.steps, seed=seed, progress=False)
                for reg in regs:
                    model = mcfg.build(train[0].n, train[0].m, seed=seed)
                    t_train = time.perf_counter()
                    hist = train_ensemble(model, train, tcfg, RegularizationConfig.named(reg),
                                          ltv_models=ltvs[:k])
                    t_train = time.perf_counter() - t_train
                    err = errors(model.freeze("float64").step, train, test)
                    A_hat, B_hat = model.freeze("float64").jacobians(obs[pts], u[pts])
                    rec = {"task": task, "episodes": k, "seed": seed, "reg": reg,
                           "transitions": N, "optimizer_steps": int(hist.steps),
                           "train_wall_s": t_train,
                           **{k: err[k] for k in ("rel_step", "nrmse", "nrmse_median_dim")},
                           **jacobian_rel_error(A, B, P, A_hat, B_hat)}
                    records.append(rec)
                    print(f"{task} seed {seed} {k} ep ({N} tr) {reg:8s}: jac {rec['jac_rel']:.3f} "
                          f"held-out {rec['rel_step']:.3f}  ({t_train:.1f} s)", flush=True)
            print(f"{task} seed {seed}: {time.perf_counter() - tic:.0f} s", flush=True)
            if args.out:  # what ran so far, in case the run is cut short
                write_json_atomic(args.out, summary())
    result = summary()
    print(result["table_markdown"])
    print(f"wall {result['wall_s']:.0f} s")
    pc.write_result(args.out, result)
    if args.plot:
        plot(result["aggregate"], records, regs, args.plot)
    return result


if __name__ == "__main__":
    main()
