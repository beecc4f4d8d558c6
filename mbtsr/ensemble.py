"""Neural-network dynamics ensembles: K members evaluated and trained in ONE batched computation.

The paper's nominal model (Bagge Carlson et al., Sec. "Nominal model") is an ensemble of 4
single-hidden-layer networks with 20 units and the activations elu, sigmoid, tanh and swish, all
trained on the same data with different random initialisations. Each member models

    x+ = s(x, u) + NN_k(x, u)

where the *skip part* ``s`` is fixed by the formulation (paper Objectives 1 and 2 and Sec.
"Weight decay"):

=============  ==========================  ========================================
formulation    s(x, u)                     Jacobian of s, ``[n, n+m]``
=============  ==========================  ========================================
``"f"``        0                           0
``"g"``        x                           [I  0]
``"nominal"``  A0 x + B0 u                 [A0 B0]
``"scaled"``   tau * x (tau scalar/[n])    [diag(tau) 0]
=============  ==========================  ========================================

Normalization (``EnsembleConfig.normalize``, default on; the original code had none): the
network sees standardized inputs and produces a standardized *residual*::

    NN_k(x, u) = out_mean + out_std * net_k(([x, u] - in_mean) / in_std)

``in_mean/in_std`` are per-dimension statistics of ``[x_t, u_t]`` and ``out_mean/out_std`` of the
residual targets ``x_{t+1} - s(x_t, u_t)`` over all transitions given to
:meth:`DynamicsEnsemble.set_normalization` (called once by training if unset, then frozen so a warm
start does not change the function the weights represent). Weight decay shrinks the weights of
``net_k``, so it pulls the model Jacobian toward the skip Jacobian (0 for f, I for g, ...) as in the
paper's analysis, but its strength acts on normalized units: a raw Jacobian entry ``(i, j)`` is
``out_std[i] / in_std[j]`` times the normalized one.

Members may differ in activation, width (padded to the widest member with a fixed zero mask),
depth (1 or 2 hidden layers; members are grouped by depth, one batched computation per group),
dropout and layer normalization. Jacobians are computed in closed form
(``W_out^T diag(act'(z)) W_1^T`` chains), batched over points and members, in torch (differentiable,
for Jacobian penalties by double backprop) and in a cached float64 numpy path used by the dynamics
protocol (``step``, ``predict``, ``jacobians``).
"""

from __future__ import annotations

import json
import math
import os
from collections.abc import Callable, Sequence
from dataclasses import asdict, dataclass, field
from operator import attrgetter
from types import SimpleNamespace

import numpy as np
import torch
from scipy.special import expit
from torch import nn
from torch.nn import functional as F  # noqa: N812
from torch.optim.optimizer import register_optimizer_step_post_hook

from mbtsr.dynamics import check_step_inputs
from mbtsr.fileformat import CheckpointError, torch_load_verified, torch_save_verified
from mbtsr.trajectory import Trajectory
from mbtsr.validation import as_array

__all__ = [
    "ACTIVATIONS",
    "FORMULATIONS",
    "MemberSpec",
    "EnsembleConfig",
    "DynamicsEnsemble",
    "save_model",
    "load_model",
]

FORMULATIONS = ("f", "g", "nominal", "scaled")
LEAKY_RELU_SLOPE = 0.01
LAYER_NORM_EPS = 1e-5
_VERSION = attrgetter("_version")
_OPTIMIZER_STEPS = [0]  # steps of any torch optimizer so far: part of the numpy cache key, because
# fused optimizers (``torch.optim.Adam(fused=True)``, used by training) update parameters in place
# WITHOUT bumping their version counters (measured, torch 2.13)


def _count_optimizer_step(optimizer, args, kwargs) -> None:
    _OPTIMIZER_STEPS[0] += 1


register_optimizer_step_post_hook(_count_optimizer_step)
STD_FLOOR = 1e-8  # a dimension with a smaller std (e.g. a constant input) is not rescaled


# --------------------------------------------------------------------------------------------
# Activations: value act(z) and derivative act'(z) given (z, act(z)). Torch values use the fused
# built-ins; torch derivatives are differentiable (Jacobian penalties back-propagate through them).
# --------------------------------------------------------------------------------------------


def _d_elu(z, a, xp):
    return xp.where(z > 0, 1.0, a + 1.0)


def _d_sigmoid(z, a, xp):
    return a * (1.0 - a)


def _d_tanh(z, a, xp):
    return 1.0 - a * a


def _d_swish(z, a, xp):
    s = torch.sigmoid(z) if xp is torch else expit(z)
    return s * (1.0 + z * (1.0 - s))


def _d_relu(z, a, xp):
    return (z > 0) * 1.0


def _d_leaky_relu(z, a, xp):
    return xp.where(z > 0, 1.0, LEAKY_RELU_SLOPE)


def _tanh_via_sigmoid(z: torch.Tensor) -> torch.Tensor:
    """``tanh(z) = 2 sigmoid(2 z) - 1``: torch 2.13's CPU tanh kernel measured ~10x slower than
    its sigmoid on the project's machines (AVX512 path); absolute difference <= 2e-7."""
    return torch.sigmoid(2.0 * z) * 2.0 - 1.0


ACTIVATIONS: dict[str, tuple[Callable, Callable, Callable]] = {
    "elu": (F.elu, lambda z: np.where(z > 0, z, np.expm1(np.minimum(z, 0.0))), _d_elu),
    "sigmoid": (torch.sigmoid, expit, _d_sigmoid),
    "tanh": (_tanh_via_sigmoid, np.tanh, _d_tanh),
    "swish": (F.silu, lambda z: z * expit(z), _d_swish),
    "relu": (F.relu, lambda z: np.maximum(z, 0.0), _d_relu),
    "leaky_relu": (
        lambda z: F.leaky_relu(z, LEAKY_RELU_SLOPE),
        lambda z: np.where(z > 0, z, LEAKY_RELU_SLOPE * z),
        _d_leaky_relu,
    ),
}
"""Supported activations: name -> (torch value, numpy value, derivative ``d(z, act(z), xp)``).
``swish(z) = z * sigmoid(z)`` (silu), ``elu`` with alpha 1, ``leaky_relu`` with slope 0.01."""


# --------------------------------------------------------------------------------------------
# Configuration
# --------------------------------------------------------------------------------------------


@dataclass(frozen=True)
class MemberSpec:
    """One ensemble member's architecture.

    :param activation: one of :data:`ACTIVATIONS` (elu, sigmoid, tanh, swish, relu, leaky_relu).
    :param width: hidden units per layer (paper: 20).
    :param depth: number of hidden layers, 1 (paper, arXiv v1) or 2 (the original code after
        2018-10; paper appendix "Number of layers").
    :param dropout: dropout probability on hidden units during training, in ``[0, 1)`` (paper
        appendix "Dropout": 0.2 studied). Inverted dropout; off in evaluation and Jacobians.
    :param layer_norm: layer normalization (with gain and bias) of each hidden pre-activation
        (paper appendix "Layer normalization").
    """

    activation: str = "elu"
    width: int = 20
    depth: int = 1
    dropout: float = 0.0
    layer_norm: bool = False

    def __post_init__(self) -> None:
        if self.activation not in ACTIVATIONS:
            raise ValueError(
                f"activation must be one of {sorted(ACTIVATIONS)}, got {self.activation!r}"
            )
        if isinstance(self.width, bool) or not isinstance(self.width, (int, np.integer)):
            raise ValueError(f"width must be an int >= 1, got {self.width!r}")
        if self.width < 1:
            raise ValueError(f"width must be an int >= 1, got {self.width!r}")
        if self.depth not in (1, 2) or isinstance(self.depth, bool):
            raise ValueError(f"depth must be 1 or 2, got {self.depth!r}")
        if not (np.isfinite(self.dropout) and 0.0 <= self.dropout < 1.0):
            raise ValueError(f"dropout must be in [0, 1), got {self.dropout!r}")
        if not isinstance(self.layer_norm, (bool, np.bool_)):
            raise ValueError(f"layer_norm must be a bool, got {self.layer_norm!r}")
        object.__setattr__(self, "width", int(self.width))
        object.__setattr__(self, "dropout", float(self.dropout))
        object.__setattr__(self, "layer_norm", bool(self.layer_norm))


def _paper_members() -> tuple[MemberSpec, ...]:
    return tuple(MemberSpec(a, 20, 1) for a in ("elu", "sigmoid", "tanh", "swish"))


def _as_matrix_tuple(name: str, a: object, shape: tuple[int, int]) -> tuple[tuple[float, ...], ...]:
    arr = as_array(name, a, shape)
    return tuple(tuple(float(v) for v in row) for row in arr)


@dataclass(frozen=True)
class EnsembleConfig:
    """Architecture of a :class:`DynamicsEnsemble`.

    :param state_dim: n.
    :param action_dim: m.
    :param members: one :class:`MemberSpec` per member; default the paper's nominal ensemble of
        four 20-unit single-layer networks with elu, sigmoid, tanh and swish.
    :param formulation: ``"f"`` (x+ = NN), ``"g"`` (x+ = x + NN, paper Objective 2, the default),
        ``"nominal"`` (x+ = A0 x + B0 u + NN) or ``"scaled"`` (x+ = tau x + NN); paper Sec.
        "Weight decay".
    :param A0: ``[n, n]`` nominal state matrix (formulation ``"nominal"`` only).
    :param B0: ``[n, m]`` nominal input matrix (formulation ``"nominal"`` only).
    :param tau: skip scale of formulation ``"scaled"``, a scalar or ``[n]`` (a diagonal).
    :param normalize: standardize network inputs ``[x, u]`` and residual outputs with statistics
        of the training data (see the module docstring); ``False`` feeds raw data as the
        original code did.
    :param seed: seed of the weight initialisation (glorot-uniform weights, zero biases, as Flux).

    Arrays are stored as tuples so the config is hashable and JSON-serializable.
    """

    state_dim: int
    action_dim: int
    members: tuple[MemberSpec, ...] = field(default_factory=_paper_members)
    formulation: str = "g"
    A0: tuple[tuple[float, ...], ...] | None = None
    B0: tuple[tuple[float, ...], ...] | None = None
    tau: float | tuple[float, ...] = 1.0
    normalize: bool = True
    seed: int = 0

    def __post_init__(self) -> None:
        for name in ("state_dim", "action_dim"):
            v = getattr(self, name)
            if isinstance(v, bool) or not isinstance(v, (int, np.integer)) or v < 1:
                raise ValueError(f"{name} must be an int >= 1, got {v!r}")
            object.__setattr__(self, name, int(v))
        n, m = self.state_dim, self.action_dim
        members = tuple(self.members)
        if len(members) == 0:
            raise ValueError("members must hold at least one MemberSpec")
        for i, spec in enumerate(members):
            if not isinstance(spec, MemberSpec):
                raise ValueError(f"members[{i}] must be a MemberSpec, got {type(spec).__name__}")
        object.__setattr__(self, "members", members)
        if self.formulation not in FORMULATIONS:
            raise ValueError(f"formulation must be one of {FORMULATIONS}, got {self.formulation!r}")
        if self.formulation == "nominal":
            if self.A0 is None or self.B0 is None:
                raise ValueError("formulation 'nominal' needs A0 [n, n] and B0 [n, m]")
            object.__setattr__(self, "A0", _as_matrix_tuple("A0", self.A0, (n, n)))
            object.__setattr__(self, "B0", _as_matrix_tuple("B0", self.B0, (n, m)))
        elif self.A0 is not None or self.B0 is not None:
            raise ValueError(
                f"A0/B0 are only used by formulation 'nominal', got formulation "
                f"{self.formulation!r}"
            )
        tau = as_array("tau", self.tau)
        if tau.ndim == 0:
            object.__setattr__(self, "tau", float(tau))
        elif tau.shape == (n,):
            object.__setattr__(self, "tau", tuple(float(v) for v in tau))
        else:
            raise ValueError(f"tau must be a scalar or have shape [{n}], got {list(tau.shape)}")
        if not isinstance(self.normalize, (bool, np.bool_)):
            raise ValueError(f"normalize must be a bool, got {self.normalize!r}")
        if isinstance(self.seed, bool) or not isinstance(self.seed, (int, np.integer)):
            raise ValueError(f"seed must be an int, got {self.seed!r}")
        object.__setattr__(self, "seed", int(self.seed))

    @property
    def n_members(self) -> int:
        return len(self.members)

    def skip_jacobian(self) -> np.ndarray:
        """``[n, n+m]`` Jacobian of the skip part ``s(x, u)`` (see the module docstring)."""
        n, m = self.state_dim, self.action_dim
        J = np.zeros((n, n + m))
        if self.formulation == "g":
            J[:, :n] = np.eye(n)
        elif self.formulation == "nominal":
            J[:, :n], J[:, n:] = np.asarray(self.A0), np.asarray(self.B0)
        elif self.formulation == "scaled":
            J[:, :n] = np.diag(np.broadcast_to(np.asarray(self.tau, dtype=float), (n,)))
        return J

    def to_json(self) -> str:
        return json.dumps(asdict(self))

    @classmethod
    def from_json(cls, text: str) -> EnsembleConfig:
        d = json.loads(text)
        d["members"] = tuple(MemberSpec(**s) for s in d["members"])
        if isinstance(d.get("tau"), list):
            d["tau"] = tuple(d["tau"])
        return cls(**d)


# --------------------------------------------------------------------------------------------
# The batched network math, written once for torch (float32, differentiable) and numpy (float64)
# --------------------------------------------------------------------------------------------

def _torch_affine(h: torch.Tensor, W: torch.Tensor, b: torch.Tensor) -> torch.Tensor:
    """``h @ W + b`` per member in one op: ``h: [B, i]`` (shared) or ``[K, B, i]``."""
    if h.dim() == 2:
        h = h.expand(W.shape[0], -1, -1)
    return torch.baddbmm(b, h, W)


_TORCH_OPS = SimpleNamespace(
    xp=torch,
    affine=_torch_affine,
    split=lambda z, sizes: z.split(sizes, 0),
    act=lambda name: ACTIVATIONS[name][0],
    sum_last=lambda a: a.sum(-1, keepdim=True),
    sum_m2=lambda a: a.sum(-2, keepdim=True),
    sqrt=torch.sqrt,
    cat=lambda parts, axis: torch.cat(parts, dim=axis),
    T=lambda a: a.transpose(-1, -2),
)
_NUMPY_OPS = SimpleNamespace(
    xp=np,
    affine=lambda h, W, b: h @ W + b,
    split=lambda z, sizes: np.split(z, np.cumsum(sizes)[:-1], 0),
    act=lambda name: ACTIVATIONS[name][1],
    sum_last=lambda a: a.sum(-1, keepdims=True),
    sum_m2=lambda a: a.sum(-2, keepdims=True),
    sqrt=np.sqrt,
    cat=lambda parts, axis: np.concatenate(parts, axis=axis),
    T=lambda a: a.swapaxes(-1, -2),
)


def _activate(z, runs, ops, jac_rows: int):
    """Per-member activations on contiguous member runs.

    ``z: [K, B, W]`` -> ``(act(z) [K, B, W], act'(z) [K, jac_rows, W] or None)``.
    """
    if len(runs) == 1:
        name = runs[0][0]
        a = ops.act(name)(z)
        if not jac_rows:
            return a, None
        return a, ACTIVATIONS[name][2](z[:, :jac_rows], a[:, :jac_rows], ops.xp)
    zs = ops.split(z, [j - i for _, i, j in runs])  # one op (and one backward) for all runs
    vals = [ops.act(name)(zr) for (name, _, _), zr in zip(runs, zs)]
    a = ops.cat(vals, 0)
    if not jac_rows:
        return a, None
    ders = [ACTIVATIONS[name][2](zr[:, :jac_rows], v[:, :jac_rows], ops.xp)
            for (name, _, _), zr, v in zip(runs, zs, vals)]
    return a, ops.cat(ders, 0)


# In-place float64 activations for the cached numpy inference path: they write ``act(z)`` into
# ``h`` and, if given, ``act'(z)`` into ``dh``; ``tmp`` is optional scratch of z's shape. Few
# temporaries: on small VMs page-faulting fresh large allocations costs more than the arithmetic.


def _np_elu_(z, h, dh=None, tmp=None):
    pos = z > 0
    if dh is None:
        np.minimum(z, 0.0, out=h)
        np.expm1(h, out=h)
    else:
        np.minimum(z, 0.0, out=dh)
        np.exp(dh, out=dh)
        np.subtract(dh, 1.0, out=h)
        np.copyto(dh, 1.0, where=pos)
    np.copyto(h, z, where=pos)


def _np_sigmoid_(z, h, dh=None, tmp=None):
    expit(z, out=h)
    if dh is not None:
        np.subtract(1.0, h, out=dh)
        dh *= h


def _np_tanh_(z, h, dh=None, tmp=None):
    np.tanh(z, out=h)
    if dh is not None:
        np.multiply(h, h, out=dh)
        np.subtract(1.0, dh, out=dh)


def _np_swish_(z, h, dh=None, tmp=None):
    if dh is None:
        expit(z, out=h)
        h *= z
        return
    expit(z, out=dh)  # s
    np.multiply(z, dh, out=h)  # z s
    tmp = np.multiply(h, dh, out=tmp)  # z s^2
    dh += h
    dh -= tmp  # s + z s - z s^2


def _np_relu_(z, h, dh=None, tmp=None):
    np.maximum(z, 0.0, out=h)
    if dh is not None:
        np.greater(z, 0.0, out=dh)


def _np_leaky_relu_(z, h, dh=None, tmp=None):
    np.multiply(z, LEAKY_RELU_SLOPE, out=h)
    np.maximum(z, h, out=h)
    if dh is not None:
        dh.fill(LEAKY_RELU_SLOPE)
        np.copyto(dh, 1.0, where=z > 0)


_NP_INPLACE = {
    "elu": _np_elu_,
    "sigmoid": _np_sigmoid_,
    "tanh": _np_tanh_,
    "swish": _np_swish_,
    "relu": _np_relu_,
    "leaky_relu": _np_leaky_relu_,
}


# Value-only activations of the ensemble-mean ``step`` fast path (:meth:`DynamicsEnsemble.step`):
# ``f(z, h)`` writes into ``h`` in place. Sigmoid, swish and tanh all go through numpy's vectorized
# tanh (scipy's ``expit`` is a scalar loop, ~5x slower on small batches), with the affine parts
# folded into the weights (see :func:`_fast_activation_plan`), so the three share ONE op:
#     sigmoid(z) = 0.5 tanh(z/2) + 0.5,     swish(z) = z sigmoid(z) = z' tanh(z') + z',  z' = z/2.


def _fast_elu(z, h):
    np.minimum(z, 0.0, out=h)
    np.expm1(h, out=h)
    np.maximum(h, z, out=h)  # expm1(z) >= z for z <= 0, and 0 < z for z > 0


def _fast_tanh(z, h):
    np.tanh(z, out=h)


def _fast_times(z, h):
    h *= z  # swish rows: z' tanh(z'), h already holds tanh(z')


def _fast_relu(z, h):
    np.maximum(z, 0.0, out=h)


def _fast_leaky_relu(z, h):
    np.multiply(z, LEAKY_RELU_SLOPE, out=h)
    np.maximum(z, h, out=h)


_FAST_VALUE = {
    "elu": _fast_elu,
    "relu": _fast_relu,
    "leaky_relu": _fast_leaky_relu,
    "sigmoid": _fast_tanh,
    "swish": _fast_tanh,
    "tanh": _fast_tanh,
}


def _fast_activation_plan(runs, W: int, H: int) -> tuple[list, np.ndarray, np.ndarray, np.ndarray]:
    """Ops of the hidden activations of member ``runs`` (``(name, first, stop)`` member ranges;
    member k owns hidden rows ``k*W .. (k+1)*W`` of ``H``).

    :return: ``(ops, half, sigmoid, swish)``: ``ops`` a list of ``(f, first_row, stop_row)``
        (consecutive tanh-family rows merged into one op), and ``[H]`` boolean row masks: ``half``
        rows whose pre-activation weights are halved (sigmoid, swish: exact), ``sigmoid`` and
        ``swish`` rows whose affine remainder the output weights must absorb.
    """
    ops: list[tuple[Callable, int, int]] = []
    swish_ops: list[tuple[Callable, int, int]] = []
    sigmoid, swish = np.zeros(H, bool), np.zeros(H, bool)
    for name, a, b in runs:
        f, first, stop = _FAST_VALUE[name], a * W, b * W
        if f is _fast_tanh and ops and ops[-1][0] is _fast_tanh and ops[-1][2] == first:
            ops[-1] = (f, ops[-1][1], stop)
        else:
            ops.append((f, first, stop))
        if name == "sigmoid":
            sigmoid[first:stop] = True
        elif name == "swish":
            swish[first:stop] = True
            swish_ops.append((_fast_times, first, stop))
    return ops + swish_ops, sigmoid | swish, sigmoid, swish


def _layer_norm(z, gain, bias, mask, width, ops):
    """Masked layer norm over the hidden axis.

    ``z: [K, B, W]``, ``gain, bias, mask: [K, 1, W]``, ``width: [K, 1, 1]`` (real units per
    member) -> ``(y, zhat, inv_std)`` with ``zhat: [K, B, W]`` and ``inv_std: [K, B, 1]``.
    """
    mu = ops.sum_last(z * mask) / width
    d = (z - mu) * mask
    inv_std = 1.0 / ops.sqrt(ops.sum_last(d * d) / width + LAYER_NORM_EPS)
    zhat = d * inv_std
    return zhat * gain + bias, zhat, inv_std


def _layer_norm_jacobian(Jz, zhat, inv_std, gain, mask, width, ops):
    """Chain rule through :func:`_layer_norm`: ``dy/dz = gain/s (I - 1 1^T/w - zhat zhat^T/w)``.

    ``Jz: [K, R or 1, W, in]`` (Jacobian of ``z``), ``zhat: [K, R, W]``, ``inv_std: [K, R, 1]``
    -> ``[K, R, W, in]``.
    """
    m = mask[..., None]
    zh = zhat[..., None]
    w = width[..., None]
    mean_J = ops.sum_m2(Jz * m) / w
    mean_zJ = ops.sum_m2(zh * Jz) / w
    return (gain * inv_std)[..., None] * (Jz - mean_J - zh * mean_zJ) * m


def _group_forward(p, g, xn, ops, jac_rows=0, dropout_masks=None):
    """Forward pass (and closed-form Jacobians) of one depth group of stacked members.

    :param p: dict of arrays/tensors: ``W1 [K, in, W]``, ``b1 [K, 1, W]``, (depth 2:
        ``W2 [K, W, W]``, ``b2 [K, 1, W]``), ``Wo [K, W, n]``, ``bo [K, 1, n]``; if padded or
        layer-normed ``mask [K, 1, W]`` and ``width [K, 1, 1]``; with layer norm
        ``ln_gain1, ln_bias1 (, ln_gain2, ln_bias2) [K, 1, W]`` and, if only some members use it,
        ``ln_select [K, 1, 1]``.
    :param g: static description: ``depth``, ``runs`` (activation, first, stop) over members,
        ``layer_norm`` (any member), ``padded``.
    :param xn: ``[B, in]`` normalized inputs, shared by all members.
    :param jac_rows: compute Jacobians for the first ``jac_rows`` points (0: none).
    :param dropout_masks: per hidden layer ``[K, B, W]`` inverted-dropout masks, or None.
    :return: ``y: [K, B, n]`` normalized outputs, ``J: [K, jac_rows, n, in]`` of ``y`` w.r.t.
        ``xn`` (or None).
    """
    mask = p.get("mask")
    W_hidden = [p["W1"], p["W2"]] if g.depth == 2 else [p["W1"]]
    b_hidden = [p["b1"], p["b2"]] if g.depth == 2 else [p["b1"]]
    Wo = p["Wo"]
    if g.padded:  # padded units have exactly zero weights in and out
        W_hidden = [W_hidden[0] * mask] + [W * ops.T(mask) * mask for W in W_hidden[1:]]
        Wo = Wo * ops.T(mask)
    fast_jacobian = g.depth == 1 and not g.layer_norm
    h, J = xn, None
    for layer, (W, b) in enumerate(zip(W_hidden, b_hidden)):
        z = ops.affine(h, W, b)
        if g.layer_norm:
            gain, bias = p[f"ln_gain{layer + 1}"], p[f"ln_bias{layer + 1}"]
            z_ln, zhat, inv_std = _layer_norm(z, gain, bias, mask, p["width"], ops)
            sel = p.get("ln_select")
            z = z_ln if sel is None else sel * z_ln + (1.0 - sel) * z
        h, d = _activate(z, g.runs, ops, jac_rows)
        if dropout_masks is not None:
            h = h * dropout_masks[layer]
        if not jac_rows:
            continue
        if dropout_masks is not None:
            d = d * dropout_masks[layer][:, :jac_rows]
        if fast_jacobian:
            # J[k, b] = Wo^T diag(d[k, b]) W1^T for all points in ONE batched product:
            # M[k, w, (o, i)] = Wo[k, w, o] * W1[k, i, w],  J[k, b, (o, i)] = d[k, b, :] @ M[k]
            K, width, n_out = Wo.shape
            M = (Wo[:, :, :, None] * ops.T(W)[:, :, None, :]).reshape(K, width, -1)
            J = (d @ M).reshape(K, jac_rows, n_out, -1)
            continue
        Jz = ops.T(W)[:, None] if J is None else ops.T(W)[:, None] @ J  # [K, R|1, W, in]
        if g.layer_norm:
            Jz_ln = _layer_norm_jacobian(
                Jz, zhat[:, :jac_rows], inv_std[:, :jac_rows], gain, mask, p["width"], ops
            )
            sel = p.get("ln_select")
            Jz = Jz_ln if sel is None else sel[..., None] * Jz_ln + (1.0 - sel[..., None]) * Jz
        J = d[..., None] * Jz
    y = ops.affine(h, Wo, p["bo"])
    if jac_rows and not fast_jacobian:
        J = ops.T(Wo)[:, None] @ J
    return y, J


def _glorot(fan_in: int, fan_out: int, gen: torch.Generator) -> torch.Tensor:
    lim = float(np.sqrt(6.0 / (fan_in + fan_out)))
    return (torch.rand(fan_in, fan_out, generator=gen, dtype=torch.float64) * 2 - 1) * lim


class _StackedGroup(nn.Module):
    """Members of one depth, weights stacked along a leading member axis ``K``."""

    def __init__(
        self, specs: Sequence[MemberSpec], weights: Sequence[dict], in_dim: int, out_dim: int
    ) -> None:
        super().__init__()
        K = len(specs)
        depth = specs[0].depth
        W = max(s.width for s in specs)
        widths = [s.width for s in specs]
        self.depth = depth
        self.padded = any(w != W for w in widths)
        self.layer_norm = any(s.layer_norm for s in specs)
        self.runs: list[tuple[str, int, int]] = []
        for k, s in enumerate(specs):
            if self.runs and self.runs[-1][0] == s.activation:
                self.runs[-1] = (s.activation, self.runs[-1][1], k + 1)
            else:
                self.runs.append((s.activation, k, k + 1))
        self.dropout_p = [s.dropout for s in specs]
        self._arrays: dict[str, torch.Tensor] | None = None

        def stacked(name: str, shape: tuple[int, int]) -> torch.Tensor:
            out = torch.zeros(K, *shape, dtype=torch.float64)
            for k, wd in enumerate(weights):
                a = wd[name]
                out[k, : a.shape[0], : a.shape[1]] = a
            return out.float()

        self.W1 = nn.Parameter(stacked("W1", (in_dim, W)))
        self.b1 = nn.Parameter(stacked("b1", (1, W)))
        if depth == 2:
            self.W2 = nn.Parameter(stacked("W2", (W, W)))
            self.b2 = nn.Parameter(stacked("b2", (1, W)))
        self.Wo = nn.Parameter(stacked("Wo", (W, out_dim)))
        self.bo = nn.Parameter(stacked("bo", (1, out_dim)))
        if self.layer_norm:
            for layer in range(1, depth + 1):
                self.register_parameter(f"ln_gain{layer}", nn.Parameter(torch.ones(K, 1, W)))
                self.register_parameter(f"ln_bias{layer}", nn.Parameter(torch.zeros(K, 1, W)))
            if not all(s.layer_norm for s in specs):
                sel = torch.tensor([float(s.layer_norm) for s in specs]).reshape(K, 1, 1)
                self.register_buffer("ln_select", sel)
        if self.padded or self.layer_norm:
            mask = torch.zeros(K, 1, W)
            for k, w in enumerate(widths):
                mask[k, 0, :w] = 1.0
            self.register_buffer("mask", mask)
            width = torch.tensor(widths, dtype=torch.float32).reshape(K, 1, 1)
            self.register_buffer("width", width)
        if any(self.dropout_p):
            self.register_buffer("dropout", torch.tensor(self.dropout_p).reshape(K, 1, 1))

    def arrays(self) -> dict[str, torch.Tensor]:
        """Parameters and buffers by name (cached; :meth:`DynamicsEnsemble.invalidate_cache`)."""
        if self._arrays is None:
            self._arrays = {**dict(self.named_parameters()), **dict(self.named_buffers())}
        return self._arrays

    def dropout_masks(self, B: int, gen: torch.Generator | None) -> list[torch.Tensor]:
        K, W = self.W1.shape[0], self.W1.shape[2]
        keep = 1.0 - self.dropout
        return [
            (torch.rand(K, B, W, generator=gen) < keep).float() / keep for _ in range(self.depth)
        ]


def _member_init(spec: MemberSpec, in_dim: int, out_dim: int, gen: torch.Generator) -> dict:
    """Flux-style init: glorot-uniform weights ``[fan_in, fan_out]``, zero biases."""
    w = spec.width
    d = {"W1": _glorot(in_dim, w, gen), "b1": torch.zeros(1, w, dtype=torch.float64)}
    if spec.depth == 2:
        d["W2"], d["b2"] = _glorot(w, w, gen), torch.zeros(1, w, dtype=torch.float64)
    d["Wo"], d["bo"] = _glorot(w, out_dim, gen), torch.zeros(1, out_dim, dtype=torch.float64)
    return d


class DynamicsEnsemble(nn.Module):
    """An ensemble of K neural dynamics models ``x+ = s(x, u) + NN_k(x, u)`` computed in one batch.

    Torch surface (float32, for training): :meth:`forward_torch`, :meth:`member_jacobians_torch`.
    Numpy float64 surface (the :class:`mbtsr.dynamics.DynamicsModel` protocol; weights are cached
    as float64 and the cache is refreshed automatically when a parameter changes in place):
    :meth:`step`, :meth:`predict`, :meth:`jacobians`, :meth:`member_jacobians`,
    :meth:`member_predictions`. Members are reported in the order of ``config.members``.

    :param config: the architecture, see :class:`EnsembleConfig`.
    """

    def __init__(self, config: EnsembleConfig) -> None:
        super().__init__()
        if not isinstance(config, EnsembleConfig):
            raise ValueError(f"config must be an EnsembleConfig, got {type(config).__name__}")
        self.config = config
        n, m = config.state_dim, config.action_dim
        self.state_dim, self.action_dim = n, m
        gen = torch.Generator().manual_seed(config.seed)
        inits = [_member_init(s, n + m, n, gen) for s in config.members]
        # stacked order: grouped by depth, activations contiguous inside a group
        order = sorted(
            range(config.n_members),
            key=lambda k: (config.members[k].depth, config.members[k].activation),
        )
        self.groups = nn.ModuleList()
        for depth in sorted({config.members[k].depth for k in order}):
            ks = [k for k in order if config.members[k].depth == depth]
            self.groups.append(
                _StackedGroup([config.members[k] for k in ks], [inits[k] for k in ks], n + m, n)
            )
        self._stacked_order = order
        position = np.argsort(order)  # position[k] = stacked index of config member k
        self._to_config_order = (
            None
            if list(order) == list(range(len(order)))
            else torch.as_tensor(position, dtype=torch.long)
        )
        self.register_buffer("in_mean", torch.zeros(n + m))
        self.register_buffer("in_std", torch.ones(n + m))
        self.register_buffer("out_mean", torch.zeros(n))
        self.register_buffer("out_std", torch.ones(n))
        self.register_buffer("skip_J", torch.as_tensor(config.skip_jacobian(), dtype=torch.float32))
        self.register_buffer("normalization_set", torch.zeros((), dtype=torch.uint8))
        self.dropout_generator: torch.Generator | None = None
        self._skip_J = config.skip_jacobian()
        self._np_cache: tuple | None = None
        self._watched: list | None = None
        self._workspace: dict[str, np.ndarray] = {}
        self._step_buffers: dict[int, tuple[np.ndarray, np.ndarray]] = {}
        self.eval()

    # ---------------------------------------------------------------- basic properties
    @property
    def n_members(self) -> int:
        return self.config.n_members

    @property
    def is_normalized(self) -> bool:
        """True once :meth:`set_normalization` has been called (or loaded from a file)."""
        return bool(self.normalization_set.item())

    def skip_torch(self, xu: torch.Tensor) -> torch.Tensor:
        """``s(x, u)`` for ``xu: [..., n+m]`` -> ``[..., n]``."""
        return xu @ self.skip_J.T

    # ---------------------------------------------------------------- normalization
    def set_normalization(self, trajs: Trajectory | Sequence[Trajectory]) -> None:
        """Set input/output statistics from data (see the module docstring).

        Inputs: per-dimension mean and (population) std of ``[x_t, u_t]``; outputs: the same for
        the residual targets ``x_{t+1} - s(x_t, u_t)``; all transitions pooled. A std below
        ``STD_FLOOR`` is replaced by 1. With ``config.normalize=False`` the statistics stay
        identity and the model is only marked as set.

        :param trajs: a :class:`~mbtsr.trajectory.Trajectory` or a list of them.
        """
        xu, x_next = _pool_transitions(trajs, self.state_dim, self.action_dim)
        if self.config.normalize:
            resid = x_next - xu @ self.config.skip_jacobian().T
            for name, data in (("in", xu), ("out", resid)):
                mean, std = data.mean(0), data.std(0)
                std = np.where(std < STD_FLOOR, 1.0, std)
                getattr(self, f"{name}_mean").copy_(torch.as_tensor(mean))
                getattr(self, f"{name}_std").copy_(torch.as_tensor(std))
        self.normalization_set.fill_(1)
        self.invalidate_cache()

    def refit_normalization(self, trajs: Trajectory | Sequence[Trajectory]) -> None:
        """Recompute the statistics from ``trajs`` (as :meth:`set_normalization`) WITHOUT
        changing the function the ensemble represents: the first layer and the output layer
        of every member absorb the change (``W1' = diag(s'/s) W1``,
        ``b1' = b1 + ((m' - m) / s) W1``, ``Wo' = Wo o_s / o_s'``,
        ``bo' = (bo o_s + o_m - o_m') / o_s'``), computed in float64. Predictions agree to
        float32 rounding; the training that follows then works in the scales of all data so
        far instead of those of the first episode. Adam's moment estimates are not rescaled.
        Unset statistics are simply set.

        :param trajs: a :class:`~mbtsr.trajectory.Trajectory` or a list of them.
        """
        if not self.is_normalized or not self.config.normalize:
            self.set_normalization(trajs)
            return
        names = ("in_mean", "in_std", "out_mean", "out_std")
        old = {k: getattr(self, k).detach().double().clone() for k in names}
        self.set_normalization(trajs)
        new = {k: getattr(self, k).detach().double() for k in names}
        with torch.no_grad():
            for g in self.groups:
                W1 = g.W1.detach().double()  # [K, in, W]
                shift = ((new["in_mean"] - old["in_mean"]) / old["in_std"])  # [in]
                g.b1.copy_(g.b1.double() + torch.einsum("i,kiw->kw", shift, W1)[:, None])
                g.W1.copy_(W1 * (new["in_std"] / old["in_std"])[None, :, None])
                g.Wo.copy_(g.Wo.double() * (old["out_std"] / new["out_std"])[None, None, :])
                g.bo.copy_((g.bo.double() * old["out_std"] + old["out_mean"] - new["out_mean"])
                           / new["out_std"])
                g._arrays = None
        self.invalidate_cache()

    # ---------------------------------------------------------------- torch surface
    def _xu_torch(self, x, u) -> torch.Tensor:
        n, m = self.state_dim, self.action_dim
        x = torch.as_tensor(x, dtype=torch.float32)
        if u is None:
            if x.ndim < 1 or x.shape[-1] != n + m:
                raise ValueError(f"xu must have last dimension n+m={n + m}, got {list(x.shape)}")
            return x
        u = torch.as_tensor(u, dtype=torch.float32)
        if x.ndim < 1 or x.shape[-1] != n:
            raise ValueError(f"x must have last dimension n={n}, got shape {list(x.shape)}")
        if u.ndim < 1 or u.shape[-1] != m:
            raise ValueError(f"u must have last dimension m={m}, got shape {list(u.shape)}")
        if x.shape[:-1] != u.shape[:-1]:
            raise ValueError(
                f"x and u must share batch dimensions, got {list(x.shape)} and {list(u.shape)}"
            )
        return torch.cat([x, u], -1)

    def stacked_forward(self, xu: torch.Tensor, jac_rows: int = 0, *, normalized: bool = False):
        """Internal training entry point, members in *stacked* order (see ``stacked_order``).

        :param xu: ``[B, n+m]`` raw inputs (float32), or normalized ones if ``normalized``
            (see :meth:`normalize_inputs`).
        :param jac_rows: also return full-map Jacobians (raw units, skip included) of the first
            ``jac_rows`` points.
        :return: ``(y_norm [K, B, n], J [K, jac_rows, n, n+m] or None)`` where ``y_norm`` is the
            normalized network output, comparable to :meth:`normalized_residual` targets.
        """
        xn = xu if normalized else self.normalize_inputs(xu)
        ys, Js = [], []
        for g in self.groups:
            masks = None
            if self.training and any(g.dropout_p):
                masks = g.dropout_masks(xu.shape[0], self.dropout_generator)
            y, J = _group_forward(g.arrays(), g, xn, _TORCH_OPS, jac_rows, masks)
            ys.append(y)
            Js.append(J)
        y = ys[0] if len(ys) == 1 else torch.cat(ys, 0)
        if not jac_rows:
            return y, None
        J = Js[0] if len(Js) == 1 else torch.cat(Js, 0)
        J = self.out_std[:, None] * J / self.in_std + self.skip_J
        return y, J

    @property
    def stacked_order(self) -> list[int]:
        """``stacked_order[i]`` is the config index of the i-th member in stacked order."""
        return list(self._stacked_order)

    def normalize_inputs(self, xu: torch.Tensor) -> torch.Tensor:
        """``([x, u] - in_mean) / in_std`` for ``xu: [..., n+m]``."""
        return (xu - self.in_mean) / self.in_std

    def normalized_residual(self, xu: torch.Tensor, x_next: torch.Tensor) -> torch.Tensor:
        """Training target of the network: ``(x+ - s(x, u) - out_mean) / out_std``, ``[B, n]``."""
        return (x_next - self.skip_torch(xu) - self.out_mean) / self.out_std

    def _config_order(self, a: torch.Tensor) -> torch.Tensor:
        return a if self._to_config_order is None else a.index_select(0, self._to_config_order)

    def forward_torch(self, x: torch.Tensor, u: torch.Tensor | None = None) -> torch.Tensor:
        """Member predictions of the next state (float32, differentiable).

        :param x: ``[..., n]`` states, or ``[..., n+m]`` concatenated ``[x, u]`` if ``u`` is None.
        :param u: ``[..., m]`` inputs.
        :return: ``[K, ..., n]`` next states, members in config order.
        """
        xu = self._xu_torch(x, u)
        lead = xu.shape[:-1]
        xu2 = xu.reshape(-1, xu.shape[-1])
        y, _ = self.stacked_forward(xu2)
        nxt = self.skip_torch(xu2) + self.out_mean + self.out_std * y
        return self._config_order(nxt).reshape(self.n_members, *lead, self.state_dim)

    def forward(self, x: torch.Tensor, u: torch.Tensor | None = None) -> torch.Tensor:
        return self.forward_torch(x, u)

    def member_jacobians_torch(self, x: torch.Tensor, u: torch.Tensor) -> torch.Tensor:
        """Differentiable full-map Jacobians ``[K, B, n, n+m]`` at ``x: [B, n]``, ``u: [B, m]``."""
        xu = self._xu_torch(x, u)
        if xu.ndim != 2:
            raise ValueError(f"x and u must be 2-D [B, .], got xu shape {list(xu.shape)}")
        _, J = self.stacked_forward(xu, jac_rows=xu.shape[0])
        return self._config_order(J)

    def member_parameters(self, k: int, *, grad: bool = False) -> dict[str, torch.Tensor]:
        """Views of member ``k``'s (config index) unpadded parameters, or of their gradients.

        Weights are ``[fan_in, fan_out]`` (``y = x @ W + b``): ``W1, b1, (W2, b2), Wo, bo`` and
        ``ln_gain*/ln_bias*`` with layer norm.
        """
        if not 0 <= k < self.n_members:
            raise ValueError(f"k must be in [0, {self.n_members}), got {k}")
        spec = self.config.members[k]
        pos = self._stacked_order.index(k)
        for g in self.groups:
            K = g.W1.shape[0]
            if pos < K and g.depth == spec.depth:
                break
            pos -= K
        w = spec.width
        out = {}
        for name, p in g.named_parameters():
            if name.startswith("ln_") and not spec.layer_norm:
                continue  # the group has layer-norm parameters, this member does not use them
            t = p.grad if grad else p.data
            if t is None:
                out[name] = None
                continue
            t = t[pos]
            if name == "W2":
                t = t[:w, :w]
            elif name == "Wo":
                t = t[:w]
            elif name != "bo":  # W1 [in, W], b1/b2/ln_* [1, W]
                t = t[:, :w]
            out[name] = t
        return out

    # ---------------------------------------------------------------- numpy float64 surface
    def invalidate_cache(self) -> None:
        """Drop the float64 weight cache (done automatically when parameters change in place)."""
        self._np_cache = None
        self._watched = None
        for g in self.groups:
            g._arrays = None

    def _apply(self, fn, recurse=True):  # .to(), .float(), ... may replace buffers
        out = super()._apply(fn, recurse)
        self.invalidate_cache()
        return out

    def _work(self, name: str, shape: tuple[int, ...]) -> np.ndarray:
        """Reusable float64 scratch buffer (the numpy path is not thread-safe, like torch)."""
        buf = self._workspace.get(name)
        if buf is None or buf.shape != shape:
            buf = self._workspace[name] = np.empty(shape)
        return buf

    def _watched_tensors(self) -> list[torch.Tensor]:
        """Parameters and buffers whose in-place version counters key the numpy cache."""
        if getattr(self, "_watched", None) is None:
            self._watched = [t for g in self.groups for t in g.arrays().values()]
            self._watched += [self.in_mean, self.in_std, self.out_mean, self.out_std]
        return self._watched

    def _numpy_state(self) -> list:
        """float64 copies of the weights with the normalization folded in (cached).

        Depth-1 groups without layer norm get a "wide" layout in which all members of the group
        are evaluated by single matrix products over the concatenated hidden units ``[B, K*W]``:
        ``z = xu @ W1_wide + b1_wide`` (input normalization folded into ``W1_wide``), the
        ensemble mean as ``h @ Wo_vertical`` and the mean Jacobian as ``act'(z) @ M`` with
        ``M[(k, w), (o, i)] = out_std[o] Wo[k, w, o] W1[k, i, w] / in_std[i] / K``.
        """
        return self._numpy_cached()[0]

    def _numpy_cached(self) -> tuple[list, SimpleNamespace | None]:
        """``(states, mean_plan)``: the cached float64 weights of :meth:`_numpy_state` and the
        plan of the ensemble-mean fast path of :meth:`step` (None when not applicable).

        The cache key is the number of torch optimizer steps taken so far (a global step hook:
        fused optimizers do not bump version counters) and the in-place version counters
        (``Tensor._version``) of every parameter and normalization buffer, so optimizer steps,
        ``copy_``, ``load_state_dict`` etc. invalidate it without any explicit call (~1 us per
        check). Only writes that bypass autograd's version counting (``.data`` assignment,
        writes through ``.numpy()`` views) need :meth:`invalidate_cache`."""
        key = (_OPTIMIZER_STEPS[0], *map(_VERSION, self._watched_tensors()))
        cache = self._np_cache
        if cache is not None and cache[0] == key:
            return cache[1], cache[2]
        in_mean, in_std, out_mean, out_std = (
            getattr(self, k).detach().double().numpy().copy()
            for k in ("in_mean", "in_std", "out_mean", "out_std")
        )
        K_total, n = self.n_members, self.state_dim
        states = []
        for g in self.groups:
            p = {k: v.detach().double().numpy().copy() for k, v in g.arrays().items()}
            st = SimpleNamespace(group=g, p=p, K=p["W1"].shape[0], wide=False)
            st.in_mean, st.in_std, st.out_mean, st.out_std = in_mean, in_std, out_mean, out_std
            if g.depth == 1 and not g.layer_norm:
                K, n_in, W = p["W1"].shape
                W1, Wo = p["W1"], p["Wo"]
                if g.padded:
                    W1, Wo = W1 * p["mask"], Wo * p["mask"].swapaxes(-1, -2)
                W1f = W1 / in_std[None, :, None]  # [K, in, W], normalization folded in
                # transposed layout: hidden units of all members along the rows, points along
                # the columns, so each activation run is a contiguous block of rows
                st.W1T_wide = np.ascontiguousarray(W1f.transpose(0, 2, 1).reshape(K * W, n_in))
                b1 = p["b1"][:, 0] - (in_mean / in_std) @ W1  # [K, W]
                st.b1T_wide = b1.reshape(K * W, 1)
                Wo_f = Wo * out_std  # [K, W, n]
                st.WoT_f = np.ascontiguousarray(Wo_f.transpose(0, 2, 1))  # [K, n, W]
                st.bo_f = p["bo"][:, 0] * out_std + out_mean  # [K, n]
                st.WoT_mean = np.ascontiguousarray(Wo_f.reshape(K * W, n).T) / K_total
                st.bo_mean = st.bo_f.sum(0) / K_total
                M = Wo_f[:, :, :, None] * W1f.swapaxes(1, 2)[:, :, None, :]  # [K, W, n, in]
                st.MT = np.ascontiguousarray(M.reshape(K, W, -1).transpose(0, 2, 1))
                st.M_wide = M.reshape(K * W, -1) / K_total
                st.runs = [(_NP_INPLACE[name], a * W, b * W) for name, a, b in g.runs]
                st.W, st.wide = W, True
            states.append(st)
        mean_plan = None
        if len(states) == 1 and states[0].wide:
            mean_plan = self._mean_step_plan(states[0])
        self._np_cache = (key, states, mean_plan)
        return states, mean_plan

    def _mean_step_plan(self, st: SimpleNamespace) -> SimpleNamespace:
        """Folded weights of the ensemble-mean :meth:`step` for a single wide group of H hidden
        units (``H = K*W``).

        One buffer ``G = [h; 1; x^T; u^T]: [H+1+n+m, B]`` holds everything:
        ``z = W_in @ G[H:]`` with ``W_in = [b1T_wide, W1T_wide]: [H, 1+n+m]``, ``h = act(z)`` in
        place, and ``x+ = G^T @ W_out`` with ``W_out = [WoT_mean^T; bo_mean; skip_J^T]:
        [H+1+n+m, n]``: the biases and the skip part ride along in the two matrix products.
        Sigmoid and swish rows run as tanh of ``z' = z/2`` (rows of ``W_in`` halved); the
        affine remainders ``0.5 t + 0.5`` (sigmoid) and ``+ z'`` (swish) are linear in ``G``
        and folded into ``W_out`` (rows of the hidden units and of ``[1, x, u]``).
        """
        H = st.W1T_wide.shape[0]
        ops, half, sigmoid, swish = _fast_activation_plan(st.group.runs, st.W, H)
        W_in = np.concatenate([st.b1T_wide, st.W1T_wide], 1)  # [H, 1+n+m]
        W_in[half] *= 0.5
        Wo = st.WoT_mean.T  # [H, n]
        W_out = np.concatenate([Wo, st.bo_mean[None], self._skip_J.T], 0)
        W_out[:H][sigmoid] *= 0.5  # Wo (0.5 t + 0.5) = (0.5 Wo) t + 0.5 Wo
        W_out[H] += 0.5 * Wo[sigmoid].sum(0)
        W_out[H:] += W_in[swish].T @ Wo[swish]  # Wo (z' t + z') = Wo z' t + (Wo W_in') G_in
        return SimpleNamespace(
            W_in=np.ascontiguousarray(W_in), W_out=np.ascontiguousarray(W_out), ops=ops, H=H,
            n=self.state_dim, m=self.action_dim,
        )

    def _numpy_eval(self, xu: np.ndarray, *, members: bool, jacobians: bool):
        """float64 evaluation at ``xu: [B, n+m]``.

        :return: ``(x_next, J)`` with ``x_next [K, B, n]`` and ``J [K, B, n, n+m]`` per member
            (config order) if ``members``, else ensemble means ``[B, n]``, ``[B, n, n+m]``;
            ``J`` is None unless ``jacobians``. Skip parts are included.
        """
        states = self._numpy_state()
        B, n, n_in = xu.shape[0], self.state_dim, xu.shape[1]
        skip_J = self._skip_J
        K_total = self.n_members
        ys, Js = [], []
        y_sum = J_sum = 0.0  # ensemble-mean contributions of the groups
        for st in states:
            if st.wide:
                shape = (st.W1T_wide.shape[0], B)
                zT = np.matmul(st.W1T_wide, xu.T, out=self._work("z", shape))  # [K*W, B]
                zT += st.b1T_wide
                hT = self._work("h", shape)
                dhT = self._work("dh", shape) if jacobians else None
                tmp = self._work("tmp", shape)
                for act, a, b in st.runs:
                    act(zT[a:b], hT[a:b], None if dhT is None else dhT[a:b], tmp[a:b])
                if members:
                    hk = hT.reshape(st.K, st.W, B)
                    ys.append((st.WoT_f @ hk).transpose(0, 2, 1) + st.bo_f[:, None, :])
                    if jacobians:
                        dk = dhT.reshape(st.K, st.W, B)
                        Js.append((st.MT @ dk).transpose(0, 2, 1).reshape(st.K, B, n, n_in))
                else:
                    y_sum = y_sum + (st.WoT_mean @ hT).T + st.bo_mean
                    if jacobians:
                        J_sum = J_sum + dhT.T @ st.M_wide
                continue
            xn = (xu - st.in_mean) / st.in_std
            y, J = _group_forward(st.p, st.group, xn, _NUMPY_OPS, B if jacobians else 0)
            y = st.out_mean + st.out_std * y
            if jacobians:
                J = st.out_std[:, None] * J / st.in_std
            if members:
                ys.append(y)
                Js.append(J)
            else:
                y_sum = y_sum + y.sum(0) / K_total
                if jacobians:
                    J_sum = J_sum + J.sum(0).reshape(B, -1) / K_total
        skip = xu @ skip_J.T
        if not members:
            x_next = skip + y_sum
            J = None if not jacobians else J_sum.reshape(B, n, n_in) + skip_J
            return x_next, J
        y = ys[0] if len(ys) == 1 else np.concatenate(ys, 0)
        x_next = y + skip
        J = None
        if jacobians:
            J = (Js[0] if len(Js) == 1 else np.concatenate(Js, 0)) + skip_J
        if self._to_config_order is not None:
            perm = self._to_config_order.numpy()
            x_next = x_next[perm]
            J = None if J is None else J[perm]
        return x_next, J

    def _stacked_inputs(self, x: object, u: object) -> tuple[np.ndarray, tuple[int, ...]]:
        """Validated ``[x, u]`` as ``[B, n+m]`` float64 and the leading (batch) shape.

        One finiteness check on the concatenation (the hot path of iLQR rollouts); on failure the
        full per-argument check names the culprit."""
        n, m = self.state_dim, self.action_dim
        xa = np.asarray(x, dtype=np.float64) if not isinstance(x, np.ndarray) else x
        ua = np.asarray(u, dtype=np.float64) if not isinstance(u, np.ndarray) else u
        if (xa.ndim < 1 or ua.ndim < 1 or xa.shape[-1] != n or ua.shape[-1] != m
                or xa.shape[:-1] != ua.shape[:-1] or xa.dtype.kind not in "fiub"
                or ua.dtype.kind not in "fiub"):
            check_step_inputs(x, u, n, m)  # raises the precise message
            raise ValueError(f"x and u must be numeric arrays [..., {n}] and [..., {m}]")
        xu = np.concatenate([xa, ua], -1, dtype=np.float64).reshape(-1, n + m)
        if not np.isfinite(xu).all():
            check_step_inputs(x, u, n, m)  # names x or u and the first bad index
        return xu, xa.shape[:-1]

    def member_predictions(self, x: np.ndarray, u: np.ndarray) -> np.ndarray:
        """Next state of every member: ``x: [..., n]``, ``u: [..., m]`` -> ``[K, ..., n]``."""
        xu, lead = self._stacked_inputs(x, u)
        nxt, _ = self._numpy_eval(xu, members=True, jacobians=False)
        return nxt.reshape(self.n_members, *lead, self.state_dim)

    def step(self, x: np.ndarray, u: np.ndarray, t: int | None = None) -> np.ndarray:
        """Ensemble-mean next state: ``x: [..., n]``, ``u: [..., m]`` -> ``[..., n]`` (float64).

        ``t`` is ignored (the model is time-invariant). The hot path of iLQR rollouts: for an
        ensemble of one depth-1 group without layer norm (the paper's) it runs two matrix
        products with folded biases and in-place activations on reused buffers (see
        :meth:`_mean_step_plan`); it agrees with :meth:`member_predictions` averaged to ~1e-15.
        """
        cache = self._np_cache  # inline cache check: this is the hot path of iLQR rollouts
        if cache is None or cache[0] != (_OPTIMIZER_STEPS[0], *map(_VERSION, self._watched)):
            cache = (None, *self._numpy_cached())
        plan = cache[2]
        if plan is None:
            xu, lead = self._stacked_inputs(x, u)
            nxt, _ = self._numpy_eval(xu, members=False, jacobians=False)
            return nxt.reshape(*lead, self.state_dim)
        n, m, H = plan.n, plan.m, plan.H
        xa = x if isinstance(x, np.ndarray) else np.asarray(x, dtype=np.float64)
        ua = u if isinstance(u, np.ndarray) else np.asarray(u, dtype=np.float64)
        lead = xa.shape[:-1]
        if (xa.shape[-1:] != (n,) or ua.shape[-1:] != (m,) or lead != ua.shape[:-1]
                or xa.dtype.kind not in "fiub" or ua.dtype.kind not in "fiub"):
            check_step_inputs(x, u, n, m)  # raises the precise message
            raise ValueError(f"x and u must be numeric arrays [..., {n}] and [..., {m}]")
        B = xa.size // n
        bufs = self._step_buffers.get(B) or self._mean_step_buffers(B, plan)
        G, z = bufs
        G[H + 1:H + 1 + n] = xa.reshape(B, n).T
        G[H + 1 + n:] = ua.reshape(B, m).T
        G_in = G[H:]  # [1+n+m, B]: ones, x^T, u^T
        if not math.isfinite(G_in.sum()):  # any NaN/inf (or an overflowing sum: checked anew)
            check_step_inputs(x, u, n, m)  # names x or u and the first bad index
        np.dot(plan.W_in, G_in, out=z)  # [H, B]
        for act, a, b in plan.ops:
            act(z[a:b], G[a:b])
        return np.dot(G.T, plan.W_out).reshape(*lead, n)  # a fresh array (callers keep it)

    def _mean_step_buffers(self, B: int, plan: SimpleNamespace) -> tuple[np.ndarray, np.ndarray]:
        """The reused buffers of :meth:`step` for batch size ``B``: ``G [H+1+n+m, B]`` with the
        constant ones row written once, and the pre-activations ``z [H, B]``. A few batch sizes
        are kept (iLQR alternates 1 and the line-search batch)."""
        if len(self._step_buffers) >= 8:
            self._step_buffers.clear()
        G = np.empty((plan.H + 1 + plan.n + plan.m, B))
        G[plan.H] = 1.0
        bufs = self._step_buffers[B] = (G, np.empty((plan.H, B)))
        return bufs

    def predict(self, x: np.ndarray, u: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
        """Ensemble mean and spread (population std over members, ``ddof=0``) of the next state.

        :return: ``(mean [..., n], std [..., n])``; the std is 0 for a single member.
        """
        preds = self.member_predictions(x, u)
        return preds.mean(0), preds.std(0)

    def member_jacobians(self, x: np.ndarray, u: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
        """Full-map Jacobians of every member (skip part included), one batched call.

        :param x: ``[T, n]`` states.  :param u: ``[T, m]`` inputs.
        :return: ``(A [K, T, n, n], B [K, T, n, m])``.
        """
        n, m = self.state_dim, self.action_dim
        x = as_array("x", x, (None, n))
        u = as_array("u", u, (x.shape[0], m))
        _, J = self._numpy_eval(np.concatenate([x, u], -1), members=True, jacobians=True)
        return J[..., :n], J[..., n:]

    def jacobians(self, x: np.ndarray, u: np.ndarray, t: int = 0) -> tuple[np.ndarray, np.ndarray]:
        """Ensemble-mean Jacobians of the full map: ``x: [T, n]``, ``u: [T, m]`` ->
        ``(A [T, n, n], B [T, n, m])`` (paper Eq. (jacerr) averages exactly these)."""
        n, m = self.state_dim, self.action_dim
        x = as_array("x", x, (None, n))
        u = as_array("u", u, (x.shape[0], m))
        _, J = self._numpy_eval(np.concatenate([x, u], -1), members=False, jacobians=True)
        return J[..., :n], J[..., n:]


def _pool_transitions(trajs, n: int, m: int) -> tuple[np.ndarray, np.ndarray]:
    """All transitions of ``trajs`` as ``xu [N, n+m]`` and ``x_next [N, n]`` (float64)."""
    if isinstance(trajs, Trajectory):
        trajs = [trajs]
    trajs = list(trajs)
    if not trajs:
        raise ValueError("trajs must hold at least one Trajectory")
    for i, tr in enumerate(trajs):
        if not isinstance(tr, Trajectory):
            raise ValueError(f"trajs[{i}] must be a Trajectory, got {type(tr).__name__}")
        if tr.n != n or tr.m != m:
            raise ValueError(f"trajs[{i}] has (n, m) = ({tr.n}, {tr.m}), the model ({n}, {m})")
        as_array(f"trajs[{i}].x", tr.x)
        as_array(f"trajs[{i}].u", tr.u)
    xu = np.concatenate([np.concatenate([tr.x[:-1], tr.u], 1) for tr in trajs])
    x_next = np.concatenate([tr.x[1:] for tr in trajs])
    return xu, x_next


# --------------------------------------------------------------------------------------------
# Save / load without pickle
# --------------------------------------------------------------------------------------------

_FORMAT = "mbtsr.DynamicsEnsemble"
_FORMAT_VERSION = 2  # 2: checksummed file (mbtsr.fileformat)


def save_model(model: DynamicsEnsemble, path: str | os.PathLike) -> None:
    """Save weights, normalization statistics and config (as JSON text) with ``torch.save``.

    Written atomically with a format version and a content checksum
    (:func:`mbtsr.fileformat.torch_save_verified`). Load with :func:`load_model`, which checks
    both and uses ``torch.load(weights_only=True)``: no arbitrary objects are unpickled.
    """
    if not isinstance(model, DynamicsEnsemble):
        raise ValueError(f"model must be a DynamicsEnsemble, got {type(model).__name__}")
    payload = {
        "format": _FORMAT,
        "version": _FORMAT_VERSION,
        "config": model.config.to_json(),
        "state_dict": {k: v.detach().clone() for k, v in model.state_dict().items()},
    }
    torch_save_verified(payload, path, kind=_FORMAT, version=_FORMAT_VERSION)


def load_model(path: str | os.PathLike) -> DynamicsEnsemble:
    """Load a model written by :func:`save_model` (checksum verified, ``weights_only=True``;
    returns eval mode).

    :raises CheckpointError: truncated, corrupted, another format, or weights that do not fit
        the saved config.
    """
    payload, _ = torch_load_verified(path, kind=_FORMAT, versions=(_FORMAT_VERSION,),
                                     what=f"a saved {_FORMAT}")
    if not isinstance(payload, dict) or payload.get("format") != _FORMAT:
        raise CheckpointError(f"{path} is not a saved {_FORMAT}")
    try:
        model = DynamicsEnsemble(EnsembleConfig.from_json(payload["config"]))
        model.load_state_dict(payload["state_dict"])
    except (KeyError, TypeError, ValueError, RuntimeError) as err:
        raise CheckpointError(
            f"{path}: the saved weights do not fit the saved config ({type(err).__name__}: "
            f"{str(err).splitlines()[0]})") from None
    model.invalidate_cache()
    return model.eval()
