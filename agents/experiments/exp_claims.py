"""Recompute the evidence of every claim row of docs/RESULTS.md from the per-run JSON alone.

What it measures and how to run it: docs/experiments.md, section ``exp_claims``.
"""

from __future__ import annotations

import json
from dataclasses import dataclass, field
from pathlib import Path

import numpy as np

from agents.experiments.paper_common import REPO, parse_args
from mbtsr.io import write_json_atomic


@dataclass
class Args:
    """Claim evidence (median [q1, q3], paired difference, wins/total) from the stored runs."""

    results: str = field(default="", metadata={"help": "results root (empty: docs/results)"})
    out: str = field(default="", metadata={
        "help": "folder of claims.json and claims.md (empty: the results root)"})
    smoke: bool = field(default=False, metadata={
        "help": "accepted for the shared convention: the command trains nothing, it only reads"})


@dataclass(frozen=True)
class Comparison:
    """``a`` vs ``b`` on ``metric`` in ``experiment``; ``mode`` "diff" (a - b) or "ratio"."""

    claim: int
    experiment: str
    a: str
    b: str
    metric: str
    mode: str = "diff"


def metric_value(res: dict, metric: str) -> float | None:
    """``metric`` of one run's result: a key, ``rounds.<i>.<key>``, or ``act.<name>@<ckpt>``."""
    if metric.startswith("rounds."):
        _, i, key = metric.split(".", 2)
        return res["rounds"][int(i)][key]
    if metric.startswith("act."):
        act, ckpt = metric[4:].split("@")
        return float(np.log10(res["pred_rms"][act][res["checkpoints"].index(int(ckpt))]))
    return res.get(metric)


COMPARISONS = [
    *[Comparison(1, "linear", m, "none", "jac_err") for m in ("sampled", "exact", "smooth")],
    *[Comparison(1, "robot", m, "none", "jac_err")
      for m in ("sampled", "sampled_full", "sampled_own", "exact", "smooth")],
    *[Comparison(2, "linear", m, "none", k) for m in ("sampled", "exact")
      for k in ("log10_pred_rms", "log10_sim_rms")],
    Comparison(3, "linear", "none", "sampled", "train_loss"),
    Comparison(3, "linear", "none_bug", "sampled_bug", "train_loss"),
    *[Comparison(4, "linear", m, "none", "eig_match_err") for m in ("sampled", "smooth", "exact")],
    Comparison(5, "linear", "sampled", "none", "rounds.2.jac_rms_entry"),
    Comparison(5, "linear", "sampled_bug", "none_bug", "rounds.2.jac_rms_entry"),
    *[Comparison(6, "weight_decay", "f_wd0.1", "f_wd0", k)
      for k in ("eig_mean_abs", "eig_match_err", "jac_rms_entry")],
    *[Comparison(7, "weight_decay", "g_wd0.1", "g_wd0", k)
      for k in ("eig_mean_dist_to_1", "jac_rms_entry", "log10_pred_rms")],
    *[Comparison(7, "weight_decay", "g_wd0.1_bug", "g_wd0_bug", k)
      for k in ("eig_mean_dist_to_1", "jac_rms_entry", "log10_pred_rms")],
    Comparison(8, "weight_decay", "f_wd0.1", "f_wd0", "jac_rms_entry", "ratio"),
    Comparison(8, "weight_decay", "g_wd0.1", "g_wd0", "jac_rms_entry", "ratio"),
    *[Comparison(9, "weight_decay", "g_wd0", "f_wd0", k)
      for k in ("log10_pred_rms", "jac_rms_entry", "train_pred_rms")],
    *[Comparison(9, "deviations", "g_nominal", "f_nominal", k)
      for k in ("log10_pred_rms", "jac_err", "train_pred_rms")],
    *[Comparison(10, "robot", m, b, k)
      for m, b in (("sampled", "none"), ("sampled_full", "none"), ("sampled_own", "none"),
                   ("sampled", "none_half"))
      for k in ("log10_pred_rms", "log10_sim_rms")],
    *[Comparison(12, "robot", m, "none", "jac_err") for m in ("sampled", "sampled_full",
                                                               "sampled_own")],
    *[Comparison(13, "deviations", f"{f}_copies_5", f"{f}_nominal", k) for f in ("f", "g")
      for k in ("log10_pred_rms", "jac_err")],
    *[Comparison(14, "activations", "all_g", "all_g", f"act.{a}@{c}|act.{b}@{c}")
      for a in ("relu", "leaky_relu") for b in ("tanh", "elu") for c in (500,)],
    *[Comparison(14, "activations", "all_g", "all_g", f"act.swish@{c}|act.relu@{c}")
      for c in (500, 1500)],
    *[Comparison(15, "deviations", f"g_{d}", f"f_{d}", "log10_pred_rms")
      for d in ("dt_slow", "nominal", "dt_fast")],
    *[Comparison(16, "deviations", f"g_{d}", "g_nominal", k)
      for d, k in (("depth_2", "log10_pred_rms"), ("dropout", "log10_sim_rms"),
                   ("layer_norm", "jac_err"), ("noise_x10", "log10_pred_rms"),
                   ("width_x2", "log10_pred_rms"), ("ensemble_x3", "log10_pred_rms"))],
]


def _load(root: Path, experiment: str) -> dict[str, dict[int, dict]]:
    out: dict[str, dict[int, dict]] = {}
    for path in sorted((root / experiment / "runs").glob("*.json")):
        rec = json.loads(path.read_text())
        if rec.get("status", "ok") == "ok":
            out.setdefault(rec["name"], {})[rec["seed"]] = rec["result"]
    return out


def _q(v: np.ndarray) -> dict:
    return {"median": float(np.median(v)), "q1": float(np.percentile(v, 25)),
            "q3": float(np.percentile(v, 75))}


def evaluate(c: Comparison, runs: dict[str, dict[int, dict]]) -> dict | None:
    """Medians and the paired statistic of one comparison (None if a side has no runs)."""
    if c.a not in runs or c.b not in runs:
        return None
    ma, mb = (c.metric.split("|") * 2)[:2]  # "a|b": metric a of c.a, b of c.b
    seeds = sorted(set(runs[c.a]) & set(runs[c.b]))
    pairs = [(metric_value(runs[c.a][s], ma), metric_value(runs[c.b][s], mb)) for s in seeds]
    a, b = np.array([p for p in pairs if None not in p], dtype=float).reshape(-1, 2).T
    stat = a / b if c.mode == "ratio" else a - b
    return {"claim": c.claim, "experiment": c.experiment, "a": c.a, "b": c.b,
            "metric": c.metric, "mode": c.mode, "a_stats": _q(a), "b_stats": _q(b),
            "paired": _q(stat), "wins": int((a < b).sum()), "total": len(a)}


def markdown(rows: list[dict]) -> str:
    lines = ["| claim | experiment | a vs b | metric | a: median [q1, q3] | b: median [q1, q3] "
             "| paired a-b (or a/b): median [q1, q3] | a lower |", "|" + "---|" * 8]
    for r in rows:
        f = lambda s: f"{s['median']:.4g} [{s['q1']:.4g}, {s['q3']:.4g}]"  # noqa: E731
        lines.append(f"| {r['claim']} | {r['experiment']} | {r['a']} vs {r['b']} | {r['metric']} "
                     f"({r['mode']}) | {f(r['a_stats'])} | {f(r['b_stats'])} | "
                     f"{f(r['paired'])} | {r['wins']}/{r['total']} |")
    return "\n".join(lines) + "\n"


def run(args: Args) -> list[dict]:
    root = Path(args.results) if args.results else REPO / "docs" / "results"
    runs = {e: _load(root, e) for e in dict.fromkeys(c.experiment for c in COMPARISONS)}
    rows = [r for c in COMPARISONS if (r := evaluate(c, runs[c.experiment])) is not None]
    out = Path(args.out) if args.out else root
    out.mkdir(parents=True, exist_ok=True)
    write_json_atomic(out / "claims.json", rows)
    (out / "claims.md").write_text(markdown(rows))
    return rows


def main(argv: list[str] | None = None) -> None:
    """The command line (``python -m agents.experiments.exp_claims``): parse, run, print."""
    print(markdown(run(parse_args(Args, argv))))


if __name__ == "__main__":
    main()
