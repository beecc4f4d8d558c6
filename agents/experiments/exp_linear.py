"""Random stable linear systems: learned Jacobian eigenvalues and errors without and with
tangent-space regularization (paper Sec. V-B, Algorithm 2, Fig. "jacpropeig").

What it measures and how to run it: docs/experiments.md, section ``exp_linear``.
"""

from __future__ import annotations

import dataclasses
from dataclasses import dataclass, field

import numpy as np

from agents.experiments import paper_common as pc

EXPERIMENT = "linear"
METHODS = ("none", "sampled", "exact", "smooth")
LABELS = {"none": "none", "sampled": "sampled", "exact": "exact-LTV", "smooth": "smooth",
          "none_bug": "none+bug", "sampled_bug": "sampled+bug"}
#: The original code's Jacobian RMS per entry after training rounds 1..3 (JP README figure,
#: original_implementation.md section 5); round 1 without JacProp is a lower bound (clipped bar).
ORIGINAL = {"none": [0.147, 0.082, 0.074], "sampled": [0.058, 0.040, 0.041]}


@dataclass
class Args(pc.LinearRoundsArgs):
    """Random stable linear systems: eigenvalues and errors without/with tangent-space
    regularization (paper Fig. jacpropeig)."""

    exact_weight: float = field(default=1.0, metadata={"help": "weight of the LTV match"})
    smooth_weight: float = field(default=0.15, metadata={
        "help": "weight of the smoothness penalty (original linear_eigvals: 0.15)"})
    original_bug: bool = field(default=True, metadata={
        "help": "also run none/sampled on data with the original's last-state bug"})

    SMOKE = {"mc": 2, "rounds": 1, "epochs_per_round": 5, "n_val": 2, "original_bug": False}


def make_configs(args: Args) -> dict[str, dict]:
    data = dataclasses.asdict(pc.LinearData(n_val=args.n_val))
    base = {"data": data, "formulation": "g", "rounds": args.rounds,
            "epochs_per_round": args.epochs_per_round, "lr": args.lr, "weight_decay": 0.0,
            "incremental": True, "n_eig_store": 30}
    reg = {"none": {}, "sampled": {}, "exact": {"exact_weight": args.exact_weight},
           "smooth": {"smooth_weight": args.smooth_weight}}
    configs = {m: {**base, "method": m, "reg": reg[m]} for m in METHODS}
    if args.original_bug:
        bug = {**base, "data": {**data, "last_state_zero": True}}
        configs["none_bug"] = {**bug, "method": "none", "reg": {}}
        configs["sampled_bug"] = {**bug, "method": "sampled", "reg": {}}
    return configs


def report(records: list[dict], out, figures, args: Args) -> dict:
    plt = pc.pyplot()
    names = [n for n in LABELS if any(r["name"] == n for r in records)]
    methods = [n for n in METHODS if n in names]

    # Fig. 1 (paper Fig. jacpropeig): eigenvalues of the learned A at validation points, first
    # MC run (one random system), learned (blue) vs true (red); bottom row: offset of each
    # learned eigenvalue from the nearest true one (the spread is too small to see on top)
    first = min(r["seed"] for r in records)
    shown = {n: next(r["result"] for r in records if r["name"] == n and r["seed"] == first)
             for n in names}
    learned = {n: pc.complex_from_pairs(res["eig_learned"]) for n, res in shown.items()}
    true = pc.complex_from_pairs(shown[names[0]]["eig_true"])
    limits = pc.eigen_limits(list(learned.values()), true)
    offsets = {n: (ev.ravel() - true[np.argmin(np.abs(ev.ravel()[:, None] - true[None]), 1)])
               for n, ev in learned.items()}
    # one offset scale for the clean-data methods and one for the original-bug variants
    half = {}
    for bug in (False, True):
        group = [offsets[n] for n in names if n.endswith("_bug") == bug]
        if group:
            half[bug] = 1.1 * max(np.percentile(np.abs(np.concatenate(group)), 99), 1e-4)
    fig, axes = plt.subplots(2, len(names), figsize=(3.1 * len(names), 6.4), squeeze=False)
    for j, name in enumerate(names):
        pc.eigen_scatter(axes[0, j], learned[name], true,
                      f"{LABELS[name]}\neig. error {shown[name]['eig_match_err']:.3f}",
                      limits=limits)
        ax, h = axes[1, j], half[name.endswith("_bug")]
        ax.plot(offsets[name].real, offsets[name].imag, ".", ms=2, alpha=0.4)
        ax.plot([0], [0], "o", ms=4, mfc="none", color="tab:red")
        ax.set(xlim=(-h, h), ylim=(-h, h), aspect="equal", xlabel="Re (learned - nearest true)",
               ylabel="Im")
        ax.tick_params(labelsize=7)
    pc.save_figure(fig, figures / "linear_eigenvalues.png")

    # Fig. 2: error distributions over the MC runs
    fig, axes = plt.subplots(1, 4, figsize=(15, 3.8))
    groups = {LABELS[n]: n for n in names}
    div = {LABELS[n]: f"div {int(pc.values(records, n, 'sim_diverged').sum())}" for n in names}
    for ax, (key, ylabel) in zip(axes, (
            ("log10_pred_rms", "log10 prediction RMS"), ("log10_sim_rms", "log10 simulation RMS"),
            ("jac_rms_entry", "Jacobian RMS per entry"),
            ("eig_match_err", "eigenvalue matching error"))):
        pc.violins(ax, {k: pc.values(records, n, key) for k, n in groups.items()}, ylabel=ylabel,
                   annotate=div if key == "log10_sim_rms" else None)
    for ax in axes[2:]:
        ax.set_yscale("log")
    pc.save_figure(fig, figures / "linear_errors.png")

    # Fig. 3: Jacobian RMS per entry after each training round vs the original's numbers
    fig, ax = plt.subplots(figsize=(6, 4))
    per_round = {n: np.array([[rd["jac_rms_entry"] for rd in r["result"]["rounds"]]
                              for r in records if r["name"] == n], dtype=float) for n in names}
    for name in names:
        med = np.nanmedian(per_round[name], 0)
        q1, q3 = np.nanpercentile(per_round[name], [25, 75], axis=0)
        ax.errorbar(np.arange(1, len(med) + 1), med, yerr=[med - q1, q3 - med], marker="o",
                    capsize=3, label=LABELS[name])
    for name, vals in ORIGINAL.items():
        ax.plot(np.arange(1, 4), vals, "k--" if name == "none" else "k:", marker="x",
                label=f"original code, {LABELS[name]}")
    ax.set(yscale="log", xticks=np.arange(1, len(records[0]["result"]["rounds"]) + 1),
           xlabel="training round (= number of training trajectories)",
           ylabel="Jacobian RMS per entry")
    ax.legend(fontsize=7)
    pc.save_figure(fig, figures / "linear_rounds.png")

    keys = ("jac_err", "jac_rms_entry", "eig_match_err", "pred_rms", "log10_pred_rms",
            "sim_rms", "log10_sim_rms", "sim_diverged", "train_loss", "train_pred_rms", "wall",
            "cpu_time")
    summary = {"configs": pc.spreads(records, names, keys)}
    for n in names:
        summary["configs"][n]["jac_rms_entry_rounds_median"] = np.nanmedian(
            per_round[n], 0).tolist()
    summary["vs_none"] = {
        n: pc.compare(records, n, "none", ("jac_err", "eig_match_err", "log10_pred_rms",
                                           "log10_sim_rms", "train_loss"))
        for n in methods if n != "none"}
    if "sampled_bug" in names and "none_bug" in names:
        summary["bug_sampled_vs_none"] = pc.compare(
            records, "sampled_bug", "none_bug", ("jac_err", "log10_pred_rms", "log10_sim_rms"))
    summary["original_jac_rms_entry_rounds"] = ORIGINAL
    summary["figures"] = ["linear_eigenvalues.png", "linear_errors.png", "linear_rounds.png"]
    return summary


def main(argv: list[str] | None = None) -> None:
    """The command line (``python -m agents.experiments.exp_linear``): parse, run, print."""
    args = pc.parse_args(Args, argv)
    summary = pc.run_experiment(args, EXPERIMENT, pc.run_linear, make_configs(args), report)
    pc.print_medians(summary["configs"], {"jac_rms_entry": "jac_rms_entry:.4f",
                                          "pred": "pred_rms:.4f", "sim": "sim_rms:.3f"}, 12)


if __name__ == "__main__":
    main()
