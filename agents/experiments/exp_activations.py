"""Comparison of activation functions (paper appendix A, Fig. "activations").

What it measures and how to run it: docs/experiments.md, section ``exp_activations``.
"""

from __future__ import annotations

import dataclasses
from dataclasses import dataclass, field

import numpy as np

from agents.experiments import paper_common as pc

EXPERIMENT = "activations"


@dataclass
class Args(pc.TrainingArgs):
    """Activation functions: log prediction error after 20 / 500 / 1500 epochs."""

    mc: int = field(default=200, metadata={"help": "Monte-Carlo runs (paper: 200)"})
    formulation: str = field(default="g", metadata={"help": "f or g"})
    checkpoints: str = field(default="20,500,1500", metadata={
        "help": "comma-separated epochs at which the error is recorded"})
    width: int = field(default=20, metadata={"help": "hidden units"})

    SMOKE = {"mc": 2, "checkpoints": "2,5,10", "n_val": 2}


def make_configs(args: Args) -> dict[str, dict]:
    checkpoints = [int(c) for c in args.checkpoints.split(",")]
    if sorted(checkpoints) != checkpoints or checkpoints[0] < 1:
        raise ValueError(f"--checkpoints must be increasing epochs >= 1, got {args.checkpoints}")
    return {f"all_{args.formulation}": {
        "data": dataclasses.asdict(pc.RobotData(n_val=args.n_val)),
        "formulation": args.formulation, "activations": list(pc.ALL_ACTIVATIONS),
        "width": args.width, "checkpoints": checkpoints, "lr": args.lr}}


def log_errors(records: list[dict]) -> tuple[list[int], dict[str, np.ndarray]]:
    """``checkpoints`` and ``{activation: [runs, checkpoints]}`` log10 prediction RMS."""
    first = records[0]["result"]
    with np.errstate(divide="ignore", invalid="ignore"):  # None: nan
        return first["checkpoints"], {a: np.log10(np.array(
            [r["result"]["pred_rms"][a] for r in records], dtype=float)) for a in first["pred_rms"]}


def report(records: list[dict], out, figures, args: Args) -> dict:
    plt = pc.pyplot()
    checkpoints, logs = log_errors(records)
    fig, axes = plt.subplots(1, len(checkpoints), figsize=(4.6 * len(checkpoints), 3.8))
    for j, (ax, c) in enumerate(zip(np.atleast_1d(axes), checkpoints)):
        data = {a: v[:, j] for a, v in logs.items()}
        # crop extreme values as the paper's figure (1st-99th percentile of all activations)
        pooled = np.concatenate([d[np.isfinite(d)] for d in data.values()])
        if pooled.size:
            lo, hi = np.percentile(pooled, [1, 99])
            data = {a: d[(d >= lo) & (d <= hi)] for a, d in data.items()}
        pc.violins(ax, data, ylabel="log10 prediction RMS" if j == 0 else "",
                title=f"after {c} epochs")
    fig.suptitle(f"{len(records)} Monte-Carlo runs per violin", fontsize=10)
    pc.save_figure(fig, figures / "activations.png")

    summary = {"checkpoints": checkpoints, "n_runs": len(records),
               "log10_pred_rms": {a: [pc.spread(v[:, j]) for j in range(len(checkpoints))]
                                  for a, v in logs.items()}}
    # rank of each activation per run at each checkpoint (1 = best), averaged
    stack = np.stack([logs[a] for a in logs])  # [A, runs, C]
    ranks = np.argsort(np.argsort(np.where(np.isfinite(stack), stack, np.inf), 0), 0) + 1
    summary["mean_rank"] = {a: ranks[i].mean(0).tolist() for i, a in enumerate(logs)}
    summary["comparisons"] = {
        f"{a}_vs_{smooth}@{c}": pc.paired_comparison(logs[a][:, j], logs[smooth][:, j])
        for j, c in enumerate(checkpoints) for a in ("relu", "leaky_relu") if a in logs
        for smooth in ("tanh", "elu")}
    summary["figures"] = ["activations.png"]
    return summary


def main(argv: list[str] | None = None) -> None:
    """The command line (``python -m agents.experiments.exp_activations``): parse, run, print."""
    args = pc.parse_args(Args, argv)
    summary = pc.run_experiment(args, EXPERIMENT, pc.run_activations, make_configs(args),
                                report)
    for a, per_c in summary["log10_pred_rms"].items():
        meds = " ".join(f"{s.get('median', float('nan')):7.3f}" for s in per_c)
        print(f"{a:11s} median log10 pred RMS at {summary['checkpoints']}: {meds}  "
              f"mean rank {np.round(summary['mean_rank'][a], 2).tolist()}")


if __name__ == "__main__":
    main()
