"""Deviations from the nominal model (paper appendix B): for each deviation, the direction of
change of prediction, simulation and Jacobian error against the nominal model, for f and g.

What it measures and how to run it: docs/experiments.md, section ``exp_deviations``.
"""

from __future__ import annotations

import dataclasses
from dataclasses import dataclass, field

import numpy as np

from agents.experiments import paper_common as pc

EXPERIMENT = "deviations"
METRICS = ("log10_pred_rms", "log10_sim_rms", "log10_jac_err")
METRIC_LABELS = {"log10_pred_rms": "prediction", "log10_sim_rms": "simulation",
                 "log10_jac_err": "Jacobian"}
#: deviation name -> (description, changes to data / model / regularization)
DEVIATIONS = {
    "nominal": ("nominal model", {}, {}, {}),
    "dt_slow": ("sampling 5x slower (dt 0.1 s)", {"dt": 0.1}, {}, {}),
    "dt_fast": ("sampling 5x faster (dt 0.004 s)", {"dt": 0.004}, {}, {}),
    "width_x2": ("neurons x2 (40)", {}, {"width": 40}, {}),
    "width_x0.5": ("neurons x0.5 (10)", {}, {"width": 10}, {}),
    "depth_2": ("one more layer", {}, {"depth": 2}, {}),
    "dropout": ("dropout 20 %", {}, {"dropout": 0.2}, {}),
    "layer_norm": ("layer normalization", {}, {"layer_norm": True}, {}),
    "noise_x10": ("measurement noise x10 (0.1)", {"noise_std": 0.1}, {}, {}),
    "ensemble_x3": ("ensemble size x3 (12)", {}, {"repeat": 3}, {}),
    "copies_5": ("5 perturbed copies", {}, {}, {"n_copies": 5}),
}


@dataclass
class Args(pc.TrainingArgs):
    """Deviations from the nominal model: direction of change of the errors (paper app. B)."""

    mc: int = field(default=16, metadata={"help": "Monte-Carlo runs per deviation"})
    deviations: str = field(default=",".join(DEVIATIONS), metadata={
        "help": "comma-separated deviations to run (nominal is always included)"})
    formulations: str = field(default="f,g", metadata={"help": "comma-separated formulations"})
    method: str = field(default="sampled", metadata={"help": "regularization of all models"})
    epoch_scale: float = field(default=1.0, metadata={"help": "multiplies the epochs"})
    alpha: float = field(default=0.05, metadata={"help": "significance level of a direction"})

    SMOKE = {"mc": 2, "epoch_scale": 0.01, "n_val": 2,
             "deviations": "nominal,dt_slow"}


def make_configs(args: Args) -> dict[str, dict]:
    names = ["nominal"] + [d for d in pc.comma_list("deviations", args.deviations, empty=True,
                                                    allowed=list(DEVIATIONS)) if d != "nominal"]
    configs = {}
    for f in pc.comma_list("formulations", args.formulations, allowed=["f", "g"]):
        for name in names:
            _, data_kw, model_kw, reg_kw = DEVIATIONS[name]
            data = dataclasses.asdict(pc.RobotData(n_val=args.n_val, **data_kw))
            model = {"activations": list(pc.NOMINAL_ACTIVATIONS), **model_kw}
            configs[f"{f}_{name}"] = {
                "data": data, "formulation": f, "method": args.method, "reg": reg_kw,
                "epochs": pc.nominal_epochs(f, args.method, args.epoch_scale), "lr": args.lr,
                "model": model, "deviation": name}
    return configs


def direction(comp: dict, alpha: float) -> str:
    """'+' (error up, worse), '-' (down, better) or '~' (not significant at ``alpha``)."""
    p, d = comp.get("p_value"), comp.get("median_diff")
    if p is None or d is None or p >= alpha:
        return "~"
    return "+" if d > 0 else "-"


def report(records: list[dict], out, figures, args: Args) -> dict:
    plt = pc.pyplot()
    present = {r["name"] for r in records}
    forms = [f for f in ("f", "g") if f"{f}_nominal" in present]
    devs = [d for d in DEVIATIONS if any(f"{f}_{d}" in present for f in forms)]
    alpha = args.alpha
    table = {}
    for d in devs:
        row = {"description": DEVIATIONS[d][0]}
        for f in forms:
            name = f"{f}_{d}"
            if name not in present:
                continue
            row[f] = pc.spreads(records, [name], (*METRICS, "train_time", "cpu_time",
                                                  "train_pred_rms", "pred_rms", "sim_rms",
                                                  "jac_err"))[name]
            row[f]["diverged"] = int(pc.values(records, name, "sim_diverged").sum())
            if d != "nominal":
                row[f"{f}_vs_nominal"] = pc.compare(records, name, f"{f}_nominal", METRICS)
        if all(f"{f}_{d}" in present for f in ("f", "g")):
            row["g_vs_f"] = pc.compare(records, f"g_{d}", f"f_{d}", (*METRICS, "train_pred_rms"))
        table[d] = row

    # the table as markdown (also pasted into docs/RESULTS.md)
    head = "| deviation | " + " | ".join(
        f"{f}: {METRIC_LABELS[k]}" for f in forms for k in METRICS) + " | g vs f (pred/sim/jac) |"
    lines = [head, "|" + "---|" * (2 + len(forms) * len(METRICS))]
    for d in devs:
        row = table[d]
        cells = []
        for f in forms:
            for k in METRICS:
                if d == "nominal":
                    s = row.get(f, {}).get(k, {})
                    cells.append(f"{s.get('median', float('nan')):.2f}" if s else "")
                else:
                    c = row.get(f"{f}_vs_nominal", {}).get(k)
                    cells.append(_cell(c, alpha) if c else "")
        gf = row.get("g_vs_f")
        gf_cell = " / ".join(_cell(gf[k], alpha) for k in METRICS) if gf else ""
        lines.append(f"| {row['description']} | " + " | ".join(cells) + f" | {gf_cell} |")
    markdown = "\n".join(lines)
    (out / "table.md").write_text(markdown + "\n")

    # figure: paired median change of log10 error vs nominal, per deviation and formulation
    others = [d for d in devs if d != "nominal"]
    fig, axes = plt.subplots(1, len(METRICS), figsize=(15, 0.45 * max(len(others), 2) + 1.8),
                             sharey=True)
    ypos = np.arange(len(others))
    for ax, k in zip(axes, METRICS):
        for i, f in enumerate(forms):
            comps = [table[d].get(f"{f}_vs_nominal", {}).get(k, {}) for d in others]
            med = np.array([c.get("median_diff") for c in comps], dtype=float)  # None: nan
            bars = ax.barh(ypos + (i - 0.5 * (len(forms) - 1)) * 0.38, med, height=0.36,
                           label=f, color=f"C{i}")
            for bar, c in zip(bars, comps):  # faint: not significant at alpha
                if direction(c, alpha) == "~":
                    bar.set_alpha(0.3)
        ax.axvline(0, color="k", lw=0.8)
        ax.set_title(f"{METRIC_LABELS[k]}: median paired change of log10 error\n"
                     f"(faint: not significant, Wilcoxon p >= {alpha:g})", fontsize=9)
        ax.set_xlabel("< better | worse >")
    axes[0].set_yticks(ypos, [DEVIATIONS[d][0] for d in others])
    axes[0].invert_yaxis()
    axes[-1].legend(title="formulation", fontsize=8)
    pc.save_figure(fig, figures / "deviations.png")

    return {"alpha": alpha, "table": table, "markdown": markdown,
            "n_runs": {n: int(sum(r["name"] == n for r in records)) for n in sorted(present)},
            "figures": ["deviations.png"]}


def _cell(comp: dict, alpha: float) -> str:
    d = comp.get("median_diff")
    if d is None:
        return "n/a"
    p = comp.get("p_value")
    return f"{direction(comp, alpha)} ({d:+.2f}{'' if p is None else f', p={p:.2g}'})"


def main(argv: list[str] | None = None) -> None:
    """The command line (``python -m agents.experiments.exp_deviations``): parse, run, print."""
    args = pc.parse_args(Args, argv)
    summary = pc.run_experiment(args, EXPERIMENT, pc.run_robot, make_configs(args), report)
    print(summary["markdown"])


if __name__ == "__main__":
    main()
