"""Benchmark of the neural dynamics ensembles and their training (issue 4).

What it measures and how to run it: docs/experiments.md, section ``bench_models``.
"""

from __future__ import annotations

import dataclasses
import json
import os
import sys
import time
from typing import Any

import numpy as np
import torch
from torch import nn

from agents.cli import main as command
from agents.experiments.paper_common import blas_threads_from_env, machine_info, write_result
from mbtsr import Trajectory
from mbtsr.ensemble import ACTIVATIONS, DynamicsEnsemble, EnsembleConfig, MemberSpec
from mbtsr.ltv import fit_ltv
from mbtsr.metrics import jacobian_error, prediction_rms
from mbtsr.training import RegularizationConfig, TrainConfig, train_ensemble


@dataclasses.dataclass
class Args:
    """Benchmark of the neural dynamics ensembles and their training."""

    out: str = ""
    """write the results to this JSON file"""
    smoke: bool = False
    """tiny CI size: the options not given take SMOKE's values"""
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


#: --smoke: the tiny CI size (options given on the command line win)
SMOKE = {"smoke": True, "epochs": 3, "repeats": 1, "robot_epochs": 10}


def main(argv: list[str] | None = None) -> dict:
    """The command line (``--help``: the options)."""
    blas_threads_from_env()  # one BLAS thread unless OMP_NUM_THREADS says otherwise
    return command(Args, run, args=argv, outputs=("out",), presets={"--smoke": SMOKE})


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


class _Bench:
    """The data of one run and the timing helper (``cpu_ms``: the median process CPU ms of the
    measurements timed with a key; on a shared machine CPU time is the steadier figure, wall
    time what a user waits)."""

    def __init__(self, args: Args) -> None:
        rng = np.random.default_rng(args.seed)
        self.args = args
        self.data = [arm_trajectory(rng) for _ in range(5)]  # 1000 transitions
        self.train = self.data[:3]  # the nominal setting: 3 x 200
        self.val = arm_trajectory(rng, noise=0.0)
        self.xu = torch.tensor(np.concatenate([np.concatenate(tr.inputs, 1) for tr in self.data]),
                               dtype=torch.float32)
        self.cpu_ms: dict[str, float] = {}

    def median_ms(self, fn, repeats: int, per: int = 1, key: str = "") -> float:
        """Median wall-clock ms per unit of ``repeats`` calls of ``fn`` (``per`` units each)."""
        wall, cpu = [], []
        for _ in range(repeats):
            t0, c0 = time.perf_counter(), time.process_time()
            fn()
            wall.append((time.perf_counter() - t0) * 1e3 / per)
            cpu.append((time.process_time() - c0) * 1e3 / per)
        if key:
            self.cpu_ms[key] = float(np.median(cpu))
        return float(np.median(wall))

    def ensemble(self, K: int = 4, members: list[MemberSpec] | None = None) -> DynamicsEnsemble:
        """K paper members (activations in turn), normalized on all the data."""
        members = members or [MemberSpec(PAPER[k % 4], 20, 1) for k in range(K)]
        model = DynamicsEnsemble(EnsembleConfig(4, 2, members=tuple(members), seed=0))
        model.set_normalization(self.data)
        return model

    def epochs(self, model: DynamicsEnsemble, data: list[Trajectory], epochs: int, *reg: Any,
               **kw: Any):
        """A call that trains ``model`` for ``epochs`` (full batch unless ``data`` is the
        nominal setting's)."""
        full = {"batch": 1000, "shuffle": False} if data is self.data else {}
        cfg = TrainConfig(epochs=epochs, progress=False, **full)
        return lambda: train_ensemble(model, data, cfg, *reg, **kw)


class _Member(nn.Module):
    """One paper member as its own torch module, with the ensemble's activation kernels (its
    tanh is 2 sigmoid(2z) - 1, faster than torch.tanh on these CPUs), so that the comparison
    isolates the batching."""

    def __init__(self, activation: str) -> None:
        super().__init__()
        self.hidden, self.out = nn.Linear(6, 20), nn.Linear(20, 4)
        self.act = ACTIVATIONS[activation][0]

    def forward(self, xn):
        return self.out(self.act(self.hidden(xn)))


def _loop_epochs(b: _Bench, K: int, epochs: int):
    """K separate modules, one Adam over all of them, one full-batch step per epoch."""
    ref = b.ensemble(K)
    with torch.no_grad():
        xn = ref.normalize_inputs(b.xu)
        x_next = torch.tensor(np.concatenate([tr.targets for tr in b.data]), dtype=torch.float32)
        target = ref.normalized_residual(b.xu, x_next)
    torch.manual_seed(b.args.seed)
    modules = [_Member(PAPER[k % 4]) for k in range(K)]
    opt = torch.optim.Adam([p for mod in modules for p in mod.parameters()], lr=0.01,
                           foreach=True)

    def run():
        for _ in range(epochs):
            loss = sum(((mod(xn) - target) ** 2).sum(-1).mean() for mod in modules)
            opt.zero_grad(set_to_none=True)
            loss.backward()
            opt.step()

    return run


def epoch_times(b: _Bench) -> dict:
    """1. batched K = 1, 4, 8 vs K separate modules in a loop (full batch of 1000, one step per
    epoch), and the same K scaling in the paper's regime (3 trajectories x 200)."""
    a, epoch_ms = b.args, {}
    for K in (1, 4, 8):
        b.epochs(b.ensemble(K), b.data, 5)()  # warm-up
        _loop_epochs(b, K, 5)()
        # interleave the repeats of the two variants so load changes hit both alike
        runs = {f"batched_K{K}": b.epochs(b.ensemble(K), b.data, a.epochs),
                f"loop_K{K}": _loop_epochs(b, K, a.epochs)}
        samples: dict[str, list] = {k: [] for k in runs}
        cpu_samples: dict[str, list] = {k: [] for k in runs}
        for _ in range(a.repeats):
            for k, fn in runs.items():
                samples[k].append(b.median_ms(fn, 1, a.epochs, key=k))
                cpu_samples[k].append(b.cpu_ms[k])
        for k in runs:
            epoch_ms[k] = float(np.median(samples[k]))
            b.cpu_ms[k] = float(np.median(cpu_samples[k]))
        print(f"K={K}: batched {epoch_ms[f'batched_K{K}']:.3f} ms/epoch, "
              f"loop {epoch_ms[f'loop_K{K}']:.3f} ms/epoch", file=sys.stderr)
    elu = [MemberSpec("elu", 20, 1)] * 4
    b.epochs(b.ensemble(members=elu), b.data, 5)()  # warm-up
    epoch_ms["batched_K4_all_elu"] = b.median_ms(b.epochs(b.ensemble(members=elu), b.data,
                                                          a.epochs), a.repeats, a.epochs,
                                                 key="batched_K4_all_elu")
    nominal_k = {}
    for K in (1, 4, 8):
        model = b.ensemble(K)
        b.epochs(model, b.train, 3)()
        nominal_k[f"batched_K{K}"] = b.median_ms(b.epochs(model, b.train, a.epochs), a.repeats,
                                                 a.epochs, key=f"nominal_K{K}")
    print(f"nominal setting: {nominal_k}", file=sys.stderr)
    return {"epoch_ms_full_batch_1000": epoch_ms,
            "epoch_cpu_ms_full_batch_1000": {k: b.cpu_ms[k] for k in epoch_ms},
            "epoch_ms_nominal_3x200": nominal_k,
            "epoch_cpu_ms_nominal_3x200": {k: b.cpu_ms[f"nominal_{k[-2:]}"] for k in nominal_k}}


def jacobian_times(b: _Bench) -> dict:
    """2. Jacobians and the protocol surface at iLQR sizes."""
    model4 = b.ensemble(4)
    frozen4 = model4.freeze()  # the planning model: numpy surface without a freeze per call
    x1000, u1000 = (np.concatenate(p) for p in zip(*[tr.inputs for tr in b.data]))
    x200, u200 = b.train[0].inputs
    n = 50
    jac = {
        "member_jacobians_4x1000_numpy_ms": b.median_ms(
            lambda: [frozen4.member_jacobians(x1000, u1000) for _ in range(n)], 5, n),
        "mean_jacobians_4x1000_numpy_ms": b.median_ms(
            lambda: [frozen4.jacobians(x1000, u1000) for _ in range(n)], 5, n),
        "member_jacobians_4x1000_torch_ms": b.median_ms(
            lambda: [model4.member_jacobians_torch(torch.tensor(x1000), torch.tensor(u1000))
                     for _ in range(n)], 5, n),
        "mean_jacobians_4x200_numpy_us": 1e3 * b.median_ms(
            lambda: [frozen4.jacobians(x200, u200) for _ in range(n)], 5, n),
        "step_1_point_us": 1e3 * b.median_ms(
            lambda: [frozen4.step(x200[0], u200[0]) for _ in range(20 * n)], 5, 20 * n),
        "step_200_points_us": 1e3 * b.median_ms(
            lambda: [frozen4.step(x200, u200) for _ in range(n)], 5, n),
    }
    print(f"jacobians: {jac}", file=sys.stderr)
    return {"jacobians": jac}


def regularizer_times(b: _Bench) -> dict:
    """3. regularizer cost per epoch in the nominal setting (3 x 200, one step per
    trajectory), the LTV models fitted once outside the timing."""
    a = b.args
    t0 = time.perf_counter()
    ltv_models = [fit_ltv(tr, RegularizationConfig().ltv_lambda) for tr in b.train]
    ltv_fit_ms = (time.perf_counter() - t0) * 1e3 / len(b.train)
    regs = {
        "none": RegularizationConfig(),
        "sampled": RegularizationConfig.paper(),
        "exact": RegularizationConfig(exact_weight=1.0),
        "smooth": RegularizationConfig(smooth_weight=0.01),
        "sampled+exact+smooth": RegularizationConfig.paper(exact_weight=1.0, smooth_weight=0.01),
    }
    reg_ms = {}
    for name, reg in regs.items():
        model = b.ensemble(4)
        b.epochs(model, b.train, 3, reg, ltv_models=ltv_models)()
        reg_ms[name] = b.median_ms(b.epochs(model, b.train, a.epochs, reg, ltv_models=ltv_models),
                                   a.repeats, a.epochs, key=f"reg_{name}")
        print(f"{name}: {reg_ms[name]:.3f} ms/epoch", file=sys.stderr)
    return {"nominal_epoch_ms": reg_ms,
            "regularizer_epoch_ratio": {k: v / reg_ms["none"] for k, v in reg_ms.items()},
            "nominal_epoch_cpu_ms": {k: b.cpu_ms[f"reg_{k}"] for k in reg_ms},
            "ltv_fit_ms_per_trajectory": ltv_fit_ms}


def robot_training(b: _Bench) -> dict:
    """4. the paper's nominal robot model, sampled Jacobian propagation (and none), trained for
    ``robot_epochs``, with its held-out prediction and Jacobian errors."""
    a = b.args
    J_true = arm_jacobians(*b.val.inputs)
    robot = {}
    for name, reg in (("sampled", RegularizationConfig.paper()), ("none", RegularizationConfig())):
        model = DynamicsEnsemble(EnsembleConfig(4, 2, seed=a.seed))
        t0, c0 = time.perf_counter(), time.process_time()
        hist = train_ensemble(model, b.train, TrainConfig(epochs=a.robot_epochs, seed=a.seed,
                                                          progress=False), reg)
        robot[name] = {
            "seconds": time.perf_counter() - t0, "cpu_seconds": time.process_time() - c0,
            "steps": hist.steps, "final_train_loss": float(hist.train_loss[-1]),
            "val_prediction_rms": prediction_rms(model, [b.val]),
            "val_jacobian_error": jacobian_error(J_true, model.member_jacobians(*b.val.inputs)),
        }
        print(f"robot {name}: {robot[name]}", file=sys.stderr)
    return {"nominal_robot_training": robot}


def _target(value: float, cpu_value: float, **bound: float) -> dict:
    met = value <= bound["max"] if "max" in bound else value >= bound["min"]
    return {"value": value, "cpu_time_value": cpu_value, **bound, "met": bool(met)}


def run(args: Args) -> dict:
    """Run the benchmark; print and return the results (and write ``args.out``).

    ``args.threads`` sets torch's threads; BLAS reads ``OMP_NUM_THREADS`` (the command sets one
    thread unless it is set).
    """
    torch.set_num_threads(args.threads)
    b = _Bench(args)
    print(f"data: {len(b.data)} trajectories, {b.xu.shape[0]} transitions; "
          f"threads {args.threads}, load {os.getloadavg()}", file=sys.stderr)
    load_start = os.getloadavg()
    results: dict = {"config": dataclasses.asdict(args)}
    for section in (epoch_times, jacobian_times, regularizer_times, robot_training):
        results.update(section(b))
    epoch_ms, cpu = results["epoch_ms_full_batch_1000"], results["epoch_cpu_ms_full_batch_1000"]
    nominal_k, robot = results["epoch_ms_nominal_3x200"], results["nominal_robot_training"]
    results["diagnostics"] = {
        "nominal_3x200_batched_K4_over_K1": nominal_k["batched_K4"] / nominal_k["batched_K1"],
        "full_batch_K4_all_elu_over_K1": epoch_ms["batched_K4_all_elu"] / epoch_ms["batched_K1"],
    }
    results["targets"] = {
        "batched_K4_over_K1": _target(epoch_ms["batched_K4"] / epoch_ms["batched_K1"],
                                      cpu["batched_K4"] / cpu["batched_K1"], max=1.5),
        "loop_K8_over_batched_K8": _target(epoch_ms["loop_K8"] / epoch_ms["batched_K8"],
                                           cpu["loop_K8"] / cpu["batched_K8"], min=2.0),
        "nominal_robot_training_seconds": _target(robot["sampled"]["seconds"],
                                                  robot["sampled"]["cpu_seconds"], max=10.0),
    }
    results["machine"] = machine_info(load_start, torch=torch.__version__, numpy=np.__version__)
    print(json.dumps(results, indent=2))
    write_result(args.out, results, indent=2)
    return results


if __name__ == "__main__":
    main()
