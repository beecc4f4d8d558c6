"""Neural-network dynamics ensembles: K members ``x+ = s(x, u) + NN_k(x, u)`` evaluated and
trained in ONE batched computation, with closed-form Jacobians in torch (differentiable) and
numpy; :meth:`DynamicsEnsemble.freeze` gives the immutable :class:`FrozenEnsemble` planning
uses. Formulations, members, normalization, the folded planning kernels: docs/models.md.
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
from mbtsr.dynamics import LINE_SEARCH_CHUNKS, check_step_inputs, check_step_shapes
from mbtsr.fileformat import CheckpointError, torch_load_verified, torch_save_verified
from mbtsr.trajectory import Trajectory, as_trajectory_list
from mbtsr.validation import as_array, check_bool, check_choice, check_int

__all__ = [
    "ModelConfig",
    "PAPER_ACTIVATIONS",
    "TrajectorySampling",
    "default_size",
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
#: planning precisions of :meth:`DynamicsEnsemble.freeze` and their numpy types
PRECISIONS = {"float32": np.float32, "float64": np.float64}
#: a dimension whose std is below REL_STD_FLOOR times its magnitude ``max |value|`` is not
#: rescaled (docs/models.md, "Normalization")
REL_STD_FLOOR = 1e-6


def _d_swish(z, a, xp):
    s = torch.sigmoid(z) if xp is torch else expit(z)
    return s * (1.0 + z * (1.0 - s))


def _tanh_via_sigmoid(z: torch.Tensor) -> torch.Tensor:
    """``tanh(z) = 2 sigmoid(2 z) - 1``: torch 2.13's CPU tanh kernel measured ~10x slower than
    its sigmoid on the project's machines (AVX512 path); absolute difference <= 2e-7."""
    return torch.sigmoid(2.0 * z) * 2.0 - 1.0


ACTIVATIONS: dict[str, tuple[Callable, Callable, Callable]] = {
    "elu": (F.elu, lambda z: np.where(z > 0, z, np.expm1(np.minimum(z, 0.0))),
            lambda z, a, xp: xp.where(z > 0, 1.0, a + 1.0)),
    "sigmoid": (torch.sigmoid, expit, lambda z, a, xp: a * (1.0 - a)),
    "tanh": (_tanh_via_sigmoid, np.tanh, lambda z, a, xp: 1.0 - a * a),
    "swish": (F.silu, lambda z: z * expit(z), _d_swish),
    "relu": (F.relu, lambda z: np.maximum(z, 0.0), lambda z, a, xp: (z > 0) * 1.0),
    "leaky_relu": (lambda z: F.leaky_relu(z, LEAKY_RELU_SLOPE),
                   lambda z: np.where(z > 0, z, LEAKY_RELU_SLOPE * z),
                   lambda z, a, xp: xp.where(z > 0, 1.0, LEAKY_RELU_SLOPE)),
}
"""Supported activations: name -> (torch value, numpy value, derivative ``d(z, act(z), xp)``;
torch derivatives are differentiable). ``swish`` is silu, ``elu`` alpha 1, ``leaky_relu``
slope 0.01."""

PAPER_ACTIVATIONS = ("elu", "sigmoid", "tanh", "swish")
"""The paper's nominal ensemble: one member of each of these activations."""


# --------------------------------------------------------------------------------------------
# Configuration
# --------------------------------------------------------------------------------------------


@dataclass(frozen=True)
class MemberSpec:
    """One ensemble member's architecture.

    :param activation: one of :data:`ACTIVATIONS` (elu, sigmoid, tanh, swish, relu, leaky_relu).
    :param width: hidden units per layer (paper: 20).
    :param depth: number of hidden layers, any integer >= 1 (paper: 1).
    :param dropout: inverted dropout probability on hidden units during training, in ``[0, 1)``.
    :param layer_norm: layer normalization (with gain and bias) of each hidden pre-activation."""

    activation: str = "elu"
    width: int = 20
    depth: int = 1
    dropout: float = 0.0
    layer_norm: bool = False

    def __post_init__(self) -> None:
        check_choice("activation", self.activation, ACTIVATIONS)
        object.__setattr__(self, "width", check_int("width", self.width, 1))
        object.__setattr__(self, "depth", check_int("depth", self.depth, 1))
        if not (np.isfinite(self.dropout) and 0.0 <= self.dropout < 1.0):
            raise ValueError(f"dropout must be in [0, 1), got {self.dropout!r}")
        object.__setattr__(self, "dropout", float(self.dropout))
        object.__setattr__(self, "layer_norm", check_bool("layer_norm", self.layer_norm))


def _paper_members() -> tuple[MemberSpec, ...]:
    return tuple(MemberSpec(a, 20, 1) for a in PAPER_ACTIVATIONS)


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
    :param formulation: ``"f"`` (x+ = NN), ``"g"`` (x+ = x + NN, the default), ``"nominal"``
        (x+ = A0 x + B0 u + NN) or ``"scaled"`` (x+ = tau x + NN).
    :param A0: ``[n, n]`` nominal state matrix (formulation ``"nominal"`` only).
    :param B0: ``[n, m]`` nominal input matrix (formulation ``"nominal"`` only).
    :param tau: skip scale of formulation ``"scaled"``, a scalar or ``[n]`` (a diagonal).
    :param normalize: standardize network inputs ``[x, u]`` and residual outputs (``False``:
        raw data, as the original code).
    :param seed: seed of the weight initialisation (glorot-uniform weights, zero biases).
    :param probabilistic: every member also has a soft-bounded log-variance head (PETS;
        docs/models.md, "Probabilistic members"); the mean is the model.

    Arrays are stored as tuples so the config is hashable and JSON-serializable."""

    state_dim: int
    action_dim: int
    members: tuple[MemberSpec, ...] = field(default_factory=_paper_members)
    formulation: str = "g"
    A0: tuple[tuple[float, ...], ...] | None = None
    B0: tuple[tuple[float, ...], ...] | None = None
    tau: float | tuple[float, ...] = 1.0
    normalize: bool = True
    seed: int = 0
    probabilistic: bool = False

    def __post_init__(self) -> None:
        for name in ("state_dim", "action_dim"):
            object.__setattr__(self, name, check_int(name, getattr(self, name), 1))
        n, m = self.state_dim, self.action_dim
        members = tuple(self.members)
        if len(members) == 0:
            raise ValueError("members must hold at least one MemberSpec")
        for i, spec in enumerate(members):
            if not isinstance(spec, MemberSpec):
                raise ValueError(f"members[{i}] must be a MemberSpec, got {type(spec).__name__}")
        object.__setattr__(self, "members", members)
        check_choice("formulation", self.formulation, FORMULATIONS)
        if self.formulation == "nominal":
            if self.A0 is None or self.B0 is None:
                raise ValueError("formulation 'nominal' needs A0 [n, n] and B0 [n, m]")
            object.__setattr__(self, "A0", _as_matrix_tuple("A0", self.A0, (n, n)))
            object.__setattr__(self, "B0", _as_matrix_tuple("B0", self.B0, (n, m)))
        elif self.A0 is not None or self.B0 is not None:
            raise ValueError(f"A0/B0 are only used by formulation 'nominal', got formulation "
                             f"{self.formulation!r}")
        tau = as_array("tau", self.tau)
        if tau.ndim == 0:
            object.__setattr__(self, "tau", float(tau))
        elif tau.shape == (n,):
            object.__setattr__(self, "tau", tuple(float(v) for v in tau))
        else:
            raise ValueError(f"tau must be a scalar or have shape [{n}], got {list(tau.shape)}")
        check_bool("normalize", self.normalize)
        object.__setattr__(self, "seed", check_int("seed", self.seed, None))
        object.__setattr__(self, "probabilistic", check_bool("probabilistic", self.probabilistic))

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



def default_size(state_dim: int, action_dim: int) -> tuple[int, int]:
    """The sizing rule of :class:`ModelConfig`: ``(hidden_layers, hidden_width)`` = ``(3,
    32 sqrt(n + m))``, the width rounded to a multiple of 16 within [64, 256] (docs/models.md,
    "Sizing", has the measurements)."""
    p = int(state_dim) + int(action_dim)
    width = 16 * int(round(32.0 * np.sqrt(p) / 16.0))
    return 3, int(min(256, max(64, width)))


@dataclass(frozen=True)
class ModelConfig:
    """An ensemble architecture before the data's dimensions are known (the agent's ``model``).

    :meth:`build` adds the dimensions and seed; formulations ``"g"``/``"f"``, uniform members
    (activations cycled); :meth:`paper` is the paper's nominal ensemble.

    :param formulation: ``"g"`` (``x+ = x + g(x, u)``, paper Objective 2) or ``"f"``
        (``x+ = f(x, u)``, Objective 1).
    :param ensemble_size: number of ensemble members (their mean is the model).
    :param hidden_width: hidden units per layer of each member; ``None``: sized by the task's
        dimensions (:func:`default_size`).
    :param hidden_layers: hidden layers per member (any integer >= 1); ``None``: sized by the
        task's dimensions (:func:`default_size`).
    :param activations: member ``k`` uses ``activations[k % len(activations)]``.
    :param probabilistic: members with a bounded log-variance head trained by Gaussian NLL
        (PETS; :class:`EnsembleConfig`)."""

    formulation: Literal["g", "f"] = "g"
    ensemble_size: int = 4
    hidden_width: int | None = None
    hidden_layers: int | None = None
    activations: tuple[str, ...] = ("swish",)
    probabilistic: bool = False

    def __post_init__(self) -> None:
        acts = (self.activations,) if isinstance(self.activations, str) else self.activations
        object.__setattr__(self, "activations", tuple(acts))
        check_choice("formulation", self.formulation, ("g", "f"))
        check_int("ensemble_size", self.ensemble_size, 1)
        for name in ("hidden_width", "hidden_layers"):
            if getattr(self, name) is not None:
                check_int(name, getattr(self, name), 1)
        if len(self.activations) == 0 or any(a not in ACTIVATIONS for a in self.activations):
            raise ValueError(
                f"activations must be a non-empty tuple of names from {sorted(ACTIVATIONS)}, "
                f"got {self.activations!r}"
            )
        check_bool("probabilistic", self.probabilistic)

    @classmethod
    def paper(cls, **overrides) -> ModelConfig:
        """The paper's nominal ensemble: 4 members x 1 hidden layer x 20 units with the
        activations elu, sigmoid, tanh and swish (``overrides`` change fields)."""
        return cls(**{"ensemble_size": 4, "hidden_width": 20, "hidden_layers": 1,
                      "activations": PAPER_ACTIVATIONS, **overrides})

    def size(self, state_dim: int, action_dim: int) -> tuple[int, int]:
        """``(hidden_layers, hidden_width)`` for these dimensions: the fields, or the sizing
        rule :func:`default_size` for those left at ``None``."""
        layers, width = default_size(state_dim, action_dim)
        return (layers if self.hidden_layers is None else int(self.hidden_layers),
                width if self.hidden_width is None else int(self.hidden_width))

    def ensemble_config(self, state_dim: int, action_dim: int, seed: int = 0) -> EnsembleConfig:
        """The :class:`EnsembleConfig` for data of these dimensions (inputs and outputs
        normalized; ``seed`` seeds the weight initialisation)."""
        acts = self.activations
        depth, width = self.size(state_dim, action_dim)
        members = tuple(MemberSpec(activation=acts[k % len(acts)], width=width, depth=depth)
                        for k in range(self.ensemble_size))
        return EnsembleConfig(state_dim=state_dim, action_dim=action_dim, members=members,
                              formulation=self.formulation, normalize=True, seed=seed,
                              probabilistic=bool(self.probabilistic))

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


def _ops(xp, affine: Callable, split: Callable, act_index: int, chain: Callable,
         softplus: Callable) -> SimpleNamespace:
    """The array operations of the network math in ``xp`` (``torch`` or ``numpy``: both take
    ``keepdims``/``axis`` and ``.mT``); ``act_index`` picks the torch (0) or numpy (1)
    activation of :data:`ACTIVATIONS`; ``chain(W, J)`` is ``W^T @ J`` per member and point
    (``W [K, V, W]``, ``J [K, R, V, in]`` -> ``[K, R, W, in]``)."""
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
        chain=chain,
        softplus=softplus,
    )


# torch: one batched product per member (einsum -> bmm), never W broadcast over the points
# (torch.matmul would materialize W^T for every point: K x R x W x W numbers); numpy's matmul
# broadcasts without copies
_TORCH_OPS = _ops(torch, _torch_affine, lambda z, sizes: z.split(sizes, 0), 0,
                  lambda W, J: torch.einsum("kvw,krvi->krwi", W, J), F.softplus)
_NUMPY_OPS = _ops(np, lambda h, W, b: h @ W + b,
                  lambda z, sizes: np.split(z, np.cumsum(sizes)[:-1], 0), 1,
                  lambda W, J: W.swapaxes(-1, -2)[:, None] @ J,
                  lambda z: np.logaddexp(0.0, z))


def _activate(z, runs, ops, jac_rows: int):
    """Per-member activations on contiguous member runs.

    ``z: [K, B, W]`` -> ``(act(z) [K, B, W], act'(z) [K, jac_rows, W] or None)``."""
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
    member) -> ``(y, zhat, inv_std)`` with ``zhat: [K, B, W]`` and ``inv_std: [K, B, 1]``."""
    mu = ops.sum_last(z * mask) / width
    d = (z - mu) * mask
    inv_std = 1.0 / ops.sqrt(ops.sum_last(d * d) / width + LAYER_NORM_EPS)
    zhat = d * inv_std
    return zhat * gain + bias, zhat, inv_std


def _layer_norm_jacobian(Jz, zhat, inv_std, gain, mask, width, ops):
    """Chain rule through :func:`_layer_norm`: ``dy/dz = gain/s (I - 1 1^T/w - zhat zhat^T/w)``.

    ``Jz: [K, R or 1, W, in]`` (Jacobian of ``z``), ``zhat: [K, R, W]``, ``inv_std: [K, R, 1]``
    -> ``[K, R, W, in]``."""
    m = mask[..., None]
    zh = zhat[..., None]
    w = width[..., None]
    mean_J = ops.sum_m2(Jz * m) / w
    mean_zJ = ops.sum_m2(zh * Jz) / w
    return (gain * inv_std)[..., None] * (Jz - mean_J - zh * mean_zJ) * m


def _bounded_logvar(raw, max_logvar, min_logvar, ops):
    """PETS' soft bounds: ``min + softplus(max - softplus(max - raw) - min)`` (mbrl-lib
    ``GaussianMLP``), elementwise; ``raw [K, B, n]``, bounds ``[K, 1, n]``."""
    lv = max_logvar - ops.softplus(max_logvar - raw)
    return min_logvar + ops.softplus(lv - min_logvar)


def _hidden_names(depth: int) -> list[tuple[str, str]]:
    """``[("W1", "b1"), ..., ("W<depth>", "b<depth>")]``: the hidden layers' parameter names."""
    return [(f"W{layer}", f"b{layer}") for layer in range(1, depth + 1)]


def _groups_forward(groups, xn, ops, jac_rows=0, masks=None):
    """:func:`_group_forward` of every depth group, outputs concatenated over members.

    :param groups: ``(g, p)`` (static description, arrays) per group, in stacked order.
    :param xn: ``[B, in]`` shared by all members, or ``[K, B, in]`` one set per member
        (stacked order).
    :param masks: ``masks(g)`` -> the group's dropout masks or None (drawn group by group).
    :return: ``(y [K, B, n], J [K, jac_rows, n, in] or None, logvar [K, B, n] or None)``."""
    ys, Js, lvs = [], [], []
    start = 0
    for g, p in groups:
        K = p["W1"].shape[0]
        xg = xn if xn.ndim == 2 else xn[start:start + K]
        start += K
        y, J, lv = _group_forward(p, g, xg, ops, jac_rows, None if masks is None else masks(g))
        ys.append(y)
        Js.append(J)
        lvs.append(lv)

    def cat(parts):
        return parts[0] if len(parts) == 1 else ops.cat(parts, 0)

    return cat(ys), cat(Js) if jac_rows else None, None if lvs[0] is None else cat(lvs)


def _zero_padded(p: dict, depth: int, T: Callable) -> dict:
    """``p`` with the weights of padded units exactly zero in and out (``T`` transposes)."""
    mask, p = p["mask"], dict(p)
    p["W1"] = p["W1"] * mask
    for w, _ in _hidden_names(depth)[1:]:
        p[w] = p[w] * T(mask) * mask
    for w in ("Wo", "Wv"):
        if w in p:
            p[w] = p[w] * T(mask)
    return p


def _group_forward(p, g, xn, ops, jac_rows=0, dropout_masks=None):
    """Forward pass (and closed-form Jacobians) of one depth group of stacked members.

    :param p: dict of arrays/tensors: ``W1 [K, in, W]``, ``b1 [K, 1, W]``, for deeper layers
        ``W<l> [K, W, W]``, ``b<l> [K, 1, W]``, ``Wo [K, W, n]``, ``bo [K, 1, n]``; if padded or
        layer-normed ``mask [K, 1, W]`` and ``width [K, 1, 1]``; with layer norm
        ``ln_gain<l>, ln_bias<l> [K, 1, W]`` and, if only some members use it,
        ``ln_select [K, 1, 1]``; probabilistic members ``Wv [K, W, n]``, ``bv``,
        ``max_logvar``, ``min_logvar [K, 1, n]``.
    :param g: static description: ``depth``, ``runs`` (activation, first, stop) over members,
        ``layer_norm`` (any member), ``padded``, ``probabilistic``.
    :param xn: ``[B, in]`` normalized inputs shared by all members, or ``[K, B, in]`` one set
        per member.
    :param jac_rows: compute Jacobians for the first ``jac_rows`` points (0: none).
    :param dropout_masks: per hidden layer ``[K, B, W]`` inverted-dropout masks, or None.
    :return: ``y: [K, B, n]`` normalized outputs (the mean), ``J: [K, jac_rows, n, in]`` of ``y``
        w.r.t. ``xn`` (or None), ``logvar: [K, B, n]`` (probabilistic members) or None."""
    mask = p.get("mask")
    if g.padded:
        p = _zero_padded(p, g.depth, ops.T)
    names = _hidden_names(g.depth)
    W_hidden = [p[w] for w, _ in names]
    b_hidden = [p[b] for _, b in names]
    Wo, Wv = p["Wo"], p.get("Wv")
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
        Jz = ops.T(W)[:, None] if J is None else ops.chain(W, J)  # [K, R|1, W, in]
        if g.layer_norm:
            Jz_ln = _layer_norm_jacobian(
                Jz, zhat[:, :jac_rows], inv_std[:, :jac_rows], gain, mask, p["width"], ops
            )
            sel = p.get("ln_select")
            Jz = Jz_ln if sel is None else sel[..., None] * Jz_ln + (1.0 - sel[..., None]) * Jz
        J = d[..., None] * Jz
    y = ops.affine(h, Wo, p["bo"])
    if jac_rows and not fast_jacobian:
        J = ops.chain(Wo, J)
    logvar = None
    if Wv is not None:
        logvar = _bounded_logvar(ops.affine(h, Wv, p["bv"]), p["max_logvar"], p["min_logvar"],
                                 ops)
    return y, J, logvar


def _glorot(fan_in: int, fan_out: int, gen: torch.Generator) -> torch.Tensor:
    lim = float(np.sqrt(6.0 / (fan_in + fan_out)))
    return (torch.rand(fan_in, fan_out, generator=gen, dtype=torch.float64) * 2 - 1) * lim


#: initial soft bounds of the log-variance head (normalized units; mbrl-lib's GaussianMLP)
MAX_LOGVAR_INIT, MIN_LOGVAR_INIT = 0.5, -10.0


class _StackedGroup(nn.Module):
    """Members of one depth, weights stacked along a leading member axis ``K``."""

    def __init__(
        self, specs: Sequence[MemberSpec], weights: Sequence[dict], in_dim: int, out_dim: int,
        probabilistic: bool = False,
    ) -> None:
        super().__init__()
        K = len(specs)
        depth = specs[0].depth
        W = max(s.width for s in specs)
        widths = [s.width for s in specs]
        self.depth = depth
        self.padded = any(w != W for w in widths)
        self.layer_norm = any(s.layer_norm for s in specs)
        self.probabilistic = bool(probabilistic)
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

        for layer, (w, b) in enumerate(_hidden_names(depth)):
            setattr(self, w, nn.Parameter(stacked(w, (in_dim if layer == 0 else W, W))))
            setattr(self, b, nn.Parameter(stacked(b, (1, W))))
        self.Wo = nn.Parameter(stacked("Wo", (W, out_dim)))
        self.bo = nn.Parameter(stacked("bo", (1, out_dim)))
        if self.layer_norm:
            for layer in range(1, depth + 1):
                self.register_parameter(f"ln_gain{layer}", nn.Parameter(torch.ones(K, 1, W)))
                self.register_parameter(f"ln_bias{layer}", nn.Parameter(torch.zeros(K, 1, W)))
            if not all(s.layer_norm for s in specs):
                sel = torch.tensor([float(s.layer_norm) for s in specs]).reshape(K, 1, 1)
                self.register_buffer("ln_select", sel)
        if self.probabilistic:
            self.Wv = nn.Parameter(stacked("Wv", (W, out_dim)))
            self.bv = nn.Parameter(stacked("bv", (1, out_dim)))
            self.max_logvar = nn.Parameter(torch.full((K, 1, out_dim), MAX_LOGVAR_INIT))
            self.min_logvar = nn.Parameter(torch.full((K, 1, out_dim), MIN_LOGVAR_INIT))
        if self.padded or self.layer_norm:
            mask = torch.zeros(K, 1, W)
            for k, w in enumerate(widths):
                mask[k, 0, :w] = 1.0
            self.register_buffer("mask", mask)
            width = torch.tensor(widths, dtype=torch.float32).reshape(K, 1, 1)
            self.register_buffer("width", width)
        if any(self.dropout_p):
            self.register_buffer("dropout", torch.tensor(self.dropout_p).reshape(K, 1, 1))

    @property
    def n_members(self) -> int:
        return self.W1.shape[0]

    def arrays(self) -> dict[str, torch.Tensor]:
        """Parameters and buffers by name."""
        return {**dict(self.named_parameters()), **dict(self.named_buffers())}

    def dropout_masks(self, B: int, gen: torch.Generator | None) -> list[torch.Tensor]:
        K, W = self.W1.shape[0], self.W1.shape[2]
        keep = 1.0 - self.dropout
        return [
            (torch.rand(K, B, W, generator=gen) < keep).float() / keep for _ in range(self.depth)
        ]


def _member_init(spec: MemberSpec, in_dim: int, out_dim: int, gen: torch.Generator,
                 probabilistic: bool = False) -> dict:
    """Flux-style init: glorot-uniform weights ``[fan_in, fan_out]``, zero biases; drawn in the
    order W1, W2, ..., Wo (, Wv)."""
    w = spec.width
    d = {}
    for layer, (wn, bn) in enumerate(_hidden_names(spec.depth)):
        d[wn] = _glorot(in_dim if layer == 0 else w, w, gen)
        d[bn] = torch.zeros(1, w, dtype=torch.float64)
    d["Wo"], d["bo"] = _glorot(w, out_dim, gen), torch.zeros(1, out_dim, dtype=torch.float64)
    if probabilistic:
        d["Wv"], d["bv"] = _glorot(w, out_dim, gen), torch.zeros(1, out_dim, dtype=torch.float64)
    return d


class DynamicsEnsemble(nn.Module):
    """An ensemble of K neural dynamics models ``x+ = s(x, u) + NN_k(x, u)`` computed in one
    batch (docs/models.md, "The model"): torch float32 for training, :meth:`freeze` for planning.

    :param config: the architecture, see :class:`EnsembleConfig`."""

    def __init__(self, config: EnsembleConfig) -> None:
        super().__init__()
        if not isinstance(config, EnsembleConfig):
            raise ValueError(f"config must be an EnsembleConfig, got {type(config).__name__}")
        self.config = config
        n, m = config.state_dim, config.action_dim
        self.state_dim, self.action_dim = n, m
        gen = torch.Generator().manual_seed(config.seed)
        inits = [_member_init(s, n + m, n, gen, config.probabilistic) for s in config.members]
        # stacked order: grouped by depth, activations contiguous inside a group
        order = sorted(
            range(config.n_members),
            key=lambda k: (config.members[k].depth, config.members[k].activation),
        )
        self.groups = nn.ModuleList()
        for depth in sorted({config.members[k].depth for k in order}):
            ks = [k for k in order if config.members[k].depth == depth]
            self.groups.append(_StackedGroup(
                [config.members[k] for k in ks], [inits[k] for k in ks], n + m, n,
                config.probabilistic))
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

    # ---------------------------------------------------------------- normalization
    def set_normalization(self, trajs: Trajectory | Sequence[Trajectory]) -> None:
        """Set input/output statistics from data (docs/models.md, "Normalization"): mean and
        population std of ``[x_t, u_t]`` and of the residual targets ``x_{t+1} - s(x_t, u_t)``,
        a std below ``REL_STD_FLOOR`` times the magnitude replaced by 1; with
        ``config.normalize=False`` the statistics stay identity and the model is only marked set.

        :param trajs: a :class:`~mbtsr.trajectory.Trajectory` or a list of them."""
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
        of every member absorb the change (computed in float64; predictions agree to float32
        rounding; Adam's moments are not rescaled). Unset statistics are simply set.

        :param trajs: a :class:`~mbtsr.trajectory.Trajectory` or a list of them."""
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
                if g.probabilistic:  # the variance in raw units stays: shift the log-variance
                    shift = 2.0 * torch.log(old["out_std"] / new["out_std"])
                    for p in (g.bv, g.max_logvar, g.min_logvar):
                        p.copy_(p.double() + shift)

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

    def stacked_forward(self, xu: torch.Tensor, jac_rows: int = 0, *, normalized: bool = False,
                        logvar: bool = False):
        """Internal training entry point, members in *stacked* order (``_stacked_order[i]``
        is the config index of the i-th).

        :param xu: ``[B, n+m]`` raw inputs (float32) shared by all members, or ``[K, B, n+m]``
            one batch per member (stacked order); normalized ones if ``normalized`` (see
            :meth:`normalize_inputs`).
        :param jac_rows: also return full-map Jacobians (raw units, skip included) of the mean
            at the first ``jac_rows`` points.
        :param logvar: also return the normalized log-variance ``[K, B, n]`` (probabilistic
            members; ``None`` otherwise).
        :return: ``(y_norm [K, B, n], J [K, jac_rows, n, n+m] or None)`` (and the log-variance
            with ``logvar``) where ``y_norm`` is the normalized network output (the mean),
            comparable to :meth:`normalized_residual` targets."""
        xn = xu if normalized else self.normalize_inputs(xu)

        def masks(g):
            if self.training and any(g.dropout_p):
                return g.dropout_masks(xn.shape[-2], self.dropout_generator)
            return None

        y, J, lv = _groups_forward(((g, g.arrays()) for g in self.groups), xn, _TORCH_OPS,
                                   jac_rows, masks)
        if jac_rows:
            J = self.out_std[:, None] * J / self.in_std + self.skip_J
        return (y, J, lv) if logvar else (y, J)

    def normalize_inputs(self, xu: torch.Tensor) -> torch.Tensor:
        """``([x, u] - in_mean) / in_std`` for ``xu: [..., n+m]``."""
        return (xu - self.in_mean) / self.in_std

    def normalized_residual(self, xu: torch.Tensor, x_next: torch.Tensor) -> torch.Tensor:
        """Training target of the network: ``(x+ - s(x, u) - out_mean) / out_std``, ``[B, n]``."""
        return (x_next - xu @ self.skip_J.T - self.out_mean) / self.out_std

    def _config_order(self, a: torch.Tensor) -> torch.Tensor:
        return a if self._to_config_order is None else a.index_select(0, self._to_config_order)

    def forward_torch(self, x: torch.Tensor, u: torch.Tensor | None = None) -> torch.Tensor:
        """Member predictions of the next state (float32, differentiable).

        :param x: ``[..., n]`` states, or ``[..., n+m]`` concatenated ``[x, u]`` if ``u`` is None.
        :param u: ``[..., m]`` inputs.
        :return: ``[K, ..., n]`` next states, members in config order."""
        xu = self._xu_torch(x, u)
        lead = xu.shape[:-1]
        xu2 = xu.reshape(-1, xu.shape[-1])
        y, _ = self.stacked_forward(xu2)
        nxt = xu2 @ self.skip_J.T + self.out_mean + self.out_std * y
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

    # ---------------------------------------------------------------- planning surface
    def freeze(self, precision: str = "float32") -> FrozenEnsemble:
        """An immutable copy for planning (:class:`FrozenEnsemble`): weights copied now,
        normalization folded in, no autograd.

        :param precision: ``"float32"`` or ``"float64"``: the arithmetic of the ensemble-mean
            step and Jacobians (the planning kernels; see :class:`FrozenEnsemble`).

        :raises ValueError: naming the tensor, if a weight or normalization statistic is NaN/inf
            (a diverged training run) or a normalization std is not positive."""
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
            return FrozenEnsemble(self, precision)

    # one-off numpy evaluation (metrics, tests): each call freezes a fresh float64 copy
    def step(self, x: np.ndarray, u: np.ndarray, t: int | None = None) -> np.ndarray:
        """``self.freeze("float64").step(x, u, t)``: ensemble-mean next state ``[..., n]``."""
        return self.freeze("float64").step(x, u, t)

    def member_predictions(self, x: np.ndarray, u: np.ndarray) -> np.ndarray:
        """``self.freeze("float64").member_predictions(x, u)``: ``[K, ..., n]``."""
        return self.freeze("float64").member_predictions(x, u)

    def predict(self, x: np.ndarray, u: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
        """``self.freeze("float64").predict(x, u)``: ensemble ``(mean, std)`` of the next state."""
        return self.freeze("float64").predict(x, u)

    def member_std(self, x: np.ndarray, u: np.ndarray) -> np.ndarray:
        """``self.freeze("float64").member_std(x, u)``: ``[K, ..., n]`` (probabilistic members)."""
        return self.freeze("float64").member_std(x, u)

    def member_jacobians(self, x: np.ndarray, u: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
        """``self.freeze("float64").member_jacobians(x, u)``: ``(A [K, T, n, n],
        B [K, T, n, m])``."""
        return self.freeze("float64").member_jacobians(x, u)

    def jacobians(self, x: np.ndarray, u: np.ndarray, t: int = 0) -> tuple[np.ndarray, np.ndarray]:
        """``self.freeze("float64").jacobians(x, u)``: mean ``(A [T, n, n], B [T, n, m])``."""
        return self.freeze("float64").jacobians(x, u, t)


# --------------------------------------------------------------------------------------------
# The frozen planning model: float64 numpy, normalization folded into the weights once
# --------------------------------------------------------------------------------------------


@njit(cache=True, fastmath=True, error_model="numpy", boundscheck=False, inline="always")
def _tanh_rational(z):  # pragma: no cover - compiled
    """``tanh(z)`` of a float32 number: a [7/6] rational minimax form on [-9, 9], clamped
    outside (error <= 3.3e-7; docs/ilqr.md)."""
    f = np.float32
    x = min(max(z, f(-9.0)), f(9.0))
    x2 = x * x
    p = (((((f(-2.76076847742355e-16) * x2 + f(2.00018790482477e-13)) * x2 - f(
        8.60467152213735e-11)) * x2 + f(5.12229709037114e-08)) * x2 + f(
        1.48572235717979e-05)) * x2 + f(6.37261928875436e-04)) * x2 + f(4.89352455891786e-03)
    q = ((f(1.19825839466702e-06) * x2 + f(1.18534705686654e-04)) * x2 + f(
        2.26843463243900e-03)) * x2 + f(4.89352518554385e-03)
    return p * x / q


_KERNEL_MAX_BATCH = 4  # rows up to which the compiled kernel beats numpy's batched products
_KERNEL_CODE = {"elu": 0, "tanh": 1, "sigmoid": 1, "swish": 2, "relu": 3, "leaky_relu": 4}
"""Activation codes of the compiled kernel on the folded weights (sigmoid rows run as tanh)."""
_TANH_RUN = np.array([[0, 1, 1]])  # tanh over a whole flat array (:func:`_act_runs`, scale N)


@njit(cache=True, fastmath={"contract"}, error_model="numpy", boundscheck=False)
def _act_runs(z, runs, fast, scale=1):  # pragma: no cover - compiled
    """``z[a s:b s] = act_c(z[a s:b s])`` in place for every run ``(a, b, c)`` of ``runs [R, 3]``
    (:data:`_KERNEL_CODE`), ``s = scale`` (the row length of a flattened ``[H, B]``); ``fast``:
    tanh and swish by :func:`_tanh_rational` (float32) in one vectorized loop, NaN kept; else
    scalar ``np.tanh``. In place: with two arrays that may alias, the loop would be scalar."""
    for r in range(runs.shape[0]):
        w, c = z[runs[r, 0] * scale:runs[r, 1] * scale], runs[r, 2]  # a view: vectorized loops
        if fast and (c == 1 or c == 2):
            swish = c == 2
            for h in range(w.shape[0]):
                x = w[h]
                t = _tanh_rational(x)
                t = t if x == x else x  # the clamp of _tanh_rational would hide a NaN
                w[h] = x * (t + np.float32(1.0)) if swish else t
            continue
        for h in range(w.shape[0]):
            x = w[h]
            if c == 0:
                w[h] = x if x > 0.0 else np.expm1(x)
            elif c == 1:
                w[h] = np.tanh(x)
            elif c == 2:
                w[h] = x * (np.tanh(x) + 1.0)
            elif c == 3:
                w[h] = 0.0 if x <= 0.0 else x  # NaN stays NaN (np.maximum's)
            else:
                w[h] = x if x > 0.0 else LEAKY_RELU_SLOPE * x


@njit(cache=True, fastmath={"contract"}, boundscheck=False)
def _mean_step_row(x, u, W_inT, Wh, bh, W_out, runs, fast, z, z2, out):  # pragma: no cover
    """One row of :func:`_mean_step_kernel`: ``x [n]``, ``u [m]`` -> ``out [n]`` (``z, z2 [H]``
    scratch in the planning precision). Layer 1 of all members is one ``[1+n+m, H]`` product;
    deeper layers are block-diagonal (one ``W x W`` block per member); the output weights hold
    the mean. Every inner loop is an axpy over contiguous weights (vectorized)."""
    n, m, H = x.shape[0], u.shape[0], W_inT.shape[1]
    L, K, W = Wh.shape[0], Wh.shape[1], Wh.shape[2]
    z[:] = W_inT[0]
    for i in range(n + m):
        xi = z.dtype.type(x[i] if i < n else u[i - n])
        row = W_inT[1 + i]  # views: indices known >= 0, the loops vectorize
        for h in range(H):
            z[h] += xi * row[h]
    _act_runs(z, runs, fast)
    for layer in range(L):
        for k in range(K):
            zk, yk, Wk = z[k * W:(k + 1) * W], z2[k * W:(k + 1) * W], Wh[layer, k]
            yk[:] = bh[layer, k]
            for i in range(W):
                a, row = zk[i], Wk[i]
                for j in range(W):
                    yk[j] += a * row[j]
        _act_runs(z2, runs, fast)
        z, z2 = z2, z
    out[:] = W_out[H]
    for i in range(n + m):
        xi = x[i] if i < n else u[i - n]
        row = W_out[H + 1 + i]
        for o in range(n):
            out[o] += xi * row[o]
    for h in range(H):
        a, row = z[h], W_out[h]
        for o in range(n):
            out[o] += a * row[o]


@njit(cache=True)
def _mean_step_kernel(x, u, W_inT, Wh, bh, W_out, runs, fast, out):  # pragma: no cover
    """Compiled ensemble-mean step on the folded weights of :func:`_mean_step_plan`:
    ``x [B, n]``, ``u [B, m]``, ``W_inT [1+n+m, H]``, ``Wh [depth-1, K, W, W]``,
    ``bh [depth-1, K, W]``, ``W_out [H+1+n+m, n]``, activation ``runs [R, 3]``
    (:func:`_act_runs`) -> ``out [B, n]``. The arithmetic of the numpy path, one row at a time,
    without numpy's per-call overhead."""
    z = np.empty_like(W_inT[0])
    z2 = np.empty_like(W_inT[0])
    for b in range(x.shape[0]):
        _mean_step_row(x[b], u[b], W_inT, Wh, bh, W_out, runs, fast, z, z2, out[b])
    return out


@njit(cache=True)
def _rollout_policy_kernel(W_inT, Wh, bh, W_out, runs, fast, x0, X, U, k, K, alphas, lower,
                           upper, max_norm):  # pragma: no cover - compiled
    """Closed-loop rollouts of the frozen ensemble-mean model for all step sizes, in one
    compiled call: ``u_t = clip(U_t + alpha k_t + K_t (x_t - X_t), lower, upper)``;
    ``X: [T+1, n]``, ``U, k: [T, m]``, ``K: [T, m, n]``, ``alphas: [N]`` ->
    ``(Xn [N, T+1, n], Un [N, T, m], alive [N])``, the semantics of
    ``mbtsr.ilqr._rollout_policy`` (a row that turns non-finite is dead and continues from the
    nominal state; rows exceeding ``max_norm`` are dead at the end)."""
    T, m = U.shape
    Xn, Un, alive = rollout_buffers(x0, T, m, alphas.shape[0])
    z = np.empty_like(W_inT[0])
    z2 = np.empty_like(W_inT[0])
    for a in range(alphas.shape[0]):
        biggest = 0.0
        for i in range(x0.shape[0]):
            biggest = max(biggest, abs(x0[i]))
        for t in range(T):
            policy_row(U, k, K, X, t, alphas[a], lower, upper, Xn[a, t], Un[a, t])
            _mean_step_row(Xn[a, t], Un[a, t], W_inT, Wh, bh, W_out, runs, fast, z, z2,
                           Xn[a, t + 1])
            finite, biggest = guard_row(Xn[a, t + 1], X[t + 1], biggest)
            alive[a] &= finite
        if not biggest <= max_norm:
            alive[a] = False
    return Xn, Un, alive


def _plan_hidden(plan: SimpleNamespace, z: np.ndarray, h: np.ndarray) -> np.ndarray:
    """The hidden layers of a folded plan (:func:`_mean_step_plan`) in numpy, hidden-major
    layout: first-layer pre-activations ``z [H, B]`` (a fresh array: activated in place) -> the
    last layer's activations, written into ``h [H, B]`` (C-contiguous; returned)."""
    H, B = z.shape
    assert z.flags.c_contiguous and h.flags.c_contiguous  # reshape(-1) must be a view
    fast, depth = z.dtype == np.float32, plan.Wh.shape[0]
    for layer in range(depth + 1):
        if layer:
            z = np.matmul(plan.WhT_f[layer - 1], z.reshape(plan.K, plan.W, B),
                          out=h.reshape(plan.K, plan.W, B) if layer == depth else None)
            z += plan.bhT[layer - 1]
        _act_runs(z.reshape(-1), plan.kernel_runs, fast, B)
    if not depth:
        h[...] = z
    return h


def _mean_step_plan(runs, hidden: list[tuple[np.ndarray, np.ndarray]], Wo: np.ndarray,
                    bo: np.ndarray, skip_J: np.ndarray, n_members: int,
                    head: tuple[np.ndarray, np.ndarray] | None = None,
                    dtype: type = np.float64) -> SimpleNamespace:
    """Folded weights of the ensemble-mean step of ONE depth group without layer norm
    (docs/models.md, "The frozen ensemble-mean step"); the unfolded ones of
    :func:`_plan_jacobians`; per-member folded output layers (and ``head = (Wv, bv)``) for
    trajectory sampling. Mean-step and Jacobian arrays in ``dtype``, per-member ones float64.

    ``hidden = [(W1 [K, n+m, W], b1 [K, W]), (W2 [K, W, W], b2 [K, W]), ...]``, ``Wo [K, W, n]``,
    ``bo [K, n]`` already hold the normalization (raw units in and out) and zero padded units;
    ``runs`` are the members' activations ``(name, first, stop)``. With ``H = K*W`` one buffer
    ``G = [h; 1; x^T; u^T]: [H+1+n+m, B]`` carries a step, ``W_out = [Wo / K; mean bo; skip_J^T]``.
    """
    W1, b1 = hidden[0]
    K, _, W = W1.shape
    H, n = K * W, Wo.shape[2]
    acts = [name for name, a, b in runs for _ in range(a, b)]  # per member
    half = np.array([0.5 if a in ("sigmoid", "swish") else 1.0 for a in acts])
    sig = np.array([a == "sigmoid" for a in acts])
    folded = []
    for layer, (Wl, bl) in enumerate(hidden):
        Wl, bl = Wl.copy(), bl.copy()
        if layer:  # consumes the previous layer's sigmoid rows: h = 0.5 t + 0.5
            bl[sig] += 0.5 * Wl[sig].sum(1)
            Wl[sig] *= 0.5
        folded.append((Wl * half[:, None, None], bl * half[:, None]))
    Wo_mean, bo_mean = Wo / n_members, bo.sum(0) / n_members
    Wo_f = Wo_mean.copy()
    bo_f = bo_mean + 0.5 * Wo_mean[sig].sum((0, 1))
    Wo_f[sig] *= 0.5

    def per_member(W: np.ndarray, b: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
        W, b = W.copy(), b + 0.5 * np.where(sig[:, None], W.sum(1), 0.0)
        W[sig] *= 0.5
        return W, b

    Wo_m, bo_m = per_member(Wo, bo)
    Wv_m, bv_m = per_member(*head) if head is not None else (None, None)
    deep = folded[1:]
    Wh = np.stack([w for w, _ in deep]) if deep else np.zeros((0, K, W, W))
    bh = np.stack([b for _, b in deep]) if deep else np.zeros((0, K, W))
    W_inT = np.concatenate([folded[0][1].reshape(1, H),
                            folded[0][0].transpose(1, 0, 2).reshape(-1, H)], 0)
    kernel_runs: list[list[int]] = []  # rows [a, b) of activation code c, consecutive ones merged
    for name, a, b in runs:
        if kernel_runs and kernel_runs[-1][2] == _KERNEL_CODE[name]:
            kernel_runs[-1][1] = b * W
        else:
            kernel_runs.append([a * W, b * W, _KERNEL_CODE[name]])
    M = None
    if len(hidden) == 1:  # mean Jacobian J[b, (o, i)] = sum_h act'(z[h, b]) M[h, (o, i)]
        M = (Wo[:, :, :, None] * W1.swapaxes(1, 2)[:, :, None, :]).reshape(H, -1) / n_members
    ro = _readonly

    def rd(a: np.ndarray) -> np.ndarray:  # the planning precision
        return _readonly(a, dtype)

    W_out = np.concatenate([Wo_f.reshape(H, n), bo_f[None], skip_J.T], 0)
    return SimpleNamespace(
        K=K, W=W, H=H, dtype=dtype, fast=dtype == np.float32,
        kernel_runs=ro(np.array(kernel_runs, np.int64)),
        # folded (the step): kernel layout and numpy layout
        W_inT=rd(W_inT), W_in=rd(W_inT.T), Wh=rd(Wh), WhT_f=rd(Wh.swapaxes(-1, -2)),
        bh=rd(bh), bhT=rd(bh[..., None]), W_out=rd(W_out), W_outT=rd(W_out.T),
        # folded, per member (trajectory sampling)
        W1fT=ro(folded[0][0].swapaxes(1, 2)), b1f=ro(folded[0][1][..., None]),
        Wo_m=ro(Wo_m), bo_m=ro(bo_m[:, None]),
        Wv_m=None if Wv_m is None else ro(Wv_m), bv_m=None if bv_m is None else ro(bv_m[:, None]),
        # unfolded (the Jacobians)
        W1T_cat=rd(W1.transpose(0, 2, 1).reshape(H, -1)), b1=rd(b1.reshape(H, 1)),
        WhT=rd(np.stack([w for w, _ in hidden[1:]]).swapaxes(-1, -2) if deep else Wh),
        bh_u=rd(np.stack([b for _, b in hidden[1:]])[..., None] if deep else bh[..., None]),
        W1T=rd(W1.swapaxes(1, 2)), WoT_mean=rd(Wo_mean.swapaxes(1, 2)),
        M=None if M is None else rd(M), member_runs=tuple(runs),
        row_runs=tuple((name, a * W, b * W) for name, a, b in runs),
    )


def _value_and_derivative(z: np.ndarray, name: str) -> tuple[np.ndarray, np.ndarray]:
    """``(act(z), act'(z))``; sigmoid and swish through the compiled tanh of :func:`_act_runs`
    (``sigmoid(z) = 0.5 tanh(z/2) + 0.5``): in float32 far faster than scipy's ``expit``."""
    if name in ("sigmoid", "swish"):
        s = 0.5 * z
        _act_runs(s.reshape(-1), _TANH_RUN, s.dtype == np.float32, s.size)
        s *= 0.5
        s += 0.5
        if name == "sigmoid":
            return s, s * (1.0 - s)
        return z * s, s * (1.0 + z * (1.0 - s))
    _, value, derivative = ACTIVATIONS[name]
    a = value(z)
    return a, derivative(z, a, np)


def _plan_jacobians(plan: SimpleNamespace, xu: np.ndarray, n: int) -> np.ndarray:
    """Ensemble-mean Jacobian ``[T, n, n+m]`` of the network part at ``xu [T, n+m]``: depth 1
    ``act'(z)^T @ M``, deeper reverse mode (docs/models.md, "The frozen ensemble-mean step")."""
    (T, p), K, W = xu.shape, plan.K, plan.W
    z = plan.W1T_cat @ xu.T.astype(plan.dtype) + plan.b1  # [H, T], member k in rows k*W:(k+1)*W
    a, d = np.empty_like(z), np.empty_like(z)
    for name, r0, r1 in plan.row_runs:
        a[r0:r1], d[r0:r1] = _value_and_derivative(z[r0:r1], name)
    if plan.M is not None:
        return (d.T @ plan.M).reshape(T, n, p).astype(np.float64)
    ds = [d.reshape(K, W, T)]
    h = a.reshape(K, W, T)
    for layer in range(plan.WhT.shape[0]):
        z = plan.WhT[layer] @ h + plan.bh_u[layer]  # [K, W, T]
        h, d = np.empty_like(z), np.empty_like(z)
        for name, k0, k1 in plan.member_runs:
            h[k0:k1], d[k0:k1] = _value_and_derivative(z[k0:k1], name)
        ds.append(d)
    ds = [np.ascontiguousarray(d.swapaxes(1, 2)) for d in ds]  # [K, T, W]: contiguous over W
    R = plan.WoT_mean[:, None] * ds[-1][:, :, None, :]  # [K, T, n, W] in C order: views below
    for layer in range(plan.WhT.shape[0] - 1, -1, -1):
        R = (R.reshape(K, T * n, W) @ plan.WhT[layer]).reshape(K, T, n, W)
        R *= ds[layer][:, :, None, :]
    return (R.reshape(K, T * n, W) @ plan.W1T).sum(0, dtype=np.float64).reshape(T, n, p)


def _readonly(a: np.ndarray, dtype: type = np.float64) -> np.ndarray:
    a = np.ascontiguousarray(a, dtype=dtype)
    a.setflags(write=False)
    return a


class FrozenEnsemble:
    """An immutable numpy copy of a :class:`DynamicsEnsemble` made by
    :meth:`DynamicsEnsemble.freeze`, the model planning uses: the
    :class:`mbtsr.dynamics.DynamicsModel` protocol plus the member spread, members in config
    order (docs/models.md, "The model"). ``precision`` is the arithmetic of the folded step,
    rollouts and Jacobians; inputs and results stay float64 (docs/ilqr.md, "Planning at the
    control rate"). ``_step`` is the unchecked kernel solver loops call (:mod:`mbtsr.dynamics`)."""

    def __init__(self, ensemble: DynamicsEnsemble, precision: str = "float32") -> None:
        check_choice("precision", precision, PRECISIONS)
        n, m = ensemble.state_dim, ensemble.action_dim
        stats = {k: getattr(ensemble, k).detach().double().numpy().copy()
                 for k in ("in_mean", "in_std", "out_mean", "out_std")}
        in_mean, in_std = stats["in_mean"], stats["in_std"]
        out_mean, out_std = stats["out_mean"], stats["out_std"]
        skip_J = ensemble.config.skip_jacobian()
        groups = []
        for g in ensemble.groups:
            p = {k: v.detach().double().numpy().copy() for k, v in g.arrays().items()}
            if g.padded:
                p = _zero_padded(p, g.depth, lambda a: a.swapaxes(-1, -2))
            # ((xu - in_mean) / in_std) @ W1 + b1 = xu @ (W1 / in_std) + (b1 - (in_mean/in_std) W1)
            p["b1"] = p["b1"] - ((in_mean / in_std) @ p["W1"])[:, None, :]
            p["W1"] = p["W1"] / in_std[None, :, None]
            # out_mean + out_std * (h @ Wo + bo); the log-variance stays normalized
            p["Wo"] = p["Wo"] * out_std
            p["bo"] = p["bo"] * out_std + out_mean
            static = SimpleNamespace(depth=g.depth, runs=list(g.runs), layer_norm=g.layer_norm,
                                     padded=False, probabilistic=g.probabilistic)
            groups.append((static, {k: _readonly(v) for k, v in p.items()}))
        plan = None
        if len(groups) == 1 and not groups[0][0].layer_norm:
            static, p = groups[0]
            plan = _mean_step_plan(static.runs,
                                   [(p[w], p[b][:, 0]) for w, b in _hidden_names(static.depth)],
                                   p["Wo"], p["bo"][:, 0], skip_J, ensemble.n_members,
                                   head=(p["Wv"], p["bv"][:, 0]) if "Wv" in p else None,
                                   dtype=PRECISIONS[precision])
        perm = None if ensemble._to_config_order is None else ensemble._to_config_order.numpy()
        for name, value in (
            ("config", ensemble.config), ("state_dim", n), ("action_dim", m),
            ("n_members", ensemble.n_members), ("_groups", tuple(groups)),
            ("_skip_J", _readonly(skip_J)), ("_perm", perm), ("_plan", plan),
            ("_order", None if perm is None else np.argsort(perm)),
            ("_out_std", _readonly(out_std)), ("probabilistic", ensemble.config.probabilistic),
            ("precision", precision),
        ):
            object.__setattr__(self, name, value)

    def __setattr__(self, name: str, value: object) -> None:
        raise AttributeError(f"a FrozenEnsemble is immutable (tried to set {name!r})")

    def __repr__(self) -> str:
        return (f"FrozenEnsemble(state_dim={self.state_dim}, action_dim={self.action_dim}, "
                f"n_members={self.n_members}, precision={self.precision!r})")

    @property
    def kernel_rows(self) -> int:
        """Batches up to this many rows run the compiled kernel (0 without the folded plan):
        measured on Reacher- to Pusher-sized members, it beats numpy's batched products up
        to 4 rows (docs/ilqr.md)."""
        return 0 if self._plan is None else _KERNEL_MAX_BATCH

    # ---------------------------------------------------------------- kernels (no checks)
    def _members(self, xu: np.ndarray, jac_rows: int, logvar: bool = False):
        """``xu [B, n+m]`` (shared) or ``[K, B, n+m]`` (one batch per member, config order) ->
        ``(x_next [K, B, n], J [K, jac_rows, n, n+m] or None, logvar [K, B, n] or None)`` in
        config order, skip parts included, the log-variance in normalized units."""
        if xu.ndim == 3 and self._order is not None:
            xu = xu[self._order]  # stacked order
        y, J, lv = _groups_forward(self._groups, xu, _NUMPY_OPS, jac_rows)
        y = y + xu @ self._skip_J.T
        if jac_rows:
            J = J + self._skip_J
        if not logvar:
            lv = None
        if self._perm is not None:
            y = y[self._perm]
            J = None if J is None else J[self._perm]
            lv = None if lv is None else lv[self._perm]
        return y, J, lv

    def _step(self, x: np.ndarray, u: np.ndarray, t: int | None = None) -> np.ndarray:
        """:meth:`step` on float64 arrays ``x [..., n]``, ``u [..., m]`` known to be valid."""
        n, m = self.state_dim, self.action_dim
        lead = x.shape[:-1]
        B = x.size // n
        plan = self._plan
        if plan is None:
            y, _, _ = self._members(np.concatenate([x.reshape(B, n), u.reshape(B, m)], 1), 0)
            return y.mean(0).reshape(*lead, n)
        x, u = x.reshape(B, n), u.reshape(B, m)
        if B > self.kernel_rows:  # numpy's BLAS and vectorized activations win on larger work
            return self._step_numpy(x, u).reshape(*lead, n)
        out = np.empty((B, n))
        _mean_step_kernel(x, u, plan.W_inT, plan.Wh, plan.bh, plan.W_out, plan.kernel_runs,
                          plan.fast, out)
        return out.reshape(*lead, n)

    @property
    def line_search_chunks(self) -> tuple[int, ...] | None:
        """Where iLQR's chunks of step sizes start (:mod:`mbtsr.ilqr`): 2, 2, 3, rest (each of
        up to :attr:`kernel_rows` rows one call of the compiled rollout kernel)."""
        return None if self._plan is None else LINE_SEARCH_CHUNKS

    def _rollout_policy(self, x0, X, U, k, K, alphas, lower, upper, max_norm):
        """iLQR's line-search rollouts in one compiled call (:func:`_rollout_policy_kernel`;
        arguments as ``mbtsr.ilqr._rollout_policy`` without ``t0``), or ``None`` (no folded plan,
        or more step sizes than ``kernel_rows``: the solver steps the model, batched)."""
        plan = self._plan
        if plan is None or alphas.shape[0] > self.kernel_rows:
            return None
        return _rollout_policy_kernel(plan.W_inT, plan.Wh, plan.bh, plan.W_out, plan.kernel_runs,
                                      plan.fast, x0, X, U, k, K, alphas, lower, upper,
                                      float(max_norm))

    def _rollout_open_loop(self, x0: np.ndarray, U: np.ndarray, max_norm: float
                           ) -> tuple[np.ndarray, np.ndarray] | None:
        """Open-loop rollouts of the ensemble mean, the batched kernel of CEM: ``x0 [n]``,
        ``U [S, T, m]`` -> ``(X [S, T+1, n], alive [S])`` with the semantics of
        :func:`mbtsr.dynamics._rollout`, in the planning precision in one buffer per step
        (:func:`_mean_step_plan`). ``None`` (the caller steps the model) without the folded
        plan or for batches of the compiled kernel (``<= kernel_rows``)."""
        plan = self._plan
        S, T, m = U.shape
        if plan is None or S <= self.kernel_rows:
            return None
        n, H = self.state_dim, plan.H
        G = np.empty((T + 1, H + 1 + n + m, S), plan.dtype)  # one buffer per time step
        G[:, H] = 1.0
        G[0, H + 1:H + 1 + n] = x0[:, None]
        G[:T, H + 1 + n:] = U.transpose(1, 2, 0)
        with np.errstate(all="ignore"):
            for t in range(T):
                _plan_hidden(plan, plan.W_in @ G[t, H:], G[t, :H])
                np.matmul(plan.W_outT, G[t], out=G[t + 1, H + 1:H + 1 + n])
            X = G[:, H + 1:H + 1 + n].transpose(2, 0, 1).astype(np.float64)  # [S, T+1, n]
            dead = ~(np.abs(X[:, 1:]).max(-1) < max_norm)  # NaN compares false
        if dead.any():
            dead = np.logical_or.accumulate(dead, axis=1)
            X[:, 1:][dead] = np.nan
            return X, ~dead[:, -1]
        return X, np.ones(S, dtype=bool)

    def _step_numpy(self, x: np.ndarray, u: np.ndarray) -> np.ndarray:
        """The ensemble-mean step of the folded plan in numpy (the compiled kernel's reference;
        ``x [B, n]``, ``u [B, m]`` -> ``[B, n]``): one product per layer for all members, in
        the hidden-major layout of :func:`_mean_step_plan` (contiguous rows per activation)."""
        n, plan = self.state_dim, self._plan
        B, H = x.shape[0], plan.H
        G = np.empty((H + 1 + n + self.action_dim, B), plan.dtype)
        G[H] = 1.0
        G[H + 1:H + 1 + n] = x.T
        G[H + 1 + n:] = u.T
        _plan_hidden(plan, plan.W_in @ G[H:], G[:H])
        return (plan.W_outT @ G).T.astype(np.float64)

    def _member_rows(self, xu: np.ndarray) -> tuple[np.ndarray, np.ndarray | None]:
        """Row ``r`` of ``xu [B, n+m]`` through member ``r mod K`` only (trajectory sampling):
        ``(next state [B, n], aleatoric std [B, n] or None)``; one batched product per layer
        for all members, each on its own rows."""
        B, K, n = xu.shape[0], self.n_members, self.state_dim
        b = -(-B // K)
        if b * K != B:
            xu = np.concatenate([xu, np.zeros((b * K - B, xu.shape[1]))])
        xk = xu.reshape(b, K, -1).swapaxes(0, 1)  # [K, b, n+m]: member k's rows
        if self._plan is None:
            y, _, lv = self._members(xk, 0, logvar=True)
        else:
            y, lv = self._member_rows_plan(xk)
        y = y.swapaxes(0, 1).reshape(b * K, n)[:B]
        if lv is None:
            return y, None
        return y, self._out_std * np.exp(0.5 * lv.swapaxes(0, 1).reshape(b * K, n)[:B])

    def _member_rows_plan(self, xk: np.ndarray, logvar: bool = True
                          ) -> tuple[np.ndarray, np.ndarray | None]:
        """Each member on its own rows with the folded plan: ``xk [K, b, n+m]`` (config order)
        -> ``(x_next [K, b, n], normalized logvar [K, b, n] or None)``; hidden-major layout,
        one batched product per layer (the log-variance head only with ``logvar``)."""
        plan, K = self._plan, self.n_members
        if self._order is not None:
            xk = xk[self._order]  # stacked order
        b, W, H = xk.shape[1], plan.W, plan.H
        h = _plan_hidden(plan, (plan.W1fT @ xk.swapaxes(1, 2) + plan.b1f).reshape(H, b),
                         np.empty((H, b)))
        hk = h.reshape(K, W, b).swapaxes(1, 2)  # [K, b, W]
        y = hk @ plan.Wo_m + plan.bo_m + xk @ self._skip_J.T
        lv = None
        if logvar and plan.Wv_m is not None:
            g = self._groups[0][1]
            lv = _bounded_logvar(hk @ plan.Wv_m + plan.bv_m, g["max_logvar"], g["min_logvar"],
                                 _NUMPY_OPS)
        if self._perm is not None:
            y = y[self._perm]
            lv = None if lv is None else lv[self._perm]
        return y, lv

    # ---------------------------------------------------------------- public surface
    def step(self, x: np.ndarray, u: np.ndarray, t: int | None = None) -> np.ndarray:
        """Ensemble-mean next state: ``x: [..., n]``, ``u: [..., m]`` -> ``[..., n]`` (float64,
        a fresh array). ``t`` is ignored (time-invariant)."""
        x, u = check_step_inputs(x, u, self.state_dim, self.action_dim)
        with np.errstate(over="ignore"):  # saturating activations are exact in the limit
            return self._step(x, u, t)

    def member_predictions(self, x: np.ndarray, u: np.ndarray) -> np.ndarray:
        """Next state (the mean of a probabilistic member) of every member: ``x: [..., n]``,
        ``u: [..., m]`` -> ``[K, ..., n]``."""
        return self._member_outputs(x, u, std=False)[0]

    def member_std(self, x: np.ndarray, u: np.ndarray) -> np.ndarray:
        """Aleatoric std of every probabilistic member's prediction (``out_std *
        exp(logvar / 2)``, raw units): ``x: [..., n]``, ``u: [..., m]`` -> ``[K, ..., n]``.

        :raises ValueError: for deterministic members."""
        if not self.probabilistic:
            raise ValueError("member_std needs probabilistic members "
                             "(EnsembleConfig(probabilistic=True))")
        return self._member_outputs(x, u)[1]

    def _member_outputs(self, x, u, std: bool = True) -> tuple[np.ndarray, np.ndarray | None]:
        """``(means [K, ..., n], stds [K, ..., n] or None)``; the log-variance head runs only
        for ``std`` with probabilistic members."""
        x, u = check_step_inputs(x, u, self.state_dim, self.action_dim)
        lead = x.shape[:-1]
        xu = np.concatenate([x, u], -1).reshape(-1, self.state_dim + self.action_dim)
        logvar = std and self.probabilistic
        with np.errstate(over="ignore"):
            if self._plan is None:
                y, _, lv = self._members(xu, 0, logvar=logvar)
            else:  # every member on every row: one batched product per layer
                y, lv = self._member_rows_plan(np.broadcast_to(xu, (self.n_members, *xu.shape)),
                                               logvar)
        shape = (self.n_members, *lead, self.state_dim)
        std = None if lv is None else (self._out_std * np.exp(0.5 * lv)).reshape(shape)
        return y.reshape(shape), std

    def disagreement(self, x: np.ndarray, u: np.ndarray) -> np.ndarray:
        """Member disagreement, the exploration bonus of :class:`mbtsr.cem.CEMOptions`
        ``explore_weight``: the variance over members of their predictions (means), in units
        of the output scale, averaged over coordinates. ``x: [..., n]``, ``u: [..., m]`` ->
        ``[...]`` (0 for a single member)."""
        return (self.member_predictions(x, u).var(0) / self._out_std**2).mean(-1)

    def predict(self, x: np.ndarray, u: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
        """Ensemble mean and spread (population std over members, ``ddof=0``) of the next state.

        :return: ``(mean [..., n], std [..., n])``; the std is 0 for a single member."""
        preds = self.member_predictions(x, u)
        return preds.mean(0), preds.std(0)

    def member_jacobians(self, x: np.ndarray, u: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
        """Full-map Jacobians of every member (skip part included), one batched call.

        :param x: ``[T, n]`` states.  :param u: ``[T, m]`` inputs.
        :return: ``(A [K, T, n, n], B [K, T, n, m])``."""
        xu = self._points(x, u)
        with np.errstate(over="ignore"):
            _, J, _ = self._members(xu, xu.shape[0])
        return J[..., :self.state_dim], J[..., self.state_dim:]

    def _points(self, x: np.ndarray, u: np.ndarray) -> np.ndarray:
        """Checked ``x [T, n]``, ``u [T, m]`` as ``xu [T, n+m]``."""
        x = as_array("x", x, (None, self.state_dim))
        return np.concatenate([x, as_array("u", u, (x.shape[0], self.action_dim))], -1)

    def jacobians(self, x: np.ndarray, u: np.ndarray, t: int = 0) -> tuple[np.ndarray, np.ndarray]:
        """Ensemble-mean Jacobians of the full map: ``x: [T, n]``, ``u: [T, m]`` ->
        ``(A [T, n, n], B [T, n, m])`` (paper Eq. (jacerr) averages exactly these)."""
        plan = self._plan
        if plan is None:
            A, B = self.member_jacobians(x, u)
            return A.mean(0), B.mean(0)
        n = self.state_dim
        with np.errstate(over="ignore"):
            J = _plan_jacobians(plan, self._points(x, u), n) + self._skip_J
        return J[..., :n], J[..., n:]

    def trajectory_sampling(self, seed: int = 0, noise: bool = True) -> TrajectorySampling:
        """The planning-model view for CEM with trajectory sampling (PETS' TS-inf): its batched
        ``step`` sends row ``r`` to member ``r mod K`` (see :class:`TrajectorySampling`)."""
        return TrajectorySampling(self, seed=seed, noise=noise)


class TrajectorySampling:
    """Trajectory sampling on a :class:`FrozenEnsemble` (PETS' TS-inf): a planning-model view
    whose batched :meth:`step` sends row ``r`` to member ``r mod K``; probabilistic members with
    ``noise`` add ``std * eps``, ``eps`` from ``default_rng([seed, t])`` (``t`` 0 when None).
    No Jacobians (docs/models.md, "Planning with the ensemble").

    :param frozen: the frozen ensemble.
    :param seed: seed of the aleatoric noise (an int >= 0).
    :param noise: sample the noise of probabilistic members (``False``: each particle follows
        its member's mean; deterministic members have no noise)."""

    def __init__(self, frozen: FrozenEnsemble, seed: int = 0, noise: bool = True) -> None:
        if not isinstance(frozen, FrozenEnsemble):
            raise ValueError(f"frozen must be a FrozenEnsemble, got {type(frozen).__name__}")
        check_int("seed", seed, 0)
        check_bool("noise", noise)
        for name, value in (("frozen", frozen), ("state_dim", frozen.state_dim),
                            ("action_dim", frozen.action_dim), ("n_members", frozen.n_members),
                            ("seed", int(seed)), ("noise", bool(noise) and frozen.probabilistic)):
            object.__setattr__(self, name, value)

    def __setattr__(self, name: str, value: object) -> None:
        raise AttributeError(f"a TrajectorySampling view is immutable (tried to set {name!r})")

    def __repr__(self) -> str:
        return (f"TrajectorySampling({self.frozen!r}, seed={self.seed}, noise={self.noise})")

    def _step(self, x: np.ndarray, u: np.ndarray, t: int | None = None) -> np.ndarray:
        """:meth:`step` without input checks."""
        n, m = self.state_dim, self.action_dim
        lead = x.shape[:-1]
        B = x.size // n
        y, std = self.frozen._member_rows(np.concatenate([x.reshape(B, n), u.reshape(B, m)], 1))
        if self.noise:
            rng = np.random.default_rng([self.seed, 0 if t is None else int(t)])
            y += std * rng.standard_normal(y.shape)
        return y.reshape(*lead, n)

    def step(self, x: np.ndarray, u: np.ndarray, t: int | None = None) -> np.ndarray:
        """Next state of row ``r`` under member ``r mod K`` (rows of the flattened batch):
        ``x: [..., n]``, ``u: [..., m]`` -> ``[..., n]``; ``t`` keys the noise."""
        x, u = check_step_inputs(x, u, self.state_dim, self.action_dim)
        if t is not None:
            check_int("t", t, 0)
        with np.errstate(over="ignore"):
            return self._step(x, u, t)

    def disagreement(self, x: np.ndarray, u: np.ndarray) -> np.ndarray:
        """The ensemble's :meth:`FrozenEnsemble.disagreement` (all members on every row)."""
        return self.frozen.disagreement(x, u)

    def member_predictions(self, x: np.ndarray, u: np.ndarray) -> np.ndarray:
        """The ensemble's :meth:`FrozenEnsemble.member_predictions` (all members on every
        row, their means)."""
        return self.frozen.member_predictions(x, u)

    def jacobians(self, x: np.ndarray, u: np.ndarray, t: int = 0):
        """Not defined for trajectory sampling: raises ``TypeError``."""
        raise TypeError("TrajectorySampling has no Jacobians: plan with a sampling planner "
                        "(CEM), or use the FrozenEnsemble itself (the ensemble mean) for iLQR")


def _pool_transitions(trajs, n: int, m: int) -> tuple[np.ndarray, np.ndarray]:
    """All transitions of ``trajs`` as ``xu [N, n+m]`` and ``x_next [N, n]`` (float64)."""
    trajs = as_trajectory_list(trajs, dims=(n, m))
    xu = np.concatenate([np.concatenate([tr.x[:-1], tr.u], 1) for tr in trajs])
    x_next = np.concatenate([tr.x[1:] for tr in trajs])
    return xu, x_next


# --------------------------------------------------------------------------------------------
# Save / load without pickle
# --------------------------------------------------------------------------------------------

_FORMAT = "mbtsr.DynamicsEnsemble"
_FORMAT_VERSION = 2  # 2: checksummed file (mbtsr.fileformat); the kind in its header


def save_model(model: DynamicsEnsemble, path: str | os.PathLike) -> None:
    """Save weights, normalization statistics and config (as JSON text) with ``torch.save``.

    Written atomically with a format version and a content checksum
    (:func:`mbtsr.fileformat.torch_save_verified`). Load with :func:`load_model`, which checks
    both and uses ``torch.load(weights_only=True)``: no arbitrary objects are unpickled."""
    if not isinstance(model, DynamicsEnsemble):
        raise ValueError(f"model must be a DynamicsEnsemble, got {type(model).__name__}")
    payload = {  # format and version also in the payload: readers before the header had them
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
        the saved config."""
    payload, _ = torch_load_verified(path, kind=_FORMAT, versions=(_FORMAT_VERSION,),
                                     what=f"a saved {_FORMAT}")
    try:  # the header named the kind: what is left to go wrong is the content
        model = DynamicsEnsemble(EnsembleConfig.from_json(payload["config"]))
        model.load_state_dict(payload["state_dict"])
    except (KeyError, TypeError, ValueError, RuntimeError) as err:
        raise CheckpointError(
            f"{path}: the saved weights do not fit the saved config ({type(err).__name__}: "
            f"{str(err).splitlines()[0]})") from None
    return model.eval()
