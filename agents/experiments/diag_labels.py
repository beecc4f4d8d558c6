"""What do the regularizers pull the model towards during an agent run? A diagnostic.

Runs the suite's agent (:func:`agents.experiments.bench_suite.make_agent`: the task's defaults,
``cem-ilqr``) once per regularization and, after every episode, replays the episode in a fresh
env (same reset seed, same actions; the replay must reproduce the recorded observations) to get
its MuJoCo states, and compares with the true Jacobians there
(:func:`agents.experiments.exp_small_data.true_jacobians`, on the observation's tangent space):

* ``label``: the LTV model the regularizer used for the episode (``sampled``/``exact`` only;
  the smooth fit fused with the model's Jacobians, as the agent makes it);
* ``fit``: the smooth LTV fit alone, at the same ``lambda`` (for ``none``, the agent's automatic
  choice);
* ``model``: the ensemble mean's Jacobians at the episode's points after the update on it;
* ``model_before``: the same of the model before that update (the previous episode's).

Each is reported as three numbers (:func:`split_errors`): ``all``, the relative error of
:func:`~agents.experiments.exp_small_data.jacobian_rel_error`; ``identified``, the same error
restricted to the directions the episode moved in (the observation-space directions of the
state coordinates that changed; those of coordinates that stayed constant through the episode,
such as Reacher's target, are left out: one episode's data cannot identify a Jacobian along
them);
``unidentified``, the median norm of the estimate's ``A`` along those directions (the truth's
norm is ``truth_unidentified``).

Each episode's row also holds the agent's log fields ``one_step_rms``, ``train_steps`` and
``eval_return``; the agent's evaluation stops early once it cannot reach the oracle's solved
threshold (the agent's default early exit), and then ``eval_return`` is ``None``.

    python scripts/diag_labels.py --task reacher --regularizations none exact --out runs/l.json
"""

from __future__ import annotations

import copy
import time
from dataclasses import asdict, dataclass
from typing import Any

import numpy as np
import torch

from agents.cli import main as command
from agents.experiments.bench_model_sizes import ltv_fit
from agents.experiments.bench_suite import TASKS, make_agent
from agents.experiments.exp_small_data import jacobian_rel_error, true_jacobians
from agents.experiments.paper_common import pyplot, save_figure
from mbtsr.io import write_json_atomic
from mbtsr.trajectory import Trajectory
from mbtsr.validation import check_int

REGULARIZATIONS = ("none", "sampled", "exact")
MUJOCO_TASKS = ("reacher", "inverted-pendulum", "inverted-double-pendulum", "pusher",
                "half-cheetah")  # those of agents.tasks (true_jacobians makes them by name)


@dataclass(frozen=True)
class Args:
    """Jacobian errors of the LTV labels and of the model along an agent run."""

    out: str = "runs/diag_labels.json"
    """output JSON (rewritten after every episode)"""
    smoke: bool = False
    """the suite's tiny model and planner and a short run (CI): the options not given take
    SMOKE's values"""
    task: str = "reacher"
    """a suite task (agents.tasks.SUITE)"""
    regularizations: tuple[str, ...] = ("none", "exact")
    """one agent run each (none, sampled, exact)"""
    seed: int = 0
    """the agent's seed"""
    env_steps: int = 2000
    """each run's budget (the suite's Reacher budget)"""
    plot: str = ""
    """PNG of the identified-direction errors along the runs ('' for none)"""

    def __post_init__(self) -> None:
        if self.task not in TASKS:
            raise ValueError(f"task must be one of {sorted(TASKS)}, got {self.task!r}")
        if self.task not in MUJOCO_TASKS or TASKS[self.task]["task"].state_fn is not None:
            raise ValueError(f"task {self.task!r}: the diagnostic needs a MuJoCo task of "
                             f"agents.tasks whose model state is the observation, one of "
                             f"{[t for t in MUJOCO_TASKS if TASKS[t]['task'].state_fn is None]}")
        bad = [r for r in self.regularizations if r not in REGULARIZATIONS]
        if bad or not self.regularizations:
            raise ValueError(f"regularizations must be some of {REGULARIZATIONS}, got "
                             f"{self.regularizations!r}")
        check_int("seed", self.seed, 0)
        check_int("env_steps", self.env_steps, 2)


#: --smoke: the tiny CI size (options given on the command line win)
SMOKE = {"smoke": True, "env_steps": 200, "out": "runs/diag_labels_smoke.json"}


def main(argv: list[str] | None = None) -> dict:
    """The command line (``--help``: the options)."""
    from agents.experiments.paper_common import blas_threads_from_env

    blas_threads_from_env()  # one BLAS thread unless OMP_NUM_THREADS says otherwise
    return command(Args, run, args=argv, outputs=("out", "plot"), presets={"--smoke": SMOKE})


def replay_states(env: Any, traj: Trajectory, state_of: Any) -> np.ndarray:
    """The MuJoCo states ``[T, nq + nv]`` before each action of ``traj``, replayed in ``env``
    from ``traj.meta["seed"]``.

    :param state_of: ``obs [k, d] -> model state [k, n]`` (the agent's state map).
    :raises ValueError: if the replay does not reproduce the recorded states (a non-deterministic
        env, or a trajectory that did not start at that reset).
    """
    if "seed" not in traj.meta:
        raise ValueError("the trajectory has no reset seed in its meta (the agent's own "
                         "trajectories have one): nothing to replay from")
    if traj.meta["seed"] is None:
        raise ValueError(f"episode {traj.meta.get('episode')} continued an earlier rollout "
                         "(collection.continue_rollouts): it has no reset seed to replay from")
    obs, _ = env.reset(seed=int(traj.meta["seed"]))
    data, states = env.unwrapped.data, []
    for t in range(traj.T + 1):
        if not np.allclose(state_of(obs[None])[0], traj.x[t], rtol=1e-6, atol=1e-8):
            raise ValueError(f"the replay of episode seed {traj.meta['seed']} leaves the "
                             f"recorded states at step {t}")
        if t < traj.T:
            states.append(np.concatenate([data.qpos, data.qvel]))
            obs, *_ = env.step(traj.u[t])
    return np.array(states)


def split_errors(A: np.ndarray, B: np.ndarray, P: np.ndarray, W: np.ndarray, U: np.ndarray,
                 A_hat: np.ndarray, B_hat: np.ndarray) -> dict[str, float]:
    """The module docstring's ``all``, ``identified`` and ``unidentified`` of an estimate
    ``(A_hat [T, d, d], B_hat [T, d, m])`` against the truth ``(A [T, d, d], B [T, d, m])``
    with tangent projector ``P [T, d, d]``, ``W [T, d, k1]`` an orthonormal basis of the
    identified directions and ``U [T, d, k2]`` of the unidentified ones
    (:func:`directions`)::

        identified_t = ||[(A_hat_t P_t - A_t) W_t, B_hat_t - B_t]||_F / ||[A_t W_t, B_t]||_F

    (its median over ``t``); ``unidentified``, the median of ``||A_hat_t P_t U_t||_F``.

    :raises ValueError: on arrays whose shapes disagree.
    """
    T, d = A.shape[0], A.shape[1]
    m = B.shape[2]
    for name, arr, shape in (("A", A, (T, d, d)), ("B", B, (T, d, m)), ("P", P, (T, d, d)),
                             ("A_hat", A_hat, (T, d, d)), ("B_hat", B_hat, (T, d, m))):
        if arr.shape != shape:
            raise ValueError(f"{name} has shape {arr.shape}, expected {shape}")
    for name, arr in (("W", W), ("U", U)):
        if arr.ndim != 3 or arr.shape[:2] != (T, d):
            raise ValueError(f"{name} has shape {arr.shape}, expected ({T}, {d}, k)")
    D = A_hat @ P - A
    num = np.sqrt(np.sum((D @ W) ** 2, (1, 2)) + np.sum((B_hat - B) ** 2, (1, 2)))
    den = np.sqrt(np.sum((A @ W) ** 2, (1, 2)) + np.sum(B**2, (1, 2)))
    return {"all": jacobian_rel_error(A, B, P, A_hat, B_hat)["jac_rel"],
            "identified": float(np.median(num / den)),
            "unidentified": float(np.median(np.linalg.norm(A_hat @ P @ U, axis=(1, 2)))),
            "truth_unidentified": float(np.median(np.linalg.norm(A @ U, axis=(1, 2))))}


def directions(task: str, states: np.ndarray, tol: float = 1e-9
               ) -> tuple[np.ndarray, np.ndarray]:
    """``(W [T, d, k1], U [T, d, k2])``: orthonormal bases of the observation-space directions
    spanned by the state coordinates that move within ``states [T, nq + nv]`` (identified) and
    by those that stay constant (unidentified), i.e. of those columns of ``C = d obs / dx``.
    The two spaces need not be orthogonal (Reacher's fingertip - target mixes the arm's and
    the target's coordinates).

    :raises ValueError: if either space's dimension changes along the episode.
    """
    from envs.mujoco_model import MujocoDynamics, ObservedDynamics

    env = TASKS[task]["task"].make_env()
    env.reset(seed=0)
    C = np.asarray(ObservedDynamics(MujocoDynamics(env), env).observation_jacobian(states))
    env.close()
    const = np.ptp(states, axis=0) <= tol * (1.0 + np.abs(states).max(axis=0))

    def basis(cols: np.ndarray) -> np.ndarray:
        out = []
        for Ct in cols:
            u, s, _ = np.linalg.svd(Ct, full_matrices=False)
            out.append(u[:, s > 1e-8 * max(s.max(initial=0.0), 1e-300)])
        ranks = {o.shape[1] for o in out}
        if len(ranks) > 1:
            raise ValueError(f"the observation's directions change dimension along the episode "
                             f"({sorted(ranks)})")
        return np.stack(out)

    return basis(C[:, :, ~const]), basis(C[:, :, const])


def run(args: Args) -> dict[str, Any]:
    """One agent run per regularization; see the module docstring."""
    torch.set_num_threads(1)
    result: dict[str, Any] = {"args": asdict(args), "runs": {}}
    for reg in args.regularizations:
        agent = make_agent(args.task, {"seed": args.seed, "planner.kind": "cem-ilqr",
                                       "regularization": reg}, smoke=args.smoke)
        replay = TASKS[args.task]["task"].make_env()
        rows: list[dict[str, Any]] = []
        previous: dict[str, Any] = {"model": None}
        result["runs"][reg] = rows

        def record(info: dict[str, Any], agent=agent, replay=replay, rows=rows,
                   previous=previous, reg=reg) -> None:
            tic = time.process_time()
            traj = agent.trajectories[-1]
            if traj.T < 2:
                previous["model"] = copy.deepcopy(agent.model)
                return
            x, u = traj.inputs
            states = replay_states(replay, traj, agent.state_map.state)
            A, B, P = true_jacobians(args.task, states, u)
            W, U = directions(args.task, states)
            lam = agent.ltv_lambdas[-1] if reg != "none" else agent.labeler.select_lambda(traj)
            fit = ltv_fit(traj, lam)
            row: dict[str, Any] = {
                "episode": len(agent.trajectories) - 1, "env_steps": agent.env_steps,
                **{k: info["row"].get(k) for k in ("eval_return", "one_step_rms",
                                                    "train_steps")},
                "lambda": lam,
                "fit": split_errors(A, B, P, W, U, np.asarray(fit.A)[:traj.T],
                                    np.asarray(fit.B)[:traj.T]),
                "model": split_errors(A, B, P, W, U, *agent.model.jacobians(x, u))}
            if reg != "none":
                lm = agent.ltv_models[-1]
                row["label"] = split_errors(A, B, P, W, U, np.asarray(lm.A)[:traj.T],
                                            np.asarray(lm.B)[:traj.T])
            if previous["model"] is not None:
                row["model_before"] = split_errors(A, B, P, W, U,
                                                   *previous["model"].jacobians(x, u))
            previous["model"] = copy.deepcopy(agent.model)
            row["cpu_s"] = time.process_time() - tic
            rows.append(row)
            write_json_atomic(args.out, result)

        agent.learn(total_timesteps=args.env_steps, callback=record, progress_bar=False)
        replay.close()
        agent.env.close()
    result["summary"] = summarize(result["runs"])
    write_json_atomic(args.out, result)
    if args.plot:
        plot(result, args.plot)
    for reg, s in result["summary"].items():
        print(f"{reg}: " + ", ".join(f"{k} {v['identified']:.3f}" for k, v in s.items()
                                    if isinstance(v, dict)) + f"; final {s['final_return']}")
    return result


def summarize(runs: dict[str, list[dict[str, Any]]]) -> dict[str, dict[str, Any]]:
    """Per regularization: the median over episodes of each estimate's three errors, and the
    run's last evaluation return."""
    out: dict[str, dict[str, Any]] = {}
    for reg, rows in runs.items():
        s: dict[str, Any] = {}
        for what in ("fit", "label", "model", "model_before"):
            got = [r[what] for r in rows if what in r]
            if got:
                s[what] = {k: float(np.median([g[k] for g in got])) for k in got[0]}
        evals = [r["eval_return"] for r in rows if r.get("eval_return") is not None]
        s["final_return"] = evals[-1] if evals else None
        out[reg] = s
    return out


def plot(result: dict[str, Any], out: str) -> None:
    """The identified-direction Jacobian error of each run's model (after each update), of the
    labels and of the smooth fits, against env steps (log scale)."""
    plt = pyplot()

    fig, ax = plt.subplots(figsize=(7, 4))
    colours = {"none": "C0", "sampled": "C1", "exact": "C2"}
    for reg, rows in result["runs"].items():
        steps = [r["env_steps"] for r in rows]
        ax.plot(steps, [r["model"]["identified"] for r in rows], "-", color=colours[reg],
                label=f"{reg}: model")
        if reg != "none":
            ax.plot(steps, [r["label"]["identified"] for r in rows], ":", color=colours[reg],
                    label=f"{reg}: its LTV labels")
        else:
            ax.plot(steps, [r["fit"]["identified"] for r in rows], ":", color="grey",
                    label="smooth LTV fit (none's episodes)")
    ax.set_yscale("log")
    ax.set_xlabel("env steps")
    ax.set_ylabel("relative Jacobian error, identified directions")
    ax.set_title(f"{result['args']['task']}, seed {result['args']['seed']}: Jacobians against "
                 "the true MuJoCo model")
    ax.legend(fontsize=8)
    ax.grid(alpha=0.3, which="both")
    save_figure(fig, out)


if __name__ == "__main__":
    main()
