"""Weight decay and the f / g formulations on random stable linear systems (paper Sec. IV and
Fig. "wd": rows without/with weight decay, columns f/g, all with sampled Jacobian propagation).

What it measures and how to run it: docs/experiments.md, section ``exp_weight_decay``.
"""

from __future__ import annotations

import dataclasses
from dataclasses import dataclass, field

import numpy as np

from agents.experiments import paper_common as pc

EXPERIMENT = "weight_decay"


@dataclass
class Args(pc.LinearRoundsArgs):
    """Weight decay x formulation (f, g) on random linear systems (paper Fig. wd)."""

    weight_decay: float = field(default=0.1, metadata={"help": "the strong weight decay"})
    weight_decay_mid: float = field(default=0.01, metadata={
        "help": "an intermediate weight decay (<= 0 to skip)"})
    method: str = field(default="sampled", metadata={"help": "regularization of all models"})
    original_bug: bool = field(default=True, metadata={
        "help": "also run on data with the original's last-state bug (no / strong decay)"})

    SMOKE = {"mc": 2, "rounds": 1, "epochs_per_round": 5, "n_val": 2, "weight_decay_mid": 0.0,
             "original_bug": False}


def config_name(formulation: str, wd: float, bug: bool = False) -> str:
    return f"{formulation}_wd{wd:g}" + ("_bug" if bug else "")


def make_configs(args: Args) -> dict[str, dict]:
    data = dataclasses.asdict(pc.LinearData(n_val=args.n_val))
    base = {"data": data, "rounds": args.rounds, "epochs_per_round": args.epochs_per_round,
            "lr": args.lr, "incremental": True, "method": args.method, "reg": {},
            "n_eig_store": 30}
    decays = [0.0] + ([args.weight_decay_mid] if args.weight_decay_mid > 0 else []) + [
        args.weight_decay]
    configs = {config_name(f, wd): {**base, "formulation": f, "weight_decay": wd}
               for f in ("f", "g") for wd in decays}
    if args.original_bug:  # the original's data (last training state 0), no/strong decay
        bug = {**base, "data": {**data, "last_state_zero": True}}
        configs.update({config_name(f, wd, True): {**bug, "formulation": f, "weight_decay": wd}
                        for f in ("f", "g") for wd in (0.0, args.weight_decay)})
    return configs


def eigen_figure(records: list[dict], wd_lo: float, wd_hi: float, bug: bool, path) -> bool:
    """The paper's 2x2 figure (rows no / strong weight decay, columns f / g) for the first
    MC run's system; False if no such records."""
    first = min(r["seed"] for r in records)
    panels = {(i, j): next((r["result"] for r in records if r["seed"] == first
                            and r["name"] == config_name(f, wd, bug)), None)
              for i, wd in enumerate((wd_lo, wd_hi)) for j, f in enumerate(("f", "g"))}
    shown = [p for p in panels.values() if p is not None]
    if not shown:
        return False
    limits = pc.eigen_limits([pc.complex_from_pairs(p["eig_learned"]) for p in shown],
                          pc.complex_from_pairs(shown[0]["eig_true"]))  # one scale for all
    plt = pc.pyplot()
    fig, axes = plt.subplots(2, 2, figsize=(8, 8.4))
    for (i, j), res in panels.items():
        if res is None:
            axes[i, j].set_visible(False)
            continue
        f, wd = ("f", "g")[j], (wd_lo, wd_hi)[i]
        pc.eigen_scatter(axes[i, j], pc.complex_from_pairs(res["eig_learned"]),
                      pc.complex_from_pairs(res["eig_true"]),
                      f"{f}, weight decay {wd:g}{', orig. data bug' if bug else ''}\n"
                      f"mean |l| {res['eig_mean_abs']:.3f}, "
                      f"mean |l-1| {res['eig_mean_dist_to_1']:.3f}", limits=limits)
    pc.save_figure(fig, path)
    return True


def report(records: list[dict], out, figures, args: Args) -> dict:
    plt = pc.pyplot()

    def order(n: str) -> tuple:
        f, rest = n.split("_wd")
        return (n.endswith("_bug"), f, float(rest.removesuffix("_bug")))

    names = sorted({r["name"] for r in records}, key=order)
    decays = sorted({r["config"]["weight_decay"] for r in records})
    wd_lo, wd_hi = decays[0], decays[-1]
    drawn = [name for bug, name in ((False, "weight_decay_eigenvalues.png"),
                                    (True, "weight_decay_eigenvalues_bug.png"))
             if eigen_figure(records, wd_lo, wd_hi, bug, figures / name)]

    fig, axes = plt.subplots(1, 4, figsize=(4 * (0.8 + 0.45 * len(names)), 4.2))
    for ax, key, label in zip(axes, ("eig_mean_abs", "eig_mean_dist_to_1", "eig_match_err",
                                     "jac_rms_entry"),
                              ("mean |eigenvalue|", "mean |eigenvalue - 1|",
                               "eigenvalue matching error", "Jacobian RMS per entry")):
        pc.violins(ax, {n: pc.values(records, n, key) for n in names}, ylabel=label)
    true_abs, true_d1 = (np.nanmean([r["result"][f"eig_true_{k}"] for r in records])
                         for k in ("mean_abs", "mean_dist_to_1"))
    for ax, v in zip(axes, (true_abs, true_d1)):
        ax.axhline(v, color="tab:red", lw=0.8, ls="--", label="true")
    axes[0].legend(fontsize=7)
    for ax in axes[2:]:
        ax.set_yscale("log")
    pc.save_figure(fig, figures / "weight_decay_errors.png")

    keys = ("eig_mean_abs", "eig_mean_dist_to_1", "eig_max_abs", "eig_match_err", "jac_err",
            "jac_rms_entry", "log10_pred_rms", "log10_sim_rms", "sim_diverged", "train_loss",
            "train_pred_rms", "wall", "cpu_time")
    summary = {"configs": pc.spreads(records, names, keys)}
    summary["true_eig_mean_abs"] = float(true_abs)
    summary["true_eig_mean_dist_to_1"] = float(true_d1)
    decay_keys = ("eig_mean_abs", "eig_mean_dist_to_1", "eig_match_err", "jac_err",
                  "log10_pred_rms", "log10_sim_rms")
    comp = {}
    for bug in (False, True):
        base = {f: config_name(f, wd_lo, bug) for f in ("f", "g")}
        comp.update(pc.compare_pairs(records, [(config_name(f, wd, bug), base[f]) for f in base
                                               for wd in decays[1:]], decay_keys))
        comp.update(pc.compare_pairs(records, [(base["g"], base["f"])], (
            "eig_match_err", "jac_err", "log10_pred_rms", "log10_sim_rms", "train_pred_rms")))
    summary["comparisons"] = comp
    summary["figures"] = [*drawn, "weight_decay_errors.png"]
    return summary


def main(argv: list[str] | None = None) -> None:
    """The command line (``python -m agents.experiments.exp_weight_decay``): parse, run, print."""
    args = pc.parse_args(Args, argv)
    summary = pc.run_experiment(args, EXPERIMENT, pc.run_linear, make_configs(args), report)
    pc.print_medians(summary["configs"], {
        "mean|l|": "eig_mean_abs:.3f", "mean|l-1|": "eig_mean_dist_to_1:.3f",
        "eig err": "eig_match_err:.3f", "jac": "jac_rms_entry:.4f"}, 14)


if __name__ == "__main__":
    main()
