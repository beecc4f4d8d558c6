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
for Jacobian penalties by double backprop) and in float64 numpy.

Train, then freeze, then plan: :meth:`DynamicsEnsemble.freeze` returns a :class:`FrozenEnsemble`,
an immutable float64 copy (weights copied at that moment, normalization folded in, no torch) with
the dynamics protocol (``step``, ``jacobians``) and the member spread (``predict``,
``member_jacobians``). Planning uses only the frozen copy; nothing global tracks the training.
"""

from __future__ import annotations

import json
import os
from collections.abc import Callable, Sequence
from dataclasses import asdict, dataclass, field
from types import SimpleNamespace
from typing import Literal

import numpy as np
import torch
from numba import njit
from scipy.special import expit
from torch import nn
from torch.nn import functional as F  # noqa: N812

from mbtsr._lqr_kernels import guard_row, policy_row, rollout_buffers
from mbtsr.dynamics import check_step_inputs, check_step_shapes
from mbtsr.fileformat import CheckpointError, torch_load_verified, torch_save_verified
from mbtsr.trajectory import Trajectory
from mbtsr.validation import as_array

__all__ = [
    "ModelConfig",
    "ACTIVATIONS",
    "FrozenEnsemble",
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
#: A dimension whose std is below REL_STD_FLOOR times its magnitude ``max |value|`` (for the
#: residual targets: the magnitude of the next state) is constant up to float32 rounding (e.g. a
#: constant input) and is not rescaled. Relative, so that data of any unit or scale normalize
#: the same way (an absolute floor of 1e-8 left data scaled by 1e-6 unnormalized).
REL_STD_FLOOR = 1e-6


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



@dataclass(frozen=True)
class ModelConfig:
    """An ensemble architecture before the data's dimensions are known (the agent's ``model``).

    :class:`EnsembleConfig` needs ``state_dim``/``action_dim`` (and a seed), which a learner only
    knows once it sees its env; this config holds everything else and :meth:`build` adds them.
    It covers the formulations that need no nominal matrices (``"g"``, ``"f"``) and uniform
    members (one width and depth, activations cycled).

    :param formulation: ``"g"`` (``x+ = x + g(x, u)``, paper Objective 2) or ``"f"``
        (``x+ = f(x, u)``, Objective 1).
    :param ensemble_size: number of ensemble members (their mean is the model).
    :param hidden_width: hidden units per layer of each member (paper: 20).
    :param hidden_layers: hidden layers per member, 1 (paper) or 2.
    :param activations: member ``k`` uses ``activations[k % len(activations)]``; the default is
        the paper's nominal ensemble (elu, sigmoid, tanh, swish).
    """

    formulation: Literal["g", "f"] = "g"
    ensemble_size: int = 4
    hidden_width: int = 20
    hidden_layers: int = 1
    activations: tuple[str, ...] = ("elu", "sigmoid", "tanh", "swish")

    def __post_init__(self) -> None:
        acts = (self.activations,) if isinstance(self.activations, str) else self.activations
        object.__setattr__(self, "activations", tuple(acts))
        if self.formulation not in ("g", "f"):
            raise ValueError(f"formulation must be one of ('g', 'f'), got {self.formulation!r}")
        for name in ("ensemble_size", "hidden_width"):
            v = getattr(self, name)
            if isinstance(v, bool) or not isinstance(v, (int, np.integer)) or v < 1:
                raise ValueError(f"{name} must be an integer >= 1, got {v!r}")
        if self.hidden_layers not in (1, 2) or isinstance(self.hidden_layers, bool):
            raise ValueError(f"hidden_layers must be 1 or 2, got {self.hidden_layers!r}")
        if len(self.activations) == 0 or any(a not in ACTIVATIONS for a in self.activations):
            raise ValueError(
                f"activations must be a non-empty tuple of names from {sorted(ACTIVATIONS)}, "
                f"got {self.activations!r}"
            )

    def ensemble_config(self, state_dim: int, action_dim: int, seed: int = 0) -> EnsembleConfig:
        """The :class:`EnsembleConfig` for data of these dimensions (inputs and outputs
        normalized; ``seed`` seeds the weight initialisation)."""
        acts = self.activations
        members = tuple(MemberSpec(activation=acts[k % len(acts)], width=self.hidden_width,
                                   depth=self.hidden_layers) for k in range(self.ensemble_size))
        return EnsembleConfig(state_dim=state_dim, action_dim=action_dim, members=members,
                              formulation=self.formulation, normalize=True, seed=seed)

    def build(self, state_dim: int, action_dim: int, seed: int = 0) -> DynamicsEnsemble:
        """A freshly initialised :class:`DynamicsEnsemble` of :meth:`ensemble_config`."""
        return DynamicsEnsemble(self.ensemble_config(state_dim, action_dim, seed))


# --------------------------------------------------------------------------------------------
# The batched network math, written once for torch (float32, differentiable) and numpy (float64)
# --------------------------------------------------------------------------------------------

def _torch_affine(h: torch.Tensor, W: torch.Tensor, b: torch.Tensor) -> torch.Tensor:
    """``h @ W + b`` per member in one op: ``h: [B, i]`` (shared) or ``[K, B, i]``."""
    if h.dim() == 2:
        h = h.expand(W.shape[0], -1, -1)
    return torch.baddbmm(b, h, W)


def _ops(xp, affine: Callable, split: Callable, act_index: int) -> SimpleNamespace:
    """The array operations of the network math in ``xp`` (``torch`` or ``numpy``: both take
    ``keepdims``/``axis`` and ``.mT``); ``act_index`` picks the torch (0) or numpy (1)
    activation of :data:`ACTIVATIONS`."""
    return SimpleNamespace(
        xp=xp,
        affine=affine,
        split=split,
        act=lambda name: ACTIVATIONS[name][act_index],
        sum_last=lambda a: xp.sum(a, -1, keepdims=True),
        sum_m2=lambda a: xp.sum(a, -2, keepdims=True),
        sqrt=xp.sqrt,
        cat=lambda parts, axis: xp.concatenate(parts, axis=axis),
        T=lambda a: a.mT,
    )


_TORCH_OPS = _ops(torch, _torch_affine, lambda z, sizes: z.split(sizes, 0), 0)
_NUMPY_OPS = _ops(np, lambda h, W, b: h @ W + b,
                  lambda z, sizes: np.split(z, np.cumsum(sizes)[:-1], 0), 1)


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
        """Parameters and buffers by name."""
        return {**dict(self.named_parameters()), **dict(self.named_buffers())}

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
    Planning surface: :meth:`freeze` -> :class:`FrozenEnsemble` (float64 numpy, immutable). The
    numpy methods :meth:`step`, :meth:`predict`, :meth:`jacobians`, :meth:`member_jacobians`,
    :meth:`member_predictions` are conveniences that freeze on every call. Members are reported
    in the order of ``config.members``.

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
        ``REL_STD_FLOOR`` times the dimension's magnitude (constant up to float32 rounding) is
        replaced by 1. With ``config.normalize=False`` the statistics stay
        identity and the model is only marked as set.

        :param trajs: a :class:`~mbtsr.trajectory.Trajectory` or a list of them.
        """
        xu, x_next = _pool_transitions(trajs, self.state_dim, self.action_dim)
        if self.config.normalize:
            resid = x_next - xu @ self.config.skip_jacobian().T
            for name, data, raw in (("in", xu, xu), ("out", resid, x_next)):
                mean, std = data.mean(0), data.std(0)
                scale = np.maximum(np.abs(raw).max(0), np.abs(data).max(0))
                std = np.where((std <= REL_STD_FLOOR * scale) | (std == 0), 1.0, std)
                getattr(self, f"{name}_mean").copy_(torch.as_tensor(mean))
                getattr(self, f"{name}_std").copy_(torch.as_tensor(std))
        self.normalization_set.fill_(1)

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

    # ---------------------------------------------------------------- torch surface
    def _xu_torch(self, x, u) -> torch.Tensor:
        n, m = self.state_dim, self.action_dim
        x = torch.as_tensor(x, dtype=torch.float32)
        if u is None:
            if x.ndim < 1 or x.shape[-1] != n + m:
                raise ValueError(f"xu must have last dimension n+m={n + m}, got {list(x.shape)}")
            return x
        u = torch.as_tensor(u, dtype=torch.float32)
        check_step_shapes(x.shape, u.shape, n, m)
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

    # ---------------------------------------------------------------- planning surface
    def freeze(self) -> FrozenEnsemble:
        """An immutable float64 copy for planning (:class:`FrozenEnsemble`): weights copied
        now, normalization folded in, no autograd. Freeze after each training round and plan
        (iLQR, MPC, CEM) with the frozen copy; the ensemble itself keeps training.

        :raises ValueError: naming the tensor, if a weight or normalization statistic is NaN/inf
            (a diverged training run) or a normalization std is not positive.
        """
        with torch.no_grad():
            for name, t in (*self.named_parameters(), *self.named_buffers()):
                if t.is_floating_point() and not bool(torch.isfinite(t).all()):
                    bad = int((~torch.isfinite(t)).sum())
                    raise ValueError(
                        f"cannot freeze: {name} contains {bad} non-finite value(s) (NaN or inf)"
                    )
            for name in ("in_std", "out_std"):
                if not bool((getattr(self, name) > 0).all()):
                    raise ValueError(f"cannot freeze: {name} must be > 0")
            return FrozenEnsemble(self)

    # Convenience for one-off numpy evaluation (metrics, tests): each call freezes a fresh copy
    # (tens of microseconds); for repeated calls freeze once and use the frozen model.
    def step(self, x: np.ndarray, u: np.ndarray, t: int | None = None) -> np.ndarray:
        """``self.freeze().step(x, u, t)``: ensemble-mean next state ``[..., n]`` (float64)."""
        return self.freeze().step(x, u, t)

    def member_predictions(self, x: np.ndarray, u: np.ndarray) -> np.ndarray:
        """``self.freeze().member_predictions(x, u)``: ``[K, ..., n]``."""
        return self.freeze().member_predictions(x, u)

    def predict(self, x: np.ndarray, u: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
        """``self.freeze().predict(x, u)``: ensemble ``(mean, std)`` of the next state."""
        return self.freeze().predict(x, u)

    def member_jacobians(self, x: np.ndarray, u: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
        """``self.freeze().member_jacobians(x, u)``: ``(A [K, T, n, n], B [K, T, n, m])``."""
        return self.freeze().member_jacobians(x, u)

    def jacobians(self, x: np.ndarray, u: np.ndarray, t: int = 0) -> tuple[np.ndarray, np.ndarray]:
        """``self.freeze().jacobians(x, u)``: ensemble-mean ``(A [T, n, n], B [T, n, m])``."""
        return self.freeze().jacobians(x, u, t)


# --------------------------------------------------------------------------------------------
# The frozen planning model: float64 numpy, normalization folded into the weights once
# --------------------------------------------------------------------------------------------


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
"""Value-only activations of :meth:`FrozenEnsemble.step`: ``f(z, h)`` writes into ``h``. Sigmoid,
swish and tanh all run as numpy's vectorized tanh, the affine parts folded into the weights::

    sigmoid(z) = 0.5 tanh(z/2) + 0.5,     swish(z) = z sigmoid(z) = z' tanh(z') + z',  z' = z/2.
"""


_KERNEL_MAX_BATCH = 4  # rows up to which the compiled kernel beats numpy (measured: ~2x at 1-4
# rows; at 11 rows numpy's SIMD transcendental functions are faster than scalar libm calls)
_KERNEL_CODE = {"elu": 0, "sigmoid": 1, "tanh": 1, "swish": 2, "relu": 3, "leaky_relu": 4}


@njit(cache=True)
def _mean_step_row(x, u, W_inT, W_out, code, z, out):  # pragma: no cover - compiled
    """One row of :func:`_mean_step_kernel`: ``x [n]``, ``u [m]`` -> ``out [n]`` (``z [H]``
    scratch)."""
    n, m, H = x.shape[0], u.shape[0], W_inT.shape[1]
    for h in range(H):
        z[h] = W_inT[0, h]
    for i in range(n):
        xi = x[i]
        for h in range(H):
            z[h] += xi * W_inT[1 + i, h]
    for j in range(m):
        uj = u[j]
        for h in range(H):
            z[h] += uj * W_inT[1 + n + j, h]
    for o in range(n):
        out[o] = W_out[H, o]
    for i in range(n):
        xi = x[i]
        for o in range(n):
            out[o] += xi * W_out[H + 1 + i, o]
    for j in range(m):
        uj = u[j]
        for o in range(n):
            out[o] += uj * W_out[H + 1 + n + j, o]
    for h in range(H):
        c, zh = code[h], z[h]
        if c == 0:
            a = zh if zh > 0.0 else np.expm1(zh)
        elif c == 1:
            a = np.tanh(zh)
        elif c == 2:
            a = zh * np.tanh(zh)
        elif c == 3:
            a = zh if zh > 0.0 else 0.0
        else:
            a = zh if zh > 0.0 else LEAKY_RELU_SLOPE * zh
        for o in range(n):
            out[o] += a * W_out[h, o]


@njit(cache=True)
def _mean_step_kernel(x, u, W_inT, W_out, code, out):  # pragma: no cover - compiled
    """Compiled ensemble-mean step on the folded weights of :func:`_mean_step_plan`:
    ``x [B, n]``, ``u [B, m]``, ``W_inT [1+n+m, H]``, ``W_out [H+1+n+m, n]``, ``code [H]``
    (0 elu, 1 tanh (sigmoid rows are pre-halved), 2 swish as ``z' tanh(z')``, 3 relu,
    4 leaky relu) -> ``out [B, n]``. The same arithmetic as the numpy path, one row at a time,
    without numpy's per-call overhead."""
    z = np.empty(W_inT.shape[1])
    for b in range(x.shape[0]):
        _mean_step_row(x[b], u[b], W_inT, W_out, code, z, out[b])
    return out


@njit(cache=True)
def _rollout_policy_kernel(W_inT, W_out, code, x0, X, U, k, K, alphas, lower, upper,
                           max_norm):  # pragma: no cover - compiled
    """Closed-loop rollouts of the frozen ensemble-mean model for all step sizes, in one
    compiled call: ``u_t = clip(U_t + alpha k_t + K_t (x_t - X_t), lower, upper)``;
    ``X: [T+1, n]``, ``U, k: [T, m]``, ``K: [T, m, n]``, ``alphas: [N]`` ->
    ``(Xn [N, T+1, n], Un [N, T, m], alive [N])``, the semantics of
    ``mbtsr.ilqr._rollout_policy`` (a row that turns non-finite is dead and continues from the
    nominal state; rows exceeding ``max_norm`` are dead at the end)."""
    T, m = U.shape
    Xn, Un, alive = rollout_buffers(x0, T, m, alphas.shape[0])
    z = np.empty(W_inT.shape[1])
    for a in range(alphas.shape[0]):
        biggest = 0.0
        for i in range(x0.shape[0]):
            biggest = max(biggest, abs(x0[i]))
        for t in range(T):
            policy_row(U, k, K, X, t, alphas[a], lower, upper, Xn[a, t], Un[a, t])
            _mean_step_row(Xn[a, t], Un[a, t], W_inT, W_out, code, z, Xn[a, t + 1])
            finite, biggest = guard_row(Xn[a, t + 1], X[t + 1], biggest)
            alive[a] &= finite
        if not biggest <= max_norm:
            alive[a] = False
    return Xn, Un, alive


def _mean_step_plan(runs, W: int, W1: np.ndarray, b1: np.ndarray, Wo: np.ndarray,
                    bo: np.ndarray, skip_J: np.ndarray, n_members: int) -> SimpleNamespace:
    """Folded weights of the ensemble-mean step of ONE depth-1 group without layer norm.

    ``W1 [K, n+m, W]``, ``b1 [K, W]``, ``Wo [K, W, n]``, ``bo [K, n]`` already hold the
    normalization (raw units in and out) and zero padded units. With ``H = K*W`` hidden units,
    one buffer ``G = [h; 1; x^T; u^T]: [H+1+n+m, B]`` carries everything: ``z = W_in @ G[H:]``
    with ``W_in = [b1, W1^T]: [H, 1+n+m]``, ``h = act(z)`` and ``x+ = G^T @ W_out`` with
    ``W_out = [Wo / K; mean bo; skip_J^T]``. Sigmoid and swish rows run as tanh of ``z/2``
    (rows of ``W_in`` halved); their affine remainders are linear in ``G`` and go into
    ``W_out``.
    """
    K = W1.shape[0]
    H = K * W
    W_in = np.concatenate([b1.reshape(H, 1), W1.transpose(0, 2, 1).reshape(H, -1)], 1)
    Wo_mean = Wo.reshape(H, -1) / n_members
    ops: list[tuple[Callable, int, int]] = []
    swish_ops: list[tuple[Callable, int, int]] = []
    sigmoid, swish = np.zeros(H, bool), np.zeros(H, bool)
    for name, a, b in runs:
        f, first, stop = _FAST_VALUE[name], a * W, b * W
        if f is _fast_tanh and ops and ops[-1][0] is _fast_tanh and ops[-1][2] == first:
            ops[-1] = (f, ops[-1][1], stop)  # one tanh call over consecutive tanh-family rows
        else:
            ops.append((f, first, stop))
        if name == "sigmoid":
            sigmoid[first:stop] = True
        elif name == "swish":
            swish[first:stop] = True
            swish_ops.append((_fast_times, first, stop))
    W_in[sigmoid | swish] *= 0.5
    W_out = np.concatenate([Wo_mean, bo.sum(0, keepdims=True) / n_members, skip_J.T], 0)
    W_out[:H][sigmoid] *= 0.5  # Wo (0.5 t + 0.5) = (0.5 Wo) t + 0.5 Wo
    W_out[H] += 0.5 * Wo_mean[sigmoid].sum(0)
    W_out[H:] += W_in[swish].T @ Wo_mean[swish]  # Wo (z' t + z') = Wo z' t + (Wo W_in') G_in
    # mean Jacobian: J[b, (o, i)] = sum_h act'(z[h, b]) M[h, (o, i)],  M = Wo[h, o] W1[i, h] / K
    M = (Wo[:, :, :, None] * W1.swapaxes(1, 2)[:, :, None, :]).reshape(H, -1) / n_members
    code = np.zeros(H, np.int64)  # per hidden row, for the compiled kernel
    for name, a, b in runs:
        code[a * W:b * W] = _KERNEL_CODE[name]
    return SimpleNamespace(
        W_in=_readonly(W_in), W_out=_readonly(W_out), ops=tuple(ops + swish_ops), H=H,
        code=_readonly(code), W_inT=_readonly(W_in.T),
        W1=_readonly(W1.transpose(1, 0, 2).reshape(-1, H)), b1=_readonly(b1.reshape(H)),
        M=_readonly(M), runs=tuple((name, a * W, b * W) for name, a, b in runs),
    )


def _readonly(a: np.ndarray) -> np.ndarray:
    a = np.ascontiguousarray(a, dtype=np.float64)
    a.setflags(write=False)
    return a


class FrozenEnsemble:
    """An immutable float64 copy of a :class:`DynamicsEnsemble`: the model planning uses.

    Made by :meth:`DynamicsEnsemble.freeze` (after each training round); it holds plain numpy
    arrays (read-only) with the input/output normalization folded into the weights, no torch
    tensors, no autograd, no cache: later training of the ensemble does not change it. It has
    the :class:`mbtsr.dynamics.DynamicsModel` protocol (``step``, ``jacobians``,
    ``state_dim``, ``action_dim``) and the member spread (:meth:`predict`,
    :meth:`member_predictions`, :meth:`member_jacobians`). Members are in config order.

    The ensemble-mean :meth:`step` of the paper's architecture (one group of depth-1 members
    without layer norm) runs on pre-folded weights (see :func:`_mean_step_plan`): a compiled
    (numba) kernel for up to ``_KERNEL_MAX_BATCH`` rows (the rollouts of iLQR and MPC), two
    matrix products and vectorized activations for larger batches; other architectures run the
    generic batched forward pass.
    Public methods validate their inputs; ``_step`` is the unchecked kernel solver loops call
    (see :mod:`mbtsr.dynamics`). Not thread-safe only in the sense that numpy is not.
    """

    def __init__(self, ensemble: DynamicsEnsemble) -> None:
        n, m = ensemble.state_dim, ensemble.action_dim
        stats = {k: getattr(ensemble, k).detach().double().numpy().copy()
                 for k in ("in_mean", "in_std", "out_mean", "out_std")}
        in_mean, in_std = stats["in_mean"], stats["in_std"]
        out_mean, out_std = stats["out_mean"], stats["out_std"]
        skip_J = ensemble.config.skip_jacobian()
        groups = []
        for g in ensemble.groups:
            p = {k: v.detach().double().numpy().copy() for k, v in g.arrays().items()}
            if g.padded:  # padded units get exactly zero weights in and out
                mask = p["mask"]
                p["W1"] = p["W1"] * mask
                if g.depth == 2:
                    p["W2"] = p["W2"] * mask.swapaxes(-1, -2) * mask
                p["Wo"] = p["Wo"] * mask.swapaxes(-1, -2)
            # ((xu - in_mean) / in_std) @ W1 + b1 = xu @ (W1 / in_std) + (b1 - (in_mean/in_std) W1)
            p["b1"] = p["b1"] - ((in_mean / in_std) @ p["W1"])[:, None, :]
            p["W1"] = p["W1"] / in_std[None, :, None]
            # out_mean + out_std * (h @ Wo + bo)
            p["Wo"] = p["Wo"] * out_std
            p["bo"] = p["bo"] * out_std + out_mean
            static = SimpleNamespace(depth=g.depth, runs=list(g.runs), layer_norm=g.layer_norm,
                                     padded=False)
            groups.append((static, {k: _readonly(v) for k, v in p.items()}))
        plan = None
        if len(groups) == 1 and groups[0][0].depth == 1 and not groups[0][0].layer_norm:
            static, p = groups[0]
            plan = _mean_step_plan(static.runs, p["W1"].shape[2], p["W1"], p["b1"][:, 0],
                                   p["Wo"], p["bo"][:, 0], skip_J, ensemble.n_members)
        perm = None if ensemble._to_config_order is None else ensemble._to_config_order.numpy()
        for name, value in (
            ("config", ensemble.config), ("state_dim", n), ("action_dim", m),
            ("n_members", ensemble.n_members), ("_groups", tuple(groups)),
            ("_skip_J", _readonly(skip_J)), ("_perm", perm), ("_plan", plan),
        ):
            object.__setattr__(self, name, value)

    def __setattr__(self, name: str, value: object) -> None:
        raise AttributeError(f"a FrozenEnsemble is immutable (tried to set {name!r})")

    def __repr__(self) -> str:
        return (f"FrozenEnsemble(state_dim={self.state_dim}, action_dim={self.action_dim}, "
                f"n_members={self.n_members})")

    # ---------------------------------------------------------------- kernels (no checks)
    def _members(self, xu: np.ndarray, jac_rows: int):
        """``xu [B, n+m]`` -> ``(x_next [K, B, n], J [K, B, n, n+m] or None)``, config order,
        skip parts included."""
        ys, Js = [], []
        for static, p in self._groups:
            y, J = _group_forward(p, static, xu, _NUMPY_OPS, jac_rows)
            ys.append(y)
            Js.append(J)
        y = (ys[0] if len(ys) == 1 else np.concatenate(ys, 0)) + xu @ self._skip_J.T
        J = None
        if jac_rows:
            J = (Js[0] if len(Js) == 1 else np.concatenate(Js, 0)) + self._skip_J
        if self._perm is not None:
            y = y[self._perm]
            J = None if J is None else J[self._perm]
        return y, J

    def _step(self, x: np.ndarray, u: np.ndarray, t: int | None = None) -> np.ndarray:
        """:meth:`step` on float64 arrays ``x [..., n]``, ``u [..., m]`` known to be valid."""
        n, m = self.state_dim, self.action_dim
        lead = x.shape[:-1]
        B = x.size // n
        plan = self._plan
        if plan is None:
            y, _ = self._members(np.concatenate([x.reshape(B, n), u.reshape(B, m)], 1), 0)
            return y.mean(0).reshape(*lead, n)
        x, u = x.reshape(B, n), u.reshape(B, m)
        if B > _KERNEL_MAX_BATCH:  # numpy's vectorized tanh/expm1 win on larger batches
            return self._step_numpy(x, u).reshape(*lead, n)
        out = np.empty((B, n))
        _mean_step_kernel(x, u, plan.W_inT, plan.W_out, plan.code, out)
        return out.reshape(*lead, n)

    @property
    def linear_batch_cost(self) -> bool:
        """True with the compiled rollouts (their cost grows with the number of step sizes,
        so iLQR rolls the step sizes out in chunks, largest first; see :mod:`mbtsr.ilqr`)."""
        return self._plan is not None

    def _rollout_policy(self, x0, X, U, k, K, alphas, lower, upper, max_norm):
        """iLQR's closed-loop line-search rollouts in one compiled call (see
        :func:`_rollout_policy_kernel`; arguments as ``mbtsr.ilqr._rollout_policy`` without
        ``t0``), or ``None`` for architectures without the folded plan (the solver then steps
        the model from Python)."""
        plan = self._plan
        if plan is None:
            return None
        return _rollout_policy_kernel(plan.W_inT, plan.W_out, plan.code, x0, X, U, k, K,
                                      alphas, lower, upper, float(max_norm))

    def _step_numpy(self, x: np.ndarray, u: np.ndarray) -> np.ndarray:
        """The ensemble-mean step of the folded plan in numpy (the compiled kernel's reference;
        ``x [B, n]``, ``u [B, m]`` -> ``[B, n]``)."""
        n, m, plan = self.state_dim, self.action_dim, self._plan
        B, H = x.shape[0], plan.H
        G = np.empty((H + 1 + n + m, B))
        G[H] = 1.0
        G[H + 1:H + 1 + n] = x.T
        G[H + 1 + n:] = u.T
        z = plan.W_in @ G[H:]  # [H, B]
        for act, a, b in plan.ops:
            act(z[a:b], G[a:b])
        return G.T @ plan.W_out

    # ---------------------------------------------------------------- public surface
    def step(self, x: np.ndarray, u: np.ndarray, t: int | None = None) -> np.ndarray:
        """Ensemble-mean next state: ``x: [..., n]``, ``u: [..., m]`` -> ``[..., n]`` (float64,
        a fresh array). ``t`` is ignored (time-invariant)."""
        x, u = check_step_inputs(x, u, self.state_dim, self.action_dim)
        with np.errstate(over="ignore"):  # saturating activations are exact in the limit
            return self._step(x, u, t)

    def member_predictions(self, x: np.ndarray, u: np.ndarray) -> np.ndarray:
        """Next state of every member: ``x: [..., n]``, ``u: [..., m]`` -> ``[K, ..., n]``."""
        x, u = check_step_inputs(x, u, self.state_dim, self.action_dim)
        lead = x.shape[:-1]
        xu = np.concatenate([x, u], -1).reshape(-1, self.state_dim + self.action_dim)
        with np.errstate(over="ignore"):
            y, _ = self._members(xu, 0)
        return y.reshape(self.n_members, *lead, self.state_dim)

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
        with np.errstate(over="ignore"):
            _, J = self._members(np.concatenate([x, u], -1), x.shape[0])
        return J[..., :n], J[..., n:]

    def jacobians(self, x: np.ndarray, u: np.ndarray, t: int = 0) -> tuple[np.ndarray, np.ndarray]:
        """Ensemble-mean Jacobians of the full map: ``x: [T, n]``, ``u: [T, m]`` ->
        ``(A [T, n, n], B [T, n, m])`` (paper Eq. (jacerr) averages exactly these)."""
        plan = self._plan
        if plan is None:
            A, B = self.member_jacobians(x, u)
            return A.mean(0), B.mean(0)
        n, m = self.state_dim, self.action_dim
        x = as_array("x", x, (None, n))
        u = as_array("u", u, (x.shape[0], m))
        z = np.concatenate([x, u], -1) @ plan.W1 + plan.b1  # [T, H]
        d = np.empty_like(z)
        with np.errstate(over="ignore"):
            for name, a, b in plan.runs:
                _, value, derivative = ACTIVATIONS[name]
                d[:, a:b] = derivative(z[:, a:b], value(z[:, a:b]), np)
        J = (d @ plan.M).reshape(-1, n, n + m) + self._skip_J
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
    return model.eval()
