"""The two-link robot: prediction, simulation and Jacobian errors without and with
tangent-space regularization (paper Sec. V-C, Figs. "valerr" and "jacerr").

What it measures and how to run it: docs/experiments.md, section ``exp_robot``.
"""

from __future__ import annotations

import dataclasses
from dataclasses import dataclass, field

import numpy as np

from agents.experiments import paper_common as pc

EXPERIMENT = "robot"
METHODS = ("none", "sampled", "exact", "smooth")
#: epoch controls, name -> (method, epoch factor, reg): the paper halves the epochs with sampled
#: JacProp; these two configs separate the effect of JacProp from the effect of the epoch count
CONTROLS = {"none_half": ("none", 0.5, {}), "sampled_full": ("sampled", 2.0, {})}
#: the original code's batching: each perturbed copy its own optimizer step, so sampled JacProp
#: at the paper's half epochs takes exactly as many optimizer steps as none at full epochs
OWN_BATCH = {"sampled_own": ("sampled", 1.0, {"copies_batch": "own"})}
LABELS = {"none": "none", "sampled": "sampled JacProp", "exact": "exact LTV match",
          "smooth": "exact smoothness", "none_half": "none", "sampled_full": "sampled JacProp",
          "sampled_own": "sampled, own batches"}


@dataclass
class Args(pc.TrainingArgs):
    """Robot arm: errors over Monte-Carlo runs for no / sampled / exact regularization."""

    mc: int = field(default=35, metadata={"help": "Monte-Carlo runs (paper: 35)"})
    formulation: str = field(default="g", metadata={"help": "f or g"})
    epoch_scale: float = field(default=1.0, metadata={
        "help": "multiplies the paper's epochs (g: 1000, 500 with sampled JacProp)"})
    exact_weight: float = field(default=0.01, metadata={"help": "weight of the LTV match"})
    smooth_weight: float = field(default=0.01, metadata={
        "help": "weight of the smoothness penalty (original two-link AD script: 0.01)"})
    epoch_controls: bool = field(default=True, metadata={
        "help": "also run none with half and sampled with full epochs"})
    own_batch_control: bool = field(default=True, metadata={
        "help": "also run sampled JacProp with the original's batching (copies in their own "
                "optimizer steps: equal steps with none)"})
    truth_diagnostics: bool = field(default=False, metadata={
        "help": "only compute what caps the Jacobian error (constant matrix, analytic twin, "
                "LTV labels per row group) over the MC seeds, into <out>/truth.json"})
    still_speed: float = field(default=0.05, metadata={
        "help": "joint speed [rad/s] below which a point counts as near-zero velocity"})

    SMOKE = {"mc": 2, "epoch_scale": 0.01, "n_val": 2, "epoch_controls": False,
             "own_batch_control": False}


def make_configs(args: Args) -> dict[str, dict]:
    data = dataclasses.asdict(pc.RobotData(n_val=args.n_val))
    reg = {"none": {}, "sampled": {}, "exact": {"exact_weight": args.exact_weight},
           "smooth": {"smooth_weight": args.smooth_weight}}
    configs = {m: {"data": data, "formulation": args.formulation, "method": m, "reg": reg[m],
                   "epochs": pc.nominal_epochs(args.formulation, m, args.epoch_scale),
                   "lr": args.lr, "model": {}}
               for m in METHODS}
    extra = {**(CONTROLS if args.epoch_controls else {}),
             **(OWN_BATCH if args.own_batch_control else {})}
    for name, (m, factor, reg_kwargs) in extra.items():
        configs[name] = {**configs[m], "reg": reg_kwargs, "epochs": pc.nominal_epochs(
            args.formulation, m, args.epoch_scale * factor)}
    return configs


def report(records: list[dict], out, figures, args: Args) -> dict:
    plt = pc.pyplot()
    names = [m for m in LABELS if any(r["name"] == m for r in records)]
    n_runs = {n: sum(r["name"] == n for r in records) for n in names}
    epochs = {r["name"]: r["config"]["epochs"] for r in records}
    groups = {f"{LABELS[n]} ({epochs[n]} ep.)": n for n in names}
    div = {k: f"diverged {int(pc.values(records, n, 'sim_diverged').sum())}"
           for k, n in groups.items()}
    fig, axes = plt.subplots(1, 3, figsize=(3 * (1.2 + 0.9 * len(names)), 4.6))
    for ax, (key, ylabel, title) in zip(axes, (
            ("log10_pred_rms", "log10 one-step prediction RMS", "prediction (validation)"),
            ("log10_sim_rms", "log10 simulation RMS", "simulation (validation)"),
            ("jac_err", "Jacobian error, paper eq. (jacerr)", "Jacobian"))):
        pc.violins(ax, {k: pc.values(records, n, key) for k, n in groups.items()}, ylabel=ylabel,
                   title=title, annotate=div if key == "log10_sim_rms" else None)
    formulations = ", ".join(sorted({r["config"]["formulation"] for r in records}))
    fig.suptitle(f"two-link robot, {formulations} ensemble, "
                 f"{max(n_runs.values())} Monte-Carlo runs per violin", fontsize=10)
    pc.save_figure(fig, figures / "robot_errors.png")

    keys = ("pred_rms", "log10_pred_rms", "sim_rms", "log10_sim_rms", "sim_diverged", "jac_err",
            "jac_rms_entry", "eig_match_err", "train_loss", "train_pred_rms", "train_time", "wall",
            "cpu_time")
    summary = {"configs": pc.spreads(records, names, keys)}
    for n in names:
        diverged = pc.values(records, n, "sim_diverged")
        summary["configs"][n].update(
            diverged_simulations=int(diverged.sum()),
            runs_with_divergence=int((diverged > 0).sum()),
            n_simulations=int(pc.values(records, n, "n_sim").sum()))
    compare = ("log10_pred_rms", "log10_sim_rms", "jac_err", "train_pred_rms")
    # the original's batching: equal optimizer steps with none
    summary.update(pc.compare_pairs(records, [("sampled_own", "none")], compare))
    summary["vs_none"] = {n: pc.compare(records, n, "none", compare)
                          for n in names if n != "none"}
    # same epoch count: JacProp's effect without the halved-epochs confound
    summary.update(pc.compare_pairs(records, [("sampled", "none_half"), ("sampled_full", "none")],
                                    compare))
    summary["figures"] = ["robot_errors.png"]
    return summary


def truth_diagnostics(args: Args) -> dict:
    """:func:`paper_common.robot_truth_diagnostics` over seeds ``0..mc-1``, with the median and
    quartiles of each quantity; written to ``<out>/truth.json``."""
    cfg = pc.RobotData(n_val=args.n_val)
    per_seed = [pc.robot_truth_diagnostics(cfg, s, args.still_speed) for s in range(args.mc)]
    summary = {"per_seed": per_seed, "still_speed": args.still_speed,
               "summary": {k: pc.spread(np.array([p[k] for p in per_seed])) for k in per_seed[0]}}
    pc.write_result(pc.output_dirs(args, EXPERIMENT)[0] / "truth.json", summary)
    return summary


def main(argv: list[str] | None = None) -> None:
    """The command line (``python -m agents.experiments.exp_robot``): parse, run, print."""
    args = pc.parse_args(Args, argv)
    if args.truth_diagnostics:
        for k, v in truth_diagnostics(args)["summary"].items():
            print(f"{k:12s} median {v['median']:.3f} [{v['q1']:.3f}, {v['q3']:.3f}]")
        raise SystemExit(0)
    summary = pc.run_experiment(args, EXPERIMENT, pc.run_robot, make_configs(args), report)
    for name, s in summary["configs"].items():
        med = {k: s[k].get("median", np.nan) for k in ("log10_pred_rms", "log10_sim_rms",
                                                       "jac_err")}
        print(f"{name:8s} log10 pred {med['log10_pred_rms']:.3f} log10 sim "
              f"{med['log10_sim_rms']:.3f} jac {med['jac_err']:.3f} diverged "
              f"{s['diverged_simulations']}/{s['n_simulations']}")


if __name__ == "__main__":
    main()
