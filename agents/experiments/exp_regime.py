"""Regime sweep of the robot Jacobian claim: where does sampled Jacobian propagation lower the
two-link arm's Jacobian error, and why not elsewhere?

What it measures and how to run it: docs/experiments.md, section ``exp_regime``.
"""

from __future__ import annotations

import dataclasses
from dataclasses import dataclass, field
from pathlib import Path
from typing import Literal

import numpy as np

from agents.experiments import paper_common as pc

EXPERIMENT = "regime"
METHOD_LABELS = {"none": "none", "sampled": "sampled JacProp", "exact": "exact LTV match",
                 "oracle": "sampled, true-Jacobian labels (oracle)",
                 "prior": "sampled, LTV fused with network prior"}


@dataclass
class Args(pc.TrainingArgs):
    """Regime sweep of the robot Jacobian error: none vs sampled JacProp (and label variants)."""

    mc: int = field(default=8, metadata={"help": "Monte-Carlo runs per cell"})
    workers: int = field(default=1, metadata={"help": "parallel worker processes"})
    n_trains: str = field(default="1,3,10", metadata={"help": "training trajectories"})
    epochs: str = field(default="1000,5000", metadata={"help": "epochs (= optimizer steps)"})
    windows: str = field(default="short,paper", metadata={"help": "excitation windows"})
    frictions: str = field(default="on,off", metadata={"help": "Coulomb friction on/off"})
    label_cells: str = field(default="paper-on", metadata={
        "help": "window-friction cells that also run oracle, exact and prior"})
    label_n_trains: str = field(default="3", metadata={
        "help": "training-trajectory counts of the label cells"})
    activations: str = field(default="tanh", metadata={
        "help": "ensemble members (comma list; paper: elu,sigmoid,tanh,swish)"})
    width: int = field(default=20, metadata={"help": "hidden units per member"})
    batch: Literal["full", "trajectory"] = field(default="full", metadata={
        "help": "full (one step/epoch) or trajectory"})
    exact_weight: float = field(default=0.01, metadata={"help": "weight of the LTV match"})
    prior_scale: float = field(default=1.0, metadata={
        "help": "prior covariance / LTV posterior covariance for the fused labels"})
    still_speed: float = field(default=0.05, metadata={
        "help": "joint speed [rad/s] below which a point counts as near-zero velocity"})
    n_log: int = field(default=5, metadata={"help": "training-point Jacobian checkpoints"})
    paper_protocol: bool = field(default=True, metadata={
        "help": "also run the paper cell with the paper's protocol (4-member nominal ensemble, "
                "one step per trajectory) for none, sampled and oracle labels"})
    duration: float = field(default=4.0, metadata={"help": "trajectory length [s]"})

    SMOKE = {"mc": 2, "n_trains": "2", "epochs": "3,6", "duration": 1.0, "n_val": 2,
             "n_log": 2, "label_n_trains": "2"}

    def __post_init__(self) -> None:
        """The comma-list options, each named when it is wrong (before any run starts), kept
        parsed in ``self.lists``."""
        from mbtsr.ensemble import ACTIVATIONS

        super().__post_init__()
        n_trains = pc.comma_list("n-trains", self.n_trains, int)
        cells = pc.comma_list("label-cells", self.label_cells, empty=True, allowed=[  # '': none
            f"{w}-{f}" for w in pc.EXCITATION_WINDOWS for f in ("on", "off")])
        self.lists = {
            "n_trains": n_trains, "epochs": pc.comma_list("epochs", self.epochs, int),
            "windows": pc.comma_list("windows", self.windows,
                                     allowed=list(pc.EXCITATION_WINDOWS)),
            "frictions": pc.comma_list("frictions", self.frictions, allowed=["on", "off"]),
            "label_cells": {tuple(c.split("-")) for c in cells},
            "label_n_trains": pc.comma_list("label-n-trains (a subset of --n-trains)",
                                            self.label_n_trains, int,
                                            allowed=n_trains if cells else None),
            "activations": pc.comma_list("activations", self.activations,
                                         allowed=list(ACTIVATIONS))}


def cell_name(method: str, n_train: int, epochs: int, window: str, friction: bool) -> str:
    return f"{method}.n{n_train}.e{epochs}.{window}.{'fric' if friction else 'nofric'}"


def make_configs(args: Args) -> dict[str, dict[str, dict]]:
    """``{"main": {name: config}, "labels": {...}, "paper_protocol": {...}}``: the none/sampled
    grid, the label-variant cells and the paper cell under the paper's protocol."""
    lists = args.lists
    n_trains, epochs, label_n_trains = lists["n_trains"], lists["epochs"], lists["label_n_trains"]
    model = {"activations": lists["activations"], "width": args.width}
    out: dict[str, dict[str, dict]] = {"main": {}, "labels": {}, "paper_protocol": {}}
    for window in lists["windows"]:
        for friction in [{"on": True, "off": False}[f] for f in lists["frictions"]]:
            base = {"data": dataclasses.asdict(pc.RegimeData(
                window=window, friction=friction, duration=args.duration,
                n_train_max=max(n_trains), n_val=args.n_val)),
                "exact_weight": args.exact_weight, "prior_scale": args.prior_scale,
                "lr": args.lr, "still_speed": args.still_speed, "n_log": args.n_log}
            label = (window, "on" if friction else "off") in lists["label_cells"]
            for n in n_trains:
                methods = {"main": ["none", "sampled"],
                           "labels": ["oracle", "exact", "prior"]
                           if label and n in label_n_trains else []}
                for e in epochs:
                    for part, ms in methods.items():
                        for m in ms:
                            out[part][cell_name(m, n, e, window, friction)] = {
                                **base, "n_train": n, "epochs": e, "method": m,
                                "batch": args.batch, "model": model}
            if args.paper_protocol and label:
                n, e = label_n_trains[0], min(epochs)
                for m in ("none", "sampled", "oracle"):
                    name = f"paperprotocol.{cell_name(m, n, e, window, friction)}"
                    out["paper_protocol"][name] = {
                        **base, "n_train": n, "epochs": e, "method": m, "batch": "trajectory",
                        "model": {}, "paper_protocol": True}
    return out


# ------------------------------------------------------------------------------------------------
# report


def _cell_of(record: dict) -> tuple:
    """A run's cell: ``(window, friction, n_train, epochs)``."""
    c = record["config"]
    return c["data"]["window"], c["data"]["friction"], c["n_train"], c["epochs"]


def _family_order(k: tuple) -> tuple:
    """Short window first, friction first; then trajectories and epochs (for a whole cell)."""
    return (k[0] != "short", not k[1], *k[2:])


def _cells(records: list[dict]) -> list[tuple]:
    return sorted({_cell_of(r) for r in records}, key=_family_order)


def _by_seed(records: list[dict], method: str, cell: tuple, key: str) -> dict[int, float]:
    """``{seed: value}`` of ``key`` for ``method`` in ``cell``; ``net_train_{pos,vel}``: the
    network's own Jacobian error at the training points at the end of training."""
    out = {}
    for r in records:
        if r["config"]["method"] == method and _cell_of(r) == cell:
            res = r["result"]
            v = (res["net_train_jac"][key[10:]][-1] if key.startswith("net_train_")
                 else res.get(key))
            if v is not None:
                out[r["seed"]] = float(v)
    return out


def _paired(records, method: str, cell: tuple, key: str) -> tuple[np.ndarray, np.ndarray]:
    """``key`` of ``method`` and of none in ``cell``, over the seeds both have."""
    a, b = _by_seed(records, method, cell, key), _by_seed(records, "none", cell, key)
    seeds = sorted(set(a) & set(b))
    return np.array([a[s] for s in seeds]), np.array([b[s] for s in seeds])


def paired_relative(records, method: str, cell: tuple, key: str = "jac_err") -> dict | None:
    """Median per-seed relative change of ``key`` (method vs none, %), q1/q3, wins/total."""
    a, b = _paired(records, method, cell, key)
    if not a.size:
        return None
    rel = 100.0 * (a - b) / b
    return {"median_pct": float(np.median(rel)), "q1_pct": float(np.percentile(rel, 25)),
            "q3_pct": float(np.percentile(rel, 75)), "wins": int((rel < 0).sum()),
            "total": len(rel), "per_seed_pct": [round(float(v), 2) for v in rel]}


def _median(records, method, cell, key) -> float | None:
    v = list(_by_seed(records, method, cell, key).values())
    return float(np.median(v)) if v else None


def _cell_label(cell: tuple) -> str:
    w, f, n, e = cell
    return f"{w}, {'friction' if f else 'no friction'}, {n} traj, {e} ep."


DIAG_KEYS = ("jac_err", "jac_pos", "jac_vel", "jac_moving_all", "jac_still_all", "frac_still",
             "label_jac_pos", "label_jac_vel", "log10_pred_rms", "log10_sim_rms")
NET_KEYS = ("net_train_pos", "net_train_vel")


def _heat_map(ax, stats: list[list[dict | None]], xticks: list[str], yticks: list[str]):
    """Colour = median relative change of the Jacobian error vs none (:func:`paired_relative`
    per row and column), text = change and wins/total."""
    grid = np.full((len(yticks), len(xticks)), np.nan)
    for i, row in enumerate(stats):
        for j, s in enumerate(row):
            if s is not None:
                grid[i, j] = s["median_pct"]
                ax.text(j, i, f"{s['median_pct']:+.0f}%\n{s['wins']}/{s['total']}", ha="center",
                        va="center", fontsize=7,
                        color="white" if abs(s["median_pct"]) > 25 else "black")
    im = ax.imshow(grid, cmap="RdBu_r", vmin=-40.0, vmax=40.0, aspect="auto")
    ax.set_xticks(range(len(xticks)), xticks, fontsize=7)
    ax.set_yticks(range(len(yticks)), yticks, fontsize=7)
    return im


def variants_map(ax, records, protocol: list[dict]) -> None:
    """Rows = methods, columns = the cells that ran the label variants (+ the paper cell under
    the paper's protocol)."""
    cells = [c for c in _cells(records) if any(
        r["config"]["method"] == "oracle" and _cell_of(r) == c for r in records)]
    cols = [(records, c, f"{c[2]} tr., {c[3]} ep.\n1 member, full batch") for c in cells]
    cols += [(protocol, c, f"{c[2]} tr., {c[3]} ep.\npaper protocol (4 members)")
             for c in _cells(protocol)]
    rows = ["sampled", "oracle", "exact", "prior"]
    _heat_map(ax, [[paired_relative(recs, m, c) for recs, c, _ in cols] for m in rows],
              [t for _, _, t in cols], [METHOD_LABELS[m] for m in rows])
    if cells:
        ax.set_title(f"label variants vs none, {cells[0][0]} window, "
                     f"{'friction' if cells[0][1] else 'no friction'}", fontsize=9)


def regime_map(ax, records, method: str, title: str):
    """Heat map: rows = excitation window x friction, columns = trajectories x epochs."""
    cells = _cells(records)
    rows = sorted({(c[0], c[1]) for c in cells}, key=_family_order)
    cols = sorted({(c[2], c[3]) for c in cells})
    im = _heat_map(ax, [[paired_relative(records, method, (w, f, n, e)) for n, e in cols]
                        for w, f in rows], [f"{n} tr.\n{e} ep." for n, e in cols],
                   [f"{w} window\n{'friction' if f else 'no friction'}" for w, f in rows])
    ax.set_title(title, fontsize=9)
    return im


def diagnostics_figure(records: list[dict], path: Path) -> None:
    """The network's own Jacobian error at the training points during training (median over
    seeds; none = solid, sampled = dotted) against the error of the LTV labels (dashed), per row
    group, for each window x friction family at its middle trajectory count and longest run."""
    plt = pc.pyplot()
    cells = _cells(records)
    if not cells:
        return
    n_mid = sorted({c[2] for c in cells})[len({c[2] for c in cells}) // 2]
    e_max = max(c[3] for c in cells)
    fams = sorted({(c[0], c[1]) for c in cells}, key=_family_order)
    fig, axes = plt.subplots(1, 2, figsize=(10, 3.8), layout="constrained")
    colors = plt.rcParams["axes.prop_cycle"].by_key()["color"]
    for i, (w, f) in enumerate(fams):
        cell, color = (w, f, n_mid, e_max), colors[i % len(colors)]
        label = f"{w} window, {'friction' if f else 'no friction'}"
        for j, rows in enumerate(("pos", "vel")):
            for method, style in (("none", "-"), ("sampled", ":")):
                logs = [r["result"]["net_train_jac"] for r in records
                        if r["config"]["method"] == method and _cell_of(r) == cell]
                if logs:
                    ep = logs[0]["epoch"]
                    med = np.median(np.array([lg[rows] for lg in logs]), 0)
                    axes[j].plot(ep, med, style, color=color,
                                 label=f"{label}: network, {method}" if j == 0 else None)
            lab = _median(records, "sampled", cell, f"label_jac_{rows}")
            if lab is not None:
                axes[j].axhline(lab, ls="--", color=color, lw=1,
                                label=f"{label}: LTV labels" if j == 0 else None)
    for j, rows in enumerate(("position rows (q)", "velocity rows (qdot)")):
        axes[j].set(xlabel="epoch", ylabel="Jacobian error at the training points")
        axes[j].set_title(f"{rows}, {n_mid} trajectories", fontsize=9)
    fig.legend(loc="outside right center", fontsize=6)
    pc.save_figure(fig, path)


def report(records: list[dict], out: Path, figures: Path, args: Args) -> dict:
    """The map's figures, table and summary, with the paper-protocol runs summarized apart."""
    plt = pc.pyplot()
    protocol = [r for r in records if r["config"].get("paper_protocol")]
    records = [r for r in records if not r["config"].get("paper_protocol")]
    methods = [m for m in ("sampled", "oracle", "exact", "prior")
               if any(r["config"]["method"] == m for r in records)]
    fig, axes = plt.subplots(2, 1, figsize=(9, 7.5), layout="constrained",
                             gridspec_kw={"height_ratios": [1.1, 1]})
    im = regime_map(axes[0], records, "sampled", "sampled JacProp vs none: median change of "
                    "the robot Jacobian error (text: change, runs better / runs)")
    variants_map(axes[1], records, protocol)
    fig.colorbar(im, ax=axes.tolist(), shrink=0.6, label="Jacobian error change vs none [%]")
    pc.save_figure(fig, figures / "regime_map.png")

    diagnostics_figure(records, figures / "regime_diagnostics.png")

    cells = _cells(records)
    table = {}
    for cell in cells:
        row = {"none_" + k: _median(records, "none", cell, k) for k in DIAG_KEYS + NET_KEYS}
        for m in methods:
            s = paired_relative(records, m, cell)
            if s is not None:
                row[m] = s
                for k in DIAG_KEYS:
                    row[f"{m}_{k}"] = _median(records, m, cell, k)
                for k in ("log10_pred_rms", "log10_sim_rms"):
                    d = np.subtract(*_paired(records, m, cell, k))
                    row[f"{m}_{k}_diff"] = {"median": float(np.median(d)),
                                            "wins": int((d < 0).sum()), "total": len(d)}
        table[_cell_label(cell)] = row
    cpu = sum(r["result"].get("cpu_time", 0.0) for r in records)
    summary = {"cells": table, "n_runs": len(records), "cpu_s_runs": cpu,
               "figures": ["regime_map.png", "regime_diagnostics.png"]}
    text = markdown_table(records, methods)
    if protocol:
        summary["paper_protocol"] = paper_protocol_summary(protocol)
        text += "\n" + paper_protocol_table(summary["paper_protocol"])
    (out / "table.md").write_text(text)
    return summary


def _fmt(v, digits=2) -> str:
    return "-" if v is None else f"{v:.{digits}f}"


def _change(s: dict | None) -> str:
    """A :func:`paired_relative` as ``median % [q1, q3], wins/total`` ("-": none)."""
    return "-" if not s else (f"{s['median_pct']:+.0f} % [{s['q1_pct']:+.0f}, "
                              f"{s['q3_pct']:+.0f}], {s['wins']}/{s['total']}")


def markdown_table(records: list[dict], methods: list[str]) -> str:
    """One row per cell: none's Jacobian error and its diagnostics, each method's change."""
    head = ["cell", "none: Jacobian error (pos / vel rows; moving / still pts)", "still pts",
            "none's network / LTV labels at the train pts, pos rows; vel rows"]
    head += [f"{m}: change, wins" for m in methods]
    lines = ["| " + " | ".join(head) + " |", "|" + "---|" * len(head)]
    for cell in _cells(records):
        md = lambda m, k, cell=cell: _median(records, m, cell, k)  # noqa: E731
        row = [_cell_label(cell),
               f"{_fmt(md('none', 'jac_err'))} ({_fmt(md('none', 'jac_pos'))} / "
               f"{_fmt(md('none', 'jac_vel'))}; {_fmt(md('none', 'jac_moving_all'))} / "
               f"{_fmt(md('none', 'jac_still_all'))})",
               f"{100 * (md('none', 'frac_still') or 0):.0f} %",
               f"{_fmt(md('none', 'net_train_pos'))} / "
               f"{_fmt(md('sampled', 'label_jac_pos'))}; "
               f"{_fmt(md('none', 'net_train_vel'))} / "
               f"{_fmt(md('sampled', 'label_jac_vel'))}"]
        row += [_change(paired_relative(records, m, cell)) for m in methods]
        lines.append("| " + " | ".join(row) + " |")
    return "\n".join(lines) + "\n"


PROTOCOL_KEYS = (*DIAG_KEYS, "steps", *NET_KEYS)


def paper_protocol_summary(records: list[dict]) -> dict:
    """The paper cell under the paper's protocol: medians per method, the network's own
    training-point error per row group at the end, and the paired change vs none."""
    cell = _cells(records)[0]
    out = {"cell": _cell_label(cell), "methods": {}}
    for m in ("none", "sampled", "oracle"):
        row = {k: _median(records, m, cell, k) for k in PROTOCOL_KEYS}
        if m != "none":
            row["vs_none"] = paired_relative(records, m, cell)
        out["methods"][m] = row
    return out


def paper_protocol_table(s: dict) -> str:
    lines = [f"Paper protocol at the paper cell ({s['cell']}; 4-member nominal ensemble, one "
             "optimizer step per trajectory, equal steps):", "",
             "| method | Jacobian error (pos / vel rows) | network at train pts pos / vel | "
             "labels pos / vel | change vs none, wins |", "|---|---|---|---|---|"]
    for m, r in s["methods"].items():
        lines.append(
            f"| {m} | {_fmt(r['jac_err'])} ({_fmt(r['jac_pos'])} / {_fmt(r['jac_vel'])}) | "
            f"{_fmt(r.get('net_train_pos'))} / {_fmt(r.get('net_train_vel'))} | "
            f"{_fmt(r['label_jac_pos'])} / {_fmt(r['label_jac_vel'])} | "
            f"{_change(r.get('vs_none'))} |")
    return "\n".join(lines) + "\n"


def run(args: Args) -> dict:
    """The sweep, the shortest runs first: the cheap shortest-run cells for every seed, then
    everything seed by seed (on a busy machine an interrupted sweep still has the whole
    short-run map at full seed count); then the report."""
    configs = make_configs(args)
    every = {**configs["main"], **configs["labels"], **configs["paper_protocol"]}
    shortest = min(c["epochs"] for c in every.values())
    stages = [("short runs", {k: c for k, c in every.items() if c["epochs"] == shortest}),
              ("all", every)]
    return pc.run_experiment(args, EXPERIMENT, pc.run_regime, every, report, stages=stages)


def main(argv: list[str] | None = None) -> None:
    """The command line (``python -m agents.experiments.exp_regime``): parse, run, print."""
    args = pc.parse_args(Args, argv)
    summary = run(args)
    for name, row in summary["cells"].items():
        s = row.get("sampled")
        if s:
            print(f"{name:40s} none {row['none_jac_err']:.3f} sampled {s['median_pct']:+.1f}% "
                  f"({s['wins']}/{s['total']})")


if __name__ == "__main__":
    main()
