"""The paper's evaluation metrics (Sec. "Evaluation"; table in docs/models.md, "Metrics") for
any :class:`mbtsr.dynamics.DynamicsModel` (an ensemble by its mean), in float64.
"""

from __future__ import annotations

from collections.abc import Sequence

import numpy as np

from mbtsr.dynamics import DynamicsModel, rollout
from mbtsr.trajectory import Trajectory, as_trajectory_list
from mbtsr.validation import as_array, check_int, check_positive

__all__ = [
    "prediction_rms",
    "k_step_rms",
    "simulation_rms",
    "jacobian_error",
    "jacobian_rms_per_entry",
    "jacobian_eigenvalues",
]


def _checked_trajs(model: DynamicsModel, trajs: object) -> list[Trajectory]:
    """``trajs`` as a list, checked against the model's dimensions."""
    n, m = getattr(model, "state_dim", None), getattr(model, "action_dim", None)
    if n is None or m is None or not hasattr(model, "step"):
        raise ValueError("model must implement the DynamicsModel protocol (step, state_dim, "
                         "action_dim)")
    return as_trajectory_list(trajs, dims=(n, m))


def _rms(err: np.ndarray, per_dimension: bool) -> float | np.ndarray:
    """RMS of ``err: [..., n]`` over all leading axes (and over n unless ``per_dimension``)."""
    with np.errstate(over="ignore", invalid="ignore"):
        sq = np.where(np.isfinite(err), err * err, np.inf)
        if per_dimension:
            return np.sqrt(sq.reshape(-1, err.shape[-1]).mean(0))
        return float(np.sqrt(sq.mean()))


def prediction_rms(
    model: DynamicsModel, trajs: Trajectory | Sequence[Trajectory], *, per_dimension: bool = False
) -> float | np.ndarray:
    """One-step prediction RMS ``sqrt(mean (x_{t+1} - f(x_t, u_t))^2)`` over all transitions
    (``model.step`` once per trajectory, ``t=None``: time-invariant models).

    :param model: a dynamics model (an ensemble is evaluated by its mean).
    :param trajs: trajectories (``x: [T+1, n]``, ``u: [T, m]``).
    :param per_dimension: return the RMS per state dimension ``[n]`` (the original's ``rms``)
        instead of one number.
    :return: float, or ``[n]``; ``inf`` if a prediction is not finite.
    """
    trajs = _checked_trajs(model, trajs)
    err = [tr.x[1:] - np.asarray(model.step(tr.x[:-1], tr.u), dtype=float) for tr in trajs]
    return _rms(np.concatenate(err), per_dimension)


def simulation_rms(
    model: DynamicsModel,
    trajs: Trajectory | Sequence[Trajectory],
    *,
    divergence_threshold: float = 100.0,
    per_dimension: bool = False,
) -> tuple[float | np.ndarray, int]:
    """Simulation RMS over ``t = 1..T`` of a free run from the recorded ``x_0`` driven by the
    recorded inputs (aligned trajectories as one batch). Diverged: non-finite, or a state
    further from the truth than ``divergence_threshold`` times its std over time (0 counts 1).

    :param divergence_threshold: ``> 0``, in units of the per-dimension std (default 100).
    :param per_dimension: return the RMS per state dimension ``[n]``.
    :return: ``(rms, n_diverged)``. ``rms`` pools all trajectories, diverged ones included, and
        is ``inf`` when a simulation blew up to non-finite values.
    """
    trajs = _checked_trajs(model, trajs)
    thr = check_positive("divergence_threshold", divergence_threshold)
    errs, n_diverged = [], 0
    for T in sorted({tr.T for tr in trajs}):
        group = [tr for tr in trajs if tr.T == T]
        X = np.stack([tr.x for tr in group], 1)  # [T+1, N, n]
        U = np.stack([tr.u for tr in group], 1)  # [T, N, m]
        sim = rollout(model, X[0], U)
        err = sim[1:] - X[1:]  # [T, N, n]
        scale = X.std(0)
        scale = np.where(scale > 0, scale, 1.0)
        with np.errstate(invalid="ignore", over="ignore"):
            far = np.abs(err) / scale > thr
        bad = ~np.isfinite(err) | far
        n_diverged += int(np.any(bad, axis=(0, 2)).sum())
        errs.append(err.reshape(-1, err.shape[-1]))
    return _rms(np.concatenate(errs), per_dimension), n_diverged


def k_step_rms(
    model: DynamicsModel,
    trajs: Trajectory | Sequence[Trajectory],
    k: int,
    *,
    per_dimension: bool = False,
) -> float | np.ndarray:
    """Open-loop prediction RMS ``k`` steps ahead from every start ``t = 0..T-k`` of the
    trajectories with ``T >= k`` (one batch); ``k = 1`` is :func:`prediction_rms`.

    :param k: steps ahead, ``>= 1``.
    :param per_dimension: return the RMS per state dimension ``[n]``.
    :return: float, or ``[n]``; ``inf`` if a prediction is not finite.
    :raises ValueError: ``k`` is not an integer >= 1, or no trajectory has ``k`` steps.
    """
    check_int("k", k, 1)
    trajs = _checked_trajs(model, trajs)
    long = [tr for tr in trajs if tr.T >= k]
    if not long:
        raise ValueError(f"no trajectory has k={k} steps (the longest has "
                         f"{max(tr.T for tr in trajs)})")
    n0 = [tr.T - k + 1 for tr in long]  # starts per trajectory
    x0 = np.concatenate([tr.x[:s] for tr, s in zip(long, n0)])  # [N, n]
    inputs = np.stack([np.concatenate([tr.u[j: j + s] for tr, s in zip(long, n0)])
                       for j in range(k)])  # [k, N, m]
    target = np.concatenate([tr.x[k: k + s] for tr, s in zip(long, n0)])
    x = rollout(model, x0, inputs)[-1]  # NaN once a prediction diverged
    return _rms(target - x, per_dimension)


def _as_jacobian(name: str, J: object, allow_members: bool) -> np.ndarray:
    """``[T, n, n+m]`` (or ``[K, T, n, n+m]``) from an array or an ``(A, B)`` pair."""
    if isinstance(J, tuple):
        if len(J) != 2:
            raise ValueError(f"{name} as a tuple must be (A, B)")
        A = as_array(f"{name}[0] (A)", J[0])
        B = as_array(f"{name}[1] (B)", J[1])
        if A.ndim != B.ndim or A.shape[:-1] != B.shape[:-1] or A.shape[-1] != A.shape[-2]:
            raise ValueError(
                f"{name}: A must be [..., n, n] and B [..., n, m] with the same leading shape, "
                f"got {list(A.shape)} and {list(B.shape)}"
            )
        J = np.concatenate([A, B], -1)
    else:
        J = as_array(name, J)
    allowed = (3, 4) if allow_members else (3,)
    if J.ndim not in allowed or J.shape[-1] <= J.shape[-2]:
        want = "[T, n, n+m]" + (" or [K, T, n, n+m]" if allow_members else "")
        raise ValueError(f"{name} must be {want} (m >= 1), got shape {list(J.shape)}")
    return J


def jacobian_error(J_true: object, J_hat: object) -> float:
    """The paper's Jacobian error, eq. (jacerr)::

        sqrt( 1/T sum_t || J_t - 1/|E| sum_E Jhat_t ||_F^2 )

    :param J_true: ``[T, n, n+m]`` true Jacobians ``[A_t B_t]`` or a pair ``(A [T, n, n],
        B [T, n, m])``.
    :param J_hat: model Jacobians at the same points: per member ``[K, T, n, n+m]`` (averaged over
        the ensemble here), already averaged ``[T, n, n+m]``, or an ``(A, B)`` pair of either.
    :return: the error (float64).
    """
    J = _as_jacobian("J_true", J_true, allow_members=False)
    Jh = _as_jacobian("J_hat", J_hat, allow_members=True)
    if Jh.ndim == 4:
        Jh = Jh.mean(0)
    if Jh.shape != J.shape:
        raise ValueError(f"J_hat must match J_true's shape {list(J.shape)}, got {list(Jh.shape)}")
    D = J - Jh
    return float(np.sqrt(np.mean(np.sum(D * D, axis=(-1, -2)))))


def jacobian_rms_per_entry(J_true: object, J_hat: object) -> float:
    """The original code's Jacobian error (``eval_jac``), the RMS over points and entries:
    ``jacobian_error / sqrt(n (n+m))``; arguments as :func:`jacobian_error`."""
    J = _as_jacobian("J_true", J_true, allow_members=False)
    return jacobian_error(J, J_hat) / float(np.sqrt(J.shape[-1] * J.shape[-2]))


def jacobian_eigenvalues(
    model_or_A: DynamicsModel | np.ndarray,
    x: np.ndarray | None = None,
    u: np.ndarray | None = None,
) -> np.ndarray:
    """Eigenvalues of the state Jacobian ``A_t = df/dx`` at the given points.

    :param model_or_A: a dynamics model (then ``x: [T, n]`` and ``u: [T, m]`` give the points and
        ``model.jacobians`` the ensemble-mean ``A_t``), or the matrices ``A: [T, n, n]`` (or one
        ``[n, n]``) themselves.
    :return: ``[T, n]`` complex eigenvalues, each row sorted by decreasing modulus, then by angle.
    """
    if isinstance(model_or_A, np.ndarray | list | tuple):
        if x is not None or u is not None:
            raise ValueError("x and u are only used with a model, not with matrices A")
        A = as_array("A", model_or_A)
        if A.ndim == 2:
            A = A[None]
    else:
        if not hasattr(model_or_A, "jacobians"):
            raise ValueError("model_or_A must be a DynamicsModel or an array A [T, n, n]")
        if x is None or u is None:
            raise ValueError("x [T, n] and u [T, m] are needed to evaluate a model's Jacobians")
        A, _ = model_or_A.jacobians(x, u)
        A = as_array("A (model Jacobian)", A)
    if A.ndim != 3 or A.shape[1] != A.shape[2]:
        raise ValueError(f"A must be [T, n, n], got shape {list(A.shape)}")
    ev = np.linalg.eigvals(A)
    order = np.lexsort((np.angle(ev), np.round(-np.abs(ev), 10)), axis=-1)  # conjugates tie
    return np.take_along_axis(ev, order, -1)
