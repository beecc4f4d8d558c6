"""Benchmark of the neural dynamics ensembles and their training (issue 4).

All in one run, on data of the paper's two-link robot (the original code's dynamics with
m = 0.2, l = 1, viscous friction 2, Coulomb friction 0.1 tanh(100 v), g = 1.82, a physically
consistent mass matrix, RK4 at dt = 0.02 s with zero-order-hold torques that are a causal
100-tap moving average of 10 N(0, 1), start [-0.4, 0, 0, 0], measurement noise 0.01):

1. ms per epoch of full-batch training on 1000 transitions for K = 1, 4, 8 members, batched
   (``train_ensemble``, one step per epoch) and as K separate torch modules in a Python loop
   (same data, loss and Adam);
2. ms for the Jacobians of 4 members at 1000 points (float64 numpy path, ensemble mean and per
   member; and the differentiable torch path), plus ``step``/``jacobians`` at iLQR sizes;
3. ms per epoch of the nominal setting (3 trajectories x 200, one step per trajectory) without
   regularization, with sampled Jacobian propagation, the exact penalty and the smoothness
   penalty, and their ratios to no regularization (LTV models fitted once, outside the timing);
4. seconds to train the paper's nominal robot model: 4 x 20 ensemble, 3 trajectories x 200,
   2000 epochs, sampled Jacobian propagation (the whole ``train_ensemble`` call, LTV fits
   included), with its Jacobian error on a held-out trajectory.

Targets: batched K = 4 epoch <= 1.5 x the K = 1 epoch; batched K = 8 >= 2 x faster than the
loop; nominal robot training <= 10 s on 2 cores.

    python scripts/bench_models.py --json runs/bench_models.json
"""

from __future__ import annotations

import dataclasses
import json
import os
import sys
import time

import numpy as np
import torch
from torch import nn

from agents.experiments.paper_common import machine_info, write_result
from mbtsr import Trajectory
from mbtsr.ensemble import ACTIVATIONS, DynamicsEnsemble, EnsembleConfig, MemberSpec
from mbtsr.ltv import fit_ltv
from mbtsr.metrics import jacobian_error, prediction_rms
from mbtsr.training import RegularizationConfig, TrainConfig, train_ensemble


@dataclasses.dataclass
class Args:
    """Benchmark of the neural dynamics ensembles and their training (issue 4)."""

    threads: int = 1
    """torch threads (BLAS threads: OMP_NUM_THREADS, default 1)"""
    epochs: int = 200
    """epochs per timed repeat of the per-epoch measurements"""
    repeats: int = 5
    """timed repeats (the median is reported)"""
    robot_epochs: int = 2000
    """epochs of the nominal robot training"""
    seed: int = 0
    """seed of the data and the models"""
    json: str = ""
    """write the results to this JSON file"""


PAPER = ("elu", "sigmoid", "tanh", "swish")

# ---------------------------------------------------------------------------------------------
# 0. robot data: the original code's two-link arm in numpy
# ---------------------------------------------------------------------------------------------
M1 = M2 = 0.2
L1 = L2 = 1.0
VISCOUS, COULOMB, GRAVITY, DT = 2.0, 0.1, 1.82, 0.02


def arm_derivative(x: np.ndarray, tau: np.ndarray) -> np.ndarray:
    """``[q1, q2, qd1, qd2] -> [qd1, qd2, qdd1, qdd2]`` (batched over leading dims)."""
    q1, q2, v1, v2 = np.moveaxis(x, -1, 0)
    c2, s2 = np.cos(q2), np.sin(q2)
    m11 = (M1 + M2) * L1**2 + M2 * L2**2 + 2 * M2 * L1 * L2 * c2
    m12 = M2 * L2**2 + M2 * L1 * L2 * c2
    m22 = np.full_like(q1, M2 * L2**2)
    h = M2 * L1 * L2 * s2
    bias1 = -h * (2 * v1 * v2 + v2**2) + (M1 + M2) * GRAVITY * L1 * np.sin(q1) \
        + M2 * GRAVITY * L2 * np.sin(q1 + q2) + VISCOUS * v1 + COULOMB * np.tanh(100 * v1)
    bias2 = h * v1**2 + M2 * GRAVITY * L2 * np.sin(q1 + q2) + VISCOUS * v2 \
        + COULOMB * np.tanh(100 * v2)
    r1, r2 = tau[..., 0] - bias1, tau[..., 1] - bias2
    det = m11 * m22 - m12 * m12
    return np.stack([v1, v2, (m22 * r1 - m12 * r2) / det, (m11 * r2 - m12 * r1) / det], -1)


def arm_step(x: np.ndarray, tau: np.ndarray, substeps: int = 4) -> np.ndarray:
    """One sample period with the torque held: RK4 with ``substeps`` steps."""
    h = DT / substeps
    for _ in range(substeps):
        k1 = arm_derivative(x, tau)
        k2 = arm_derivative(x + h / 2 * k1, tau)
        k3 = arm_derivative(x + h / 2 * k2, tau)
        k4 = arm_derivative(x + h * k3, tau)
        x = x + h / 6 * (k1 + 2 * k2 + 2 * k3 + k4)
    return x


def arm_jacobians(x: np.ndarray, u: np.ndarray, eps: float = 1e-6) -> np.ndarray:
    """True discrete Jacobians ``[T, 4, 6]`` by central differences of ``arm_step``."""
    xu = np.concatenate([x, u], -1)
    cols = []
    for j in range(6):
        e = np.zeros(6)
        e[j] = eps
        plus, minus = xu + e, xu - e
        cols.append((arm_step(plus[:, :4], plus[:, 4:]) - arm_step(minus[:, :4], minus[:, 4:]))
                    / (2 * eps))
    return np.stack(cols, -1)


def arm_trajectory(rng: np.random.Generator, T: int = 200, noise: float = 0.01) -> Trajectory:
    """A filtered-Gaussian rollout, redrawn while ``|q| >= 0.9 pi`` (original v1 recipe)."""
    while True:
        w = 10 * rng.normal(size=(T + 99, 2))
        u = np.stack([w[t : t + 100].mean(0) for t in range(T)])  # causal 100-tap average
        x = np.zeros((T + 1, 4))
        x[0] = [-0.4, 0, 0, 0]
        for t in range(T):
            x[t + 1] = arm_step(x[t], u[t])
        if np.all(np.abs(x[:, :2]) < 0.9 * np.pi):
            return Trajectory(x + noise * rng.normal(size=x.shape), u, dt=DT)


def run(args: Args) -> dict:
    """Run the benchmark; print and return the results (and write ``args.json``).

    ``args.threads`` sets torch's threads; BLAS reads ``OMP_NUM_THREADS`` when numpy loads
    (``scripts/bench_models.py`` sets it to 1 unless it is set).
    """
    torch.set_num_threads(args.threads)
    rng = np.random.default_rng(args.seed)
    data_1000 = [arm_trajectory(rng) for _ in range(5)]  # 1000 transitions
    robot_train = data_1000[:3]  # the nominal setting: 3 x 200
    robot_val = arm_trajectory(rng, noise=0.0)
    xu_all = torch.tensor(np.concatenate([np.concatenate(tr.inputs, 1) for tr in data_1000]),
                          dtype=torch.float32)
    print(f"data: {len(data_1000)} trajectories, {xu_all.shape[0]} transitions; "
          f"threads {args.threads}, load {os.getloadavg()}", file=sys.stderr)


    CPU_MS: dict[str, float] = {}  # process CPU time of the same measurements (see cpu_ms below)


    def median_ms(fn, repeats: int, per: int = 1, key: str = "") -> float:
        """Median wall-clock ms per unit; the median process CPU ms is kept in ``CPU_MS[key]``
        (on a shared machine CPU time is the steadier figure, wall time what a user waits)."""
        wall, cpu = [], []
        for _ in range(repeats):
            t0, c0 = time.perf_counter(), time.process_time()
            fn()
            wall.append((time.perf_counter() - t0) * 1e3 / per)
            cpu.append((time.process_time() - c0) * 1e3 / per)
        if key:
            CPU_MS[key] = float(np.median(cpu))
        return float(np.median(wall))


    def ensemble(members, seed=0) -> DynamicsEnsemble:
        model = DynamicsEnsemble(EnsembleConfig(4, 2, members=tuple(members), seed=seed))
        model.set_normalization(data_1000)
        return model


    def members_of(K: int) -> list[MemberSpec]:
        return [MemberSpec(PAPER[k % 4], 20, 1) for k in range(K)]


    quiet = {"progress": False}
    load_start = os.getloadavg()
    results: dict = {"config": dataclasses.asdict(args)}

    # ---------------------------------------------------------------------------------------------
    # 1. batched K = 1, 4, 8 vs K separate modules in a loop (full batch of 1000, one step/epoch)
    # ---------------------------------------------------------------------------------------------
    # the same activation kernels as the ensemble (its tanh is 2 sigmoid(2z) - 1, faster than
    # torch.tanh on these CPUs), so the comparison isolates the batching
    ACT = {name: ACTIVATIONS[name][0] for name in PAPER}


    class Member(nn.Module):
        def __init__(self, activation: str) -> None:
            super().__init__()
            self.hidden, self.out, self.act = nn.Linear(6, 20), nn.Linear(20, 4), ACT[activation]

        def forward(self, xn):
            return self.out(self.act(self.hidden(xn)))


    def loop_epochs(K: int, epochs: int):
        """K separate modules, one Adam over all of them, one full-batch step per epoch."""
        ref = ensemble(members_of(K))
        with torch.no_grad():
            xn = ref.normalize_inputs(xu_all)
            x_next = torch.tensor(np.concatenate([tr.targets for tr in data_1000]),
                                  dtype=torch.float32)
            target = ref.normalized_residual(xu_all, x_next)
        torch.manual_seed(args.seed)
        modules = [Member(PAPER[k % 4]) for k in range(K)]
        opt = torch.optim.Adam([p for mod in modules for p in mod.parameters()], lr=0.01,
                               foreach=True)

        def run():
            for _ in range(epochs):
                loss = sum(((mod(xn) - target) ** 2).sum(-1).mean() for mod in modules)
                opt.zero_grad(set_to_none=True)
                loss.backward()
                opt.step()

        return run


    def batched_epochs(K: int, epochs: int):
        model = ensemble(members_of(K))
        cfg = TrainConfig(epochs=epochs, batch=1000, shuffle=False, **quiet)
        return lambda: train_ensemble(model, data_1000, cfg)


    epoch_ms = {}
    for K in (1, 4, 8):
        batched_epochs(K, 5)()  # warm-up
        loop_epochs(K, 5)()
        # interleave the repeats of the two variants so load changes hit both alike
        runs = {f"batched_K{K}": batched_epochs(K, args.epochs),
                f"loop_K{K}": loop_epochs(K, args.epochs)}
        samples = {k: [] for k in runs}
        cpu_samples = {k: [] for k in runs}
        for _ in range(args.repeats):
            for k, fn in runs.items():
                samples[k].append(median_ms(fn, 1, args.epochs, key=k))
                cpu_samples[k].append(CPU_MS[k])
        for k in runs:
            epoch_ms[k] = float(np.median(samples[k]))
            CPU_MS[k] = float(np.median(cpu_samples[k]))
        print(f"K={K}: batched {epoch_ms[f'batched_K{K}']:.3f} ms/epoch, "
              f"loop {epoch_ms[f'loop_K{K}']:.3f} ms/epoch", file=sys.stderr)


    def same_activation_epochs(epochs: int):
        model = ensemble([MemberSpec("elu", 20, 1)] * 4)
        cfg = TrainConfig(epochs=epochs, batch=1000, shuffle=False, **quiet)
        return lambda: train_ensemble(model, data_1000, cfg)


    same_activation_epochs(5)()
    epoch_ms["batched_K4_all_elu"] = median_ms(same_activation_epochs(args.epochs), args.repeats,
                                               args.epochs, key="batched_K4_all_elu")
    results["epoch_ms_full_batch_1000"] = epoch_ms
    results["epoch_cpu_ms_full_batch_1000"] = {k: CPU_MS[k] for k in epoch_ms}

    # the same K scaling in the paper's training regime: 3 trajectories x 200, one step each
    nominal_k = {}
    for K in (1, 4, 8):
        model = ensemble(members_of(K))
        cfg = TrainConfig(epochs=args.epochs, **quiet)
        train_ensemble(model, robot_train, TrainConfig(epochs=3, **quiet))
        nominal_k[f"batched_K{K}"] = median_ms(
            lambda model=model, cfg=cfg: train_ensemble(model, robot_train, cfg), args.repeats,
            args.epochs, key=f"nominal_K{K}")
    results["epoch_ms_nominal_3x200"] = nominal_k
    results["epoch_cpu_ms_nominal_3x200"] = {k: CPU_MS[f"nominal_{k[-2:]}"] for k in nominal_k}
    print(f"nominal setting: {nominal_k}", file=sys.stderr)

    # ---------------------------------------------------------------------------------------------
    # 2. Jacobians and the protocol surface at iLQR sizes
    # ---------------------------------------------------------------------------------------------
    model4 = ensemble(members_of(4))
    frozen4 = model4.freeze()  # the planning model: numpy surface without a freeze per call
    x1000, u1000 = (np.concatenate(p) for p in zip(*[tr.inputs for tr in data_1000]))
    x200, u200 = robot_train[0].inputs
    n_rep = 50
    jac = {
        "member_jacobians_4x1000_numpy_ms": median_ms(
            lambda: [frozen4.member_jacobians(x1000, u1000) for _ in range(n_rep)], 5, n_rep),
        "mean_jacobians_4x1000_numpy_ms": median_ms(
            lambda: [frozen4.jacobians(x1000, u1000) for _ in range(n_rep)], 5, n_rep),
        "member_jacobians_4x1000_torch_ms": median_ms(
            lambda: [model4.member_jacobians_torch(torch.tensor(x1000), torch.tensor(u1000))
                     for _ in range(n_rep)], 5, n_rep),
        "mean_jacobians_4x200_numpy_us": 1e3 * median_ms(
            lambda: [frozen4.jacobians(x200, u200) for _ in range(n_rep)], 5, n_rep),
        "step_1_point_us": 1e3 * median_ms(
            lambda: [frozen4.step(x200[0], u200[0]) for _ in range(20 * n_rep)], 5, 20 * n_rep),
        "step_200_points_us": 1e3 * median_ms(
            lambda: [frozen4.step(x200, u200) for _ in range(n_rep)], 5, n_rep),
    }
    results["jacobians"] = jac
    print(f"jacobians: {jac}", file=sys.stderr)

    # ---------------------------------------------------------------------------------------------
    # 3. regularizer cost per epoch in the nominal setting (3 x 200, one step per trajectory)
    # ---------------------------------------------------------------------------------------------
    t0 = time.perf_counter()
    ltv_models = [fit_ltv(tr, RegularizationConfig().ltv_lambda) for tr in robot_train]
    ltv_fit_ms = (time.perf_counter() - t0) * 1e3 / len(robot_train)
    regs = {
        "none": RegularizationConfig(),
        "sampled": RegularizationConfig.paper(),
        "exact": RegularizationConfig(exact_weight=1.0),
        "smooth": RegularizationConfig(smooth_weight=0.01),
        "sampled+exact+smooth": RegularizationConfig.paper(exact_weight=1.0, smooth_weight=0.01),
    }
    reg_ms = {}
    for name, reg in regs.items():
        model = ensemble(members_of(4))
        cfg = TrainConfig(epochs=args.epochs, **quiet)
        train_ensemble(model, robot_train, TrainConfig(epochs=3, **quiet), reg,
                       ltv_models=ltv_models)
        reg_ms[name] = median_ms(
            lambda model=model, cfg=cfg, reg=reg: train_ensemble(model, robot_train, cfg, reg,
                                                                 ltv_models=ltv_models),
            args.repeats, args.epochs, key=f"reg_{name}")
        print(f"{name}: {reg_ms[name]:.3f} ms/epoch", file=sys.stderr)
    results["nominal_epoch_ms"] = reg_ms
    results["regularizer_epoch_ratio"] = {k: v / reg_ms["none"] for k, v in reg_ms.items()}
    results["nominal_epoch_cpu_ms"] = {k: CPU_MS[f"reg_{k}"] for k in reg_ms}
    results["ltv_fit_ms_per_trajectory"] = ltv_fit_ms

    # ---------------------------------------------------------------------------------------------
    # 4. the paper's nominal robot model, sampled Jacobian propagation, 2000 epochs
    # ---------------------------------------------------------------------------------------------
    J_true = arm_jacobians(*robot_val.inputs)
    robot = {}
    for name, reg in (("sampled", RegularizationConfig.paper()), ("none", RegularizationConfig())):
        model = DynamicsEnsemble(EnsembleConfig(4, 2, seed=args.seed))
        t0, c0 = time.perf_counter(), time.process_time()
        hist = train_ensemble(model, robot_train, TrainConfig(epochs=args.robot_epochs,
                                                               seed=args.seed, **quiet), reg)
        seconds, cpu_seconds = time.perf_counter() - t0, time.process_time() - c0
        robot[name] = {
            "seconds": seconds,
            "cpu_seconds": cpu_seconds,
            "steps": hist.steps,
            "final_train_loss": float(hist.train_loss[-1]),
            "val_prediction_rms": prediction_rms(model, [robot_val]),
            "val_jacobian_error": jacobian_error(J_true, model.member_jacobians(*robot_val.inputs)),
        }
        print(f"robot {name}: {robot[name]}", file=sys.stderr)
    results["nominal_robot_training"] = robot

    # ---------------------------------------------------------------------------------------------
    # targets and output
    # ---------------------------------------------------------------------------------------------
    cpu = results["epoch_cpu_ms_full_batch_1000"]
    results["diagnostics"] = {
        "nominal_3x200_batched_K4_over_K1": nominal_k["batched_K4"] / nominal_k["batched_K1"],
        "full_batch_K4_all_elu_over_K1": epoch_ms["batched_K4_all_elu"] / epoch_ms["batched_K1"],
    }
    results["targets"] = {
        "batched_K4_over_K1": {"value": epoch_ms["batched_K4"] / epoch_ms["batched_K1"],
                               "cpu_time_value": cpu["batched_K4"] / cpu["batched_K1"],
                               "max": 1.5},
        "loop_K8_over_batched_K8": {"value": epoch_ms["loop_K8"] / epoch_ms["batched_K8"],
                                    "cpu_time_value": cpu["loop_K8"] / cpu["batched_K8"],
                                    "min": 2.0},
        "nominal_robot_training_seconds": {"value": robot["sampled"]["seconds"],
                                           "cpu_time_value": robot["sampled"]["cpu_seconds"],
                                           "max": 10.0},
    }
    for t in results["targets"].values():
        t["met"] = bool(t["value"] <= t["max"]) if "max" in t else bool(t["value"] >= t["min"])
    results["machine"] = machine_info(load_start, torch=torch.__version__, numpy=np.__version__)
    print(json.dumps(results, indent=2))
    write_result(args.json, results, indent=2)
    return results
