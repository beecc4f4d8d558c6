"""Tests of mbtsr.ensemble against independent computations.

References: central finite differences of the float64 prediction path, torch autograd
(``torch.autograd.functional.jacobian``) of the float32 path, and a plain per-member torch MLP
written here from ``nn.functional`` primitives (one module per member, a Python loop).
"""

import dataclasses
import json
from fractions import Fraction

import numpy as np
import pytest
import torch
from hypothesis import given, settings
from hypothesis import strategies as st
from torch.nn import functional as F  # noqa: N812

from mbtsr import DynamicsModel, Trajectory
from mbtsr.ensemble import (
    ACTIVATIONS,
    FORMULATIONS,
    DynamicsEnsemble,
    EnsembleConfig,
    MemberSpec,
    ModelConfig,
    load_model,
    save_model,
)
from mbtsr.fileformat import torch_save_verified

torch.set_num_threads(1)

N_STATE, N_INPUT = 3, 2


def formulation_kwargs(formulation, n=N_STATE, m=N_INPUT, seed=0):
    rng = np.random.default_rng(seed)
    if formulation == "nominal":
        return {"A0": rng.normal(size=(n, n)), "B0": rng.normal(size=(n, m))}
    if formulation == "scaled":
        return {"tau": tuple(rng.uniform(0.5, 1.2, size=n))}
    return {}


def random_trajectory(T, n, m, seed, scale_x=3.0, scale_u=2.0):
    rng = np.random.default_rng(seed)
    x = rng.normal(size=(T + 1, n)) * scale_x + 1.0
    return Trajectory(x, rng.normal(size=(T, m)) * scale_u)


def make_model(members, formulation="g", seed=0, perturb=0.3, normalize=True, **kw):
    """An ensemble with data-set normalization and randomised biases/gains (so no derivative is
    trivially zero or one)."""
    kw = {**formulation_kwargs(formulation), **kw}
    cfg = EnsembleConfig(N_STATE, N_INPUT, members=tuple(members), formulation=formulation,
                         normalize=normalize, seed=seed, **kw)
    model = DynamicsEnsemble(cfg)
    model.set_normalization([random_trajectory(30, N_STATE, N_INPUT, seed + 1)])
    gen = torch.Generator().manual_seed(seed + 2)
    with torch.no_grad():
        for p in model.parameters():
            p.add_(perturb * torch.randn(p.shape, generator=gen))
    return model


def finite_difference_jacobians(model, x, u, eps=1e-6):
    """Central differences of every member's float64 prediction: ``[K, T, n, n+m]``."""
    n = x.shape[1]
    cols = []
    for j in range(n + u.shape[1]):
        e = np.zeros(n + u.shape[1])
        e[j] = eps
        plus = model.member_predictions(x + e[:n], u + e[n:])
        minus = model.member_predictions(x - e[:n], u - e[n:])
        cols.append((plus - minus) / (2 * eps))
    return np.stack(cols, -1)


def sample_points(T=6, seed=3):
    rng = np.random.default_rng(seed)
    return rng.normal(size=(T, N_STATE)) * 3 + 1, rng.normal(size=(T, N_INPUT)) * 2


MIXED_MEMBERS = (
    MemberSpec("elu", 5, 2, layer_norm=True),
    MemberSpec("tanh", 8, 1),
    MemberSpec("relu", 3, 2),
    MemberSpec("leaky_relu", 6, 1, layer_norm=True),
    MemberSpec("swish", 7, 2, dropout=0.3),
    MemberSpec("sigmoid", 4, 1),
    MemberSpec("elu", 8, 1),
    MemberSpec("tanh", 6, 3, layer_norm=True),
    MemberSpec("relu", 4, 4),
)


# ------------------------------------------------------------------------------------------
# Jacobians
# ------------------------------------------------------------------------------------------


@pytest.mark.parametrize("formulation", FORMULATIONS)
@pytest.mark.parametrize("activation", sorted(ACTIVATIONS))
def test_jacobians_match_finite_differences(formulation, activation):
    members = [MemberSpec(activation, 7, 1), MemberSpec(activation, 4, 2),
               MemberSpec(activation, 5, 3)]
    model = make_model(members, formulation)
    x, u = sample_points()
    A, B = model.member_jacobians(x, u)
    J = np.concatenate([A, B], -1)
    J_fd = finite_difference_jacobians(model, x, u)
    assert J.shape == (3, len(x), N_STATE, N_STATE + N_INPUT)
    np.testing.assert_allclose(J, J_fd, rtol=1e-6, atol=1e-7)
    # ensemble mean = mean of members, and = finite differences of the mean prediction (step)
    A_mean, B_mean = model.jacobians(x, u)
    np.testing.assert_allclose(np.concatenate([A_mean, B_mean], -1), J_fd.mean(0), atol=1e-7)
    # differentiable torch path (float32) agrees with the float64 finite differences
    J_torch = model.member_jacobians_torch(torch.tensor(x), torch.tensor(u)).detach().numpy()
    np.testing.assert_allclose(J_torch, J_fd, rtol=1e-4, atol=1e-4 * np.abs(J_fd).max())


@pytest.mark.parametrize("formulation", FORMULATIONS)
def test_mixed_architecture_jacobians_match_autograd_and_finite_differences(formulation):
    """Padded widths, depth 1 to 4 groups, layer norm on some members, dropout (inactive in
    evaluation): closed form vs finite differences (float64) and torch autograd (float32)."""
    model = make_model(MIXED_MEMBERS, formulation)
    x, u = sample_points(T=5)
    A, B = model.member_jacobians(x, u)
    J = np.concatenate([A, B], -1)
    np.testing.assert_allclose(J, finite_difference_jacobians(model, x, u), rtol=1e-6, atol=1e-7)
    xu = torch.tensor(np.concatenate([x, u], 1), dtype=torch.float32)
    J_auto = torch.stack([
        torch.autograd.functional.jacobian(lambda p: model.forward_torch(p[None])[:, 0], xu[i])
        for i in range(len(xu))
    ], 1).numpy()
    np.testing.assert_allclose(J, J_auto, rtol=1e-4, atol=1e-4 * np.abs(J).max())


@pytest.mark.parametrize("formulation", ["g", "nominal", "scaled"])
def test_skip_formulations_add_their_linear_part_to_the_network_jacobian(formulation):
    """With identical weights (same seed, no normalization) the f model is the bare network, so
    g's state Jacobian is I + dNN/dx (paper eq. (jacshift)), nominal's A0 + dNN/dx and B0 +
    dNN/du, scaled's diag(tau) + dNN/dx."""
    kw = formulation_kwargs(formulation)
    f_model = make_model(MIXED_MEMBERS, "f", normalize=False)
    other = make_model(MIXED_MEMBERS, formulation, normalize=False, **{})
    other.load_state_dict(f_model.state_dict() | {"skip_J": other.skip_J})
    x, u = sample_points()
    A_f, B_f = f_model.member_jacobians(x, u)
    A_o, B_o = other.member_jacobians(x, u)
    expected_A = {"g": np.eye(N_STATE), "nominal": kw.get("A0"),
                  "scaled": np.diag(kw.get("tau", (0,) * N_STATE))}[formulation]
    expected_B = kw["B0"] if formulation == "nominal" else np.zeros((N_STATE, N_INPUT))
    np.testing.assert_allclose(A_o - A_f, np.broadcast_to(expected_A, A_f.shape), atol=1e-12)
    np.testing.assert_allclose(B_o - B_f, np.broadcast_to(expected_B, B_f.shape), atol=1e-12)
    # and the predictions differ by exactly the skip part
    skip = x @ expected_A.T + u @ expected_B.T
    np.testing.assert_allclose(other.member_predictions(x, u) - f_model.member_predictions(x, u),
                               np.broadcast_to(skip, (len(MIXED_MEMBERS), *skip.shape)),
                               atol=1e-12)


# ------------------------------------------------------------------------------------------
# batched ensemble == members one by one (outputs and gradients)
# ------------------------------------------------------------------------------------------


def member_parameters(model, k, *, grad=False):
    """Views of member ``k``'s (config index) unpadded parameters, or of their gradients.

    Weights are ``[fan_in, fan_out]`` (``y = x @ W + b``): ``W1, b1, W2, b2, ..., Wo, bo``,
    ``ln_gain*/ln_bias*`` with layer norm and ``Wv, bv, max_logvar, min_logvar`` (``[1, n]``)
    for probabilistic members.
    """
    spec = model.config.members[k]
    pos = model._stacked_order.index(k)
    for g in model.groups:
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
        if name in ("Wo", "Wv"):
            t = t[:w]
        elif name[0] == "W" and name != "W1":  # W2, W3, ... [W, W]
            t = t[:w, :w]
        elif name not in ("bo", "bv", "max_logvar", "min_logvar"):  # W1 [in, W], b*/ln_*
            t = t[:, :w]
        out[name] = t
    return out


def reference_member_forward(params, spec, xu, model):
    """Plain per-member MLP from functional primitives, with the model's normalization and skip."""
    act = {
        "elu": F.elu,
        "sigmoid": torch.sigmoid,
        "tanh": torch.tanh,
        "swish": lambda z: z * torch.sigmoid(z),
        "relu": F.relu,
        "leaky_relu": lambda z: F.leaky_relu(z, 0.01),
    }[spec.activation]
    h = (xu - model.in_mean) / model.in_std
    layers = [(f"W{i}", f"b{i}") for i in range(1, spec.depth + 1)]
    for i, (w, b) in enumerate(layers, start=1):
        z = F.linear(h, params[w].T, params[b][0])
        if spec.layer_norm:
            z = F.layer_norm(z, (spec.width,), params[f"ln_gain{i}"][0], params[f"ln_bias{i}"][0],
                             eps=1e-5)
        h = act(z)
    y = F.linear(h, params["Wo"].T, params["bo"][0])
    return xu @ model.skip_J.T + model.out_mean + model.out_std * y


@pytest.mark.parametrize("members", [MIXED_MEMBERS, EnsembleConfig(1, 1).members])
def test_batched_ensemble_equals_members_one_by_one(members):
    model = make_model(members, "g")
    rng = np.random.default_rng(7)
    xu = torch.tensor(np.concatenate(sample_points(T=40, seed=8), 1), dtype=torch.float32)
    target = torch.tensor(rng.normal(size=(40, N_STATE)), dtype=torch.float32)

    # batched: one forward for all members, one backward of the summed member losses
    model.zero_grad()
    pred = model.forward_torch(xu)
    ((pred - target) ** 2).sum(-1).mean(-1).sum().backward()

    for k, spec in enumerate(members):
        ref_params = {name: p.detach().clone().requires_grad_(True)
                      for name, p in member_parameters(model, k).items()}
        ref = reference_member_forward(ref_params, spec, xu, model)
        torch.testing.assert_close(pred[k], ref, rtol=1e-5, atol=1e-5)
        ((ref - target) ** 2).sum(-1).mean().backward()
        grads = member_parameters(model, k, grad=True)
        for name, p in ref_params.items():
            torch.testing.assert_close(grads[name], p.grad, rtol=1e-4, atol=1e-5,
                                       msg=f"member {k} ({spec.activation}) gradient of {name}")


def test_dropout_is_active_only_in_training_mode_and_seeded():
    model = make_model([MemberSpec("tanh", 16, 1, dropout=0.5)] * 2, "g")
    xu = torch.tensor(np.concatenate(sample_points(T=10), 1), dtype=torch.float32)
    eval_out = model.forward_torch(xu)
    torch.testing.assert_close(eval_out, model.forward_torch(xu))  # deterministic in eval
    model.train()
    outs = []
    for _ in range(2):
        model.dropout_generator = torch.Generator().manual_seed(5)
        outs.append(model.forward_torch(xu))
    model.eval()
    torch.testing.assert_close(outs[0], outs[1])  # same seed, same masks
    assert not torch.allclose(outs[0], eval_out)


# ------------------------------------------------------------------------------------------
# protocol surface, normalization, caching
# ------------------------------------------------------------------------------------------


def test_protocol_surface_and_shapes():
    model = make_model(EnsembleConfig(1, 1).members, "g")
    assert isinstance(model, DynamicsModel)
    assert (model.state_dim, model.action_dim, model.n_members) == (N_STATE, N_INPUT, 4)
    x, u = sample_points(T=6)
    mean, std = model.predict(x, u)
    members = model.member_predictions(x, u)
    np.testing.assert_allclose(mean, members.mean(0), atol=1e-12)
    np.testing.assert_allclose(std, members.std(0), atol=1e-12)
    np.testing.assert_allclose(model.step(x, u), mean, atol=1e-12)
    assert model.step(x[0], u[0]).shape == (N_STATE,)
    torch_pred = model.forward_torch(torch.tensor(x), torch.tensor(u)).detach().numpy()
    np.testing.assert_allclose(torch_pred, members, rtol=1e-5, atol=1e-5)


@settings(max_examples=25, deadline=None)
@given(lead=st.lists(st.integers(1, 4), min_size=0, max_size=3), seed=st.integers(0, 1000))
def test_step_is_batched_over_any_leading_dimensions(lead, seed):
    model = _HYPOTHESIS_MODEL
    rng = np.random.default_rng(seed)
    x = rng.normal(size=(*lead, N_STATE)) * 3
    u = rng.normal(size=(*lead, N_INPUT))
    out = model.step(x, u)
    assert out.shape == (*lead, N_STATE)
    rows = model.step(x.reshape(-1, N_STATE), u.reshape(-1, N_INPUT))
    np.testing.assert_allclose(out.reshape(-1, N_STATE), rows, rtol=1e-12, atol=1e-12)
    one = model.step(x.reshape(-1, N_STATE)[0], u.reshape(-1, N_INPUT)[0])
    np.testing.assert_allclose(one, rows[0], rtol=1e-12, atol=1e-12)


_HYPOTHESIS_MODEL = make_model(MIXED_MEMBERS, "g")


def test_single_member_has_zero_spread():
    model = make_model([MemberSpec("tanh", 5)], "f")
    _, std = model.predict(*sample_points())
    np.testing.assert_array_equal(std, 0.0)


def test_set_normalization_uses_input_and_residual_statistics():
    trajs = [random_trajectory(20, N_STATE, N_INPUT, s) for s in (1, 2)]
    kw = formulation_kwargs("nominal")
    model = DynamicsEnsemble(EnsembleConfig(N_STATE, N_INPUT, formulation="nominal", **kw))
    assert not model.is_normalized
    model.set_normalization(trajs)
    assert model.is_normalized
    xu = np.concatenate([np.concatenate([t.x[:-1], t.u], 1) for t in trajs])
    resid = np.concatenate([t.x[1:] for t in trajs]) - xu @ np.concatenate(
        [kw["A0"], kw["B0"]], 1).T
    np.testing.assert_allclose(model.in_mean.numpy(), xu.mean(0), rtol=1e-6)
    np.testing.assert_allclose(model.in_std.numpy(), xu.std(0), rtol=1e-6)
    np.testing.assert_allclose(model.out_mean.numpy(), resid.mean(0), rtol=1e-5, atol=1e-6)
    np.testing.assert_allclose(model.out_std.numpy(), resid.std(0), rtol=1e-6)
    # a constant input dimension is not rescaled (std floor)
    const = Trajectory(np.ones((5, N_STATE)), np.zeros((4, N_INPUT)))
    model.set_normalization([const])
    np.testing.assert_array_equal(model.in_std.numpy(), 1.0)
    # normalize=False keeps the identity statistics (the original code's raw data)
    raw = DynamicsEnsemble(EnsembleConfig(N_STATE, N_INPUT, normalize=False))
    raw.set_normalization(trajs)
    assert raw.is_normalized
    np.testing.assert_array_equal(raw.in_std.numpy(), 1.0)
    np.testing.assert_array_equal(raw.out_mean.numpy(), 0.0)


def test_frozen_model_is_a_snapshot_and_a_new_freeze_sees_the_update():
    model = make_model(EnsembleConfig(1, 1).members, "g")
    x, u = sample_points()
    frozen = model.freeze("float64")
    before = frozen.step(x, u)
    with torch.no_grad():
        model.groups[0].bo.add_(1.0)  # as an optimizer step would
    np.testing.assert_array_equal(frozen.step(x, u), before)
    after = model.freeze("float64").step(x, u)
    np.testing.assert_allclose(after - before, np.broadcast_to(model.out_std.numpy(), after.shape),
                               rtol=1e-6)


def test_same_seed_same_weights_different_seed_different_weights():
    a, b, c = (DynamicsEnsemble(EnsembleConfig(N_STATE, N_INPUT, seed=s)) for s in (4, 4, 5))
    for (na, pa), (_, pb), (_, pc) in zip(a.named_parameters(), b.named_parameters(),
                                          c.named_parameters()):
        torch.testing.assert_close(pa, pb, rtol=0, atol=0)
        if na.endswith("W1"):
            assert not torch.equal(pa, pc)
    # glorot-uniform weights within +-sqrt(6 / (fan_in + fan_out)), zero biases
    w1 = member_parameters(a, 0)["W1"]
    assert float(w1.abs().max()) <= np.sqrt(6 / (N_STATE + N_INPUT + 20))
    assert float(member_parameters(a, 0)["b1"].abs().max()) == 0.0


def test_paper_nominal_default():
    cfg = EnsembleConfig(4, 2)
    assert [s.activation for s in cfg.members] == ["elu", "sigmoid", "tanh", "swish"]
    assert all(s.width == 20 and s.depth == 1 for s in cfg.members)
    assert cfg.formulation == "g"


# ------------------------------------------------------------------------------------------
# save / load
# ------------------------------------------------------------------------------------------


@pytest.mark.parametrize("formulation", FORMULATIONS)
def test_save_load_round_trip_is_identical(tmp_path, formulation):
    model = make_model(MIXED_MEMBERS, formulation)
    path = tmp_path / "model.pt"
    save_model(model, path)
    loaded = load_model(path)
    assert loaded.config == model.config
    assert loaded.is_normalized
    x, u = sample_points()
    np.testing.assert_array_equal(loaded.member_predictions(x, u), model.member_predictions(x, u))
    for a, b in zip(loaded.member_jacobians(x, u), model.member_jacobians(x, u)):
        np.testing.assert_array_equal(a, b)
    assert not loaded.training


def test_load_refuses_foreign_files(tmp_path):
    path = tmp_path / "other.pt"
    torch.save({"weights": torch.zeros(3)}, path)
    with pytest.raises(ValueError, match="not a saved"):
        load_model(path)

    # an arbitrary pickled object (here a stdlib class outside torch's allow-list) is refused,
    # even inside a file with a valid header and checksum
    torch_save_verified({"format": "mbtsr.DynamicsEnsemble", "obj": Fraction(1, 3)}, path,
                        kind="mbtsr.DynamicsEnsemble", version=2)
    with pytest.raises(Exception, match="(?i)weights_only|unpickl|global"):
        load_model(path)


# ------------------------------------------------------------------------------------------
# bad input
# ------------------------------------------------------------------------------------------


@pytest.mark.parametrize(
    "kwargs, match",
    [
        ({"activation": "gelu"}, "activation"),
        ({"width": 0}, "width"),
        ({"width": 2.5}, "width"),
        ({"depth": 0}, "depth"),
        ({"depth": 2.0}, "depth"),
        ({"dropout": 1.0}, "dropout"),
        ({"dropout": -0.1}, "dropout"),
        ({"dropout": float("nan")}, "dropout"),
        ({"layer_norm": "yes"}, "layer_norm"),
    ],
)
def test_member_spec_rejects_bad_values(kwargs, match):
    with pytest.raises(ValueError, match=match):
        MemberSpec(**kwargs)


@pytest.mark.parametrize(
    "kwargs, match",
    [
        ({"state_dim": 0}, "state_dim"),
        ({"action_dim": -1}, "action_dim"),
        ({"formulation": "h"}, "formulation"),
        ({"formulation": "nominal"}, "A0"),
        ({"formulation": "nominal", "A0": np.eye(2), "B0": np.zeros((3, 2))}, "A0"),
        ({"formulation": "nominal", "A0": np.eye(3), "B0": np.full((3, 2), np.nan)}, "B0"),
        ({"A0": np.eye(3), "B0": np.zeros((3, 2))}, "nominal"),
        ({"formulation": "scaled", "tau": (1.0, 2.0)}, "tau"),
        ({"formulation": "scaled", "tau": float("inf")}, "tau"),
        ({"members": ()}, "members"),
        ({"members": ("tanh",)}, "MemberSpec"),
        ({"normalize": 1}, "normalize"),
    ],
)
def test_ensemble_config_rejects_bad_values(kwargs, match):
    base = {"state_dim": 3, "action_dim": 2}
    with pytest.raises(ValueError, match=match):
        EnsembleConfig(**{**base, **kwargs})


def test_model_methods_reject_bad_inputs():
    model = make_model(EnsembleConfig(1, 1).members, "g")
    x, u = sample_points()
    with pytest.raises(ValueError, match="x must have last dimension"):
        model.step(x[:, :2], u)
    with pytest.raises(ValueError, match="u must have last dimension"):
        model.step(x, u[:, :1])
    with pytest.raises(ValueError, match="batch"):
        model.step(x, u[:3])
    bad = x.copy()
    bad[2, 1] = np.nan
    with pytest.raises(ValueError, match="non-finite"):
        model.step(bad, u)
    with pytest.raises(ValueError, match="non-finite"):
        model.jacobians(x, np.where(u > 0, np.inf, u))
    with pytest.raises(ValueError, match="u must have shape"):
        model.jacobians(x, u[:-1])
    with pytest.raises(ValueError, match="x must have shape"):
        model.member_jacobians(x[None], u)
    with pytest.raises(ValueError, match="last dimension"):
        model.forward_torch(torch.zeros(4, 3))
    with pytest.raises(ValueError, match=r"\(n, m\)"):
        model.set_normalization([random_trajectory(5, 2, 2, 0)])
    with pytest.raises(ValueError, match="Trajectory"):
        model.set_normalization([(x, u)])


@settings(max_examples=40, deadline=None)
@given(
    width=st.integers(-3, 40),
    depth=st.integers(-1, 4),
    dropout=st.floats(-1.0, 2.0) | st.just(float("nan")),
    activation=st.sampled_from(sorted(ACTIVATIONS) + ["gelu", "ELU", ""]),
)
def test_member_spec_accepts_exactly_the_valid_values(width, depth, dropout, activation):
    valid = (width >= 1 and depth >= 1 and 0 <= dropout < 1 and activation in ACTIVATIONS)
    if valid:
        spec = MemberSpec(activation, width, depth, dropout)
        assert (spec.width, spec.depth) == (width, depth)
    else:
        with pytest.raises(ValueError):
            MemberSpec(activation, width, depth, dropout)


# ---------------------------------------------------------------- the ensemble-mean step fast path

WIDE_MEMBERS = (  # depth 1, no layer norm, padded widths: the folded fast path of ``step``
    MemberSpec("elu", 5),
    MemberSpec("tanh", 8),
    MemberSpec("relu", 3),
    MemberSpec("swish", 7),
    MemberSpec("sigmoid", 4),
    MemberSpec("elu", 8),
    MemberSpec("leaky_relu", 6),
)
#: one depth-3 group, no layer norm, padded widths: the folded plan with block-diagonal layers
DEEP_MEMBERS = tuple(MemberSpec(a, w, 3) for a, w in zip(sorted(ACTIVATIONS), (5, 8, 3, 7, 4, 6)))


def _normwise_close(a, b, tol):
    """max |a - b| <= tol * max |b| (rounding-level agreement of differently ordered sums)."""
    assert a.shape == b.shape
    assert np.max(np.abs(a - b)) <= tol * max(np.max(np.abs(b)), 1e-300)


@pytest.mark.parametrize("formulation", FORMULATIONS)
@pytest.mark.parametrize(
    "members",
    [[MemberSpec(a, 6) for a in ACTIVATIONS],  # every activation, one wide group
     WIDE_MEMBERS,
     [MemberSpec("swish", 7), MemberSpec("sigmoid", 3), MemberSpec("swish", 5)],  # padded
     [MemberSpec(a, 4) for a in ACTIVATIONS] + [MemberSpec("tanh", 4, depth=2)],  # generic path
     DEEP_MEMBERS],
    ids=["all-activations", "wide-padded", "padded-swish-sigmoid", "two-depths", "deep"],
)
def test_step_agrees_with_the_per_member_path(formulation, members):
    """``step`` (folded fast path: tanh-based sigmoid/swish, the mean, biases and skip inside the
    matrix products, deeper layers block-diagonal) equals the mean of the per-member float64
    predictions to rounding."""
    model = make_model(members, formulation, perturb=0.5).freeze("float64")
    assert (model._plan is None) == (len({s.depth for s in members}) > 1)
    rng = np.random.default_rng(7)
    for lead in [(11,), (), (3, 4), (0,)]:
        x = rng.normal(size=(*lead, N_STATE)) * 3 + 1
        u = rng.normal(size=(*lead, N_INPUT)) * 2
        out = model.step(x, u)
        assert out.shape == (*lead, N_STATE) and out.dtype == np.float64
        if out.size:
            _normwise_close(out, model.member_predictions(x, u).mean(0), 1e-14)


def test_step_saturating_inputs_no_warnings_and_exact_limits():
    """Huge pre-activations saturate every activation without overflow warnings; sigmoid and
    swish then reach their limits (sigmoid -> 0/1, swish -> 0/z) like scipy's expit."""
    model = make_model([MemberSpec(a, 5) for a in ACTIVATIONS], "f", perturb=0.5)
    x, u = sample_points(T=8)
    scale = np.array([1e3, 1e6, 1e12])[:, None, None]
    with np.errstate(all="raise"):
        out = model.step(x[None] * scale, u[None] * scale)  # the fast path raises on a warning
    assert np.isfinite(out).all()
    _normwise_close(out, model.member_predictions(x[None] * scale, u[None] * scale).mean(0),
                    1e-14)


def test_step_returns_a_fresh_array():
    model = make_model(WIDE_MEMBERS, "g")
    x, u = sample_points(T=5)
    first = model.step(x, u)
    kept = first.copy()
    second = model.step(x + 1.0, u)
    np.testing.assert_array_equal(first, kept)  # not a view of a reused buffer
    assert not np.shares_memory(first, second)


@pytest.mark.parametrize("make_optimizer", [
    lambda params: torch.optim.SGD(params, lr=0.1),
    lambda params: torch.optim.Adam(params, lr=0.05, fused=True),  # no version-counter bump
    lambda params: torch.optim.Adam(params, lr=0.05, foreach=True),
], ids=["sgd", "adam-fused", "adam-foreach"])
def test_freeze_after_optimizer_steps_and_load_state_dict(make_optimizer):
    """Nothing to invalidate: a freeze after an optimizer step (in place, even fused) or after
    ``load_state_dict`` computes what a freshly built model with those weights computes, and
    the copy frozen before the step is unchanged."""
    model = make_model(WIDE_MEMBERS, "g")
    x, u = sample_points(T=7)
    old = model.freeze("float64")
    before = old.step(x, u)
    opt = make_optimizer(model.parameters())
    loss = model.forward_torch(torch.tensor(x), torch.tensor(u)).square().sum()
    loss.backward()
    opt.step()
    after = model.freeze("float64").step(x, u)
    assert np.max(np.abs(after - before)) > 1e-3
    np.testing.assert_array_equal(old.step(x, u), before)
    fresh = DynamicsEnsemble(model.config)
    fresh.load_state_dict(model.state_dict())
    _normwise_close(after, fresh.freeze("float64").step(x, u), 1e-14)
    _normwise_close(after, model.freeze("float64").member_predictions(x, u).mean(0), 1e-14)
    other = make_model(WIDE_MEMBERS, "g", seed=5)
    fresh.load_state_dict(other.state_dict())  # copies in place into the same tensors
    _normwise_close(fresh.freeze("float64").step(x, u), other.member_predictions(x, u).mean(0),
                    1e-14)


@pytest.mark.parametrize("members", [WIDE_MEMBERS, MIXED_MEMBERS, DEEP_MEMBERS],
                         ids=["wide", "mixed", "deep"])
def test_frozen_model_matches_the_torch_model_and_is_immutable_float64_numpy(members):
    """The frozen copy: outputs equal the torch (float32) forward pass, Jacobians equal torch
    autograd of it and finite differences of the frozen step; float64 numpy only, read-only."""
    model = make_model(members, "nominal")
    frozen = model.freeze("float64")
    assert (frozen.state_dim, frozen.action_dim, frozen.n_members) == (N_STATE, N_INPUT,
                                                                      len(members))
    x, u = sample_points(T=5)
    members_t = model.forward_torch(torch.tensor(x), torch.tensor(u)).detach().numpy()
    pred = frozen.member_predictions(x, u)
    np.testing.assert_allclose(pred, members_t, rtol=1e-5, atol=1e-5 * np.abs(pred).max())
    mean, std = frozen.predict(x, u)
    np.testing.assert_allclose(frozen.step(x, u), mean, rtol=1e-13, atol=1e-13)
    np.testing.assert_allclose(std, pred.std(0), rtol=1e-13)
    xu = torch.tensor(np.concatenate([x, u], 1), dtype=torch.float32)
    J_auto = torch.stack([
        torch.autograd.functional.jacobian(lambda p: model.forward_torch(p[None])[:, 0].mean(0),
                                           xu[i])
        for i in range(len(xu))
    ]).numpy()
    A, B = frozen.jacobians(x, u)
    J = np.concatenate([A, B], -1)
    np.testing.assert_allclose(J, J_auto, rtol=1e-4, atol=1e-4 * np.abs(J).max())
    eps, cols = 1e-6, []
    for j in range(N_STATE + N_INPUT):
        e = np.zeros(N_STATE + N_INPUT)
        e[j] = eps
        cols.append((frozen.step(x + e[:N_STATE], u + e[N_STATE:])
                     - frozen.step(x - e[:N_STATE], u - e[N_STATE:])) / (2 * eps))
    np.testing.assert_allclose(J, np.stack(cols, -1), rtol=1e-6, atol=1e-7)
    # immutable: no attribute can be set, no array written; nothing torch inside
    with pytest.raises(AttributeError, match="immutable"):
        frozen.state_dim = 7
    arrays = [a for _, p in frozen._groups for a in p.values()] + [frozen._skip_J]
    if frozen._plan is not None:
        arrays += [v for v in vars(frozen._plan).values()
                   if isinstance(v, np.ndarray) and v.dtype.kind == "f"]
        assert not frozen._plan.kernel_runs.flags.writeable
    assert all(isinstance(a, np.ndarray) and a.dtype == np.float64 for a in arrays)
    with pytest.raises(ValueError, match="read-only"):
        arrays[0][...] = 0.0
    assert not any(isinstance(v, torch.Tensor) for v in vars(frozen).values())


@pytest.mark.parametrize(
    "call, match",
    [
        (lambda f, x, u: f.step(x[:, :2], u), "x must have last dimension"),
        (lambda f, x, u: f.step(x, u[:3]), "batch"),
        (lambda f, x, u: f.step(np.where(x > 1, np.nan, x), u), "x contains .* non-finite"),
        (lambda f, x, u: f.step(x, np.full_like(u, np.inf)), "u contains .* non-finite"),
        (lambda f, x, u: f.jacobians(x, u[:-1]), r"u must have shape \[6, 2\]"),
        (lambda f, x, u: f.member_jacobians(x[None], u), "x must have shape"),
        (lambda f, x, u: f.predict(x, "u"), "u must be numeric"),
    ],
)
def test_frozen_model_names_bad_inputs(call, match):
    frozen = make_model(WIDE_MEMBERS, "g").freeze("float64")
    x, u = sample_points()
    with pytest.raises(ValueError, match=match):
        call(frozen, x, u)


def test_planning_code_refuses_the_trainable_model():
    from mbtsr.costs import quadratic_cost
    from mbtsr.ilqr import ilqr

    model = make_model(WIDE_MEMBERS, "g")
    cost = quadratic_cost(np.eye(N_STATE), np.eye(N_INPUT))
    with pytest.raises(TypeError, match=r"model.freeze\(\)"):
        ilqr(cost, model, np.zeros(N_STATE), np.zeros((4, N_INPUT)))
    res = ilqr(cost, model.freeze("float64"), np.zeros(N_STATE), np.zeros((4, N_INPUT)),
               options={"max_iter": 3})
    assert np.isfinite(res.U).all()


@pytest.mark.parametrize(
    "corrupt, match",
    [
        (lambda m: m.groups[0].W1.data.__setitem__((0, 1, 2), float("nan")),
         r"groups.0.W1 contains 1 non-finite"),
        (lambda m: m.out_mean.__setitem__(0, float("inf")), "out_mean contains 1 non-finite"),
        (lambda m: m.in_std.__setitem__(1, 0.0), "in_std must be > 0"),
    ],
)
def test_freeze_names_a_non_finite_or_invalid_tensor(corrupt, match):
    model = make_model(WIDE_MEMBERS, "g")
    with torch.no_grad():
        corrupt(model)
    with pytest.raises(ValueError, match=match):
        model.freeze("float64")


def test_rollout_of_the_trainable_model_simulates_one_frozen_copy():
    from mbtsr.dynamics import rollout

    model = make_model(WIDE_MEMBERS, "g")
    x, u = sample_points(T=6)
    frozen = model.freeze("float64")  # a metric's copy: float64, as the ensemble's own methods
    want = [x[0]]
    for t in range(6):
        want.append(frozen.step(want[-1], u[t]))
    np.testing.assert_array_equal(rollout(model, x[0], u), np.array(want))


@pytest.mark.parametrize(
    "members", [[MemberSpec(a, 6) for a in ACTIVATIONS], WIDE_MEMBERS, DEEP_MEMBERS],
    ids=["all-activations", "wide-padded", "deep"],
)
def test_compiled_step_kernel_equals_the_numpy_step(members):
    """The compiled kernel (small batches) and the numpy path (large batches) of the frozen
    ensemble-mean step agree to rounding, also with saturated activations."""
    frozen = make_model(members, "nominal", perturb=0.5).freeze("float64")
    rng = np.random.default_rng(11)
    for B in (1, 2, 3, 4):
        for scale in (1.0, 1e3, 1e12):
            x = rng.normal(size=(B, N_STATE)) * 3 * scale
            u = rng.normal(size=(B, N_INPUT)) * scale
            got = frozen._step(x, u)
            want = frozen._step_numpy(x, u)
            _normwise_close(got, want, 1e-14)
            _normwise_close(got, frozen.member_predictions(x, u).mean(0), 1e-13)
    x = rng.normal(size=(7, 3, N_STATE))[:, 1]  # a strided view, as in batched rollouts
    u = rng.normal(size=(7, N_INPUT))
    _normwise_close(frozen._step(x[:3], u[:3]), frozen._step_numpy(x[:3], u[:3]), 1e-14)


@pytest.mark.parametrize("activation", ACTIVATIONS)
@pytest.mark.parametrize("precision", ["float32", "float64"])
def test_folded_steps_pass_a_nan_on_as_the_members_do(activation, precision):
    """An infinite input makes inf - inf (NaN) inside a deeper layer: the compiled kernel and
    the numpy path of the folded step pass it on as the unfolded members do."""
    frozen = make_model([MemberSpec(activation, 5, 3)] * 2, perturb=0.5).freeze(precision)
    x, u = np.array([[np.inf, 0.3, -0.2]]), np.array([[0.1, 0.4]])
    with np.errstate(all="ignore"):
        members = frozen._members(np.concatenate([x, u], 1), 0)[0].mean(0)
        for step in (frozen._step, frozen._step_numpy):
            np.testing.assert_array_equal(np.isnan(step(x, u)), np.isnan(members))


@pytest.mark.parametrize("members", [WIDE_MEMBERS, DEEP_MEMBERS], ids=["wide", "deep"])
@pytest.mark.parametrize("max_norm", [1e8, 6.0])
def test_compiled_line_search_rollouts_equal_the_python_rollouts(max_norm, members):
    """iLQR's closed-loop rollouts through the frozen ensemble's compiled kernel equal the
    solver's generic rollouts through ``step`` (same states, controls and dead rows)."""
    from mbtsr.ilqr import _rollout_policy

    frozen = make_model(members, "g", perturb=0.5).freeze("float64")

    class StepOnly:  # the same model seen only through its step: the generic path
        state_dim, action_dim = frozen.state_dim, frozen.action_dim
        step = staticmethod(frozen.step)

    rng = np.random.default_rng(5)
    T = 9
    X = rng.normal(size=(T + 1, N_STATE))
    U, k = rng.normal(size=(T, N_INPUT)), rng.normal(size=(T, N_INPUT))
    K = 0.3 * rng.normal(size=(T, N_INPUT, N_STATE))
    alphas = np.array([1.0, 0.5, 0.1, 0.01])
    lower, upper = np.array([-1.0, -np.inf]), np.array([0.5, np.inf])
    got = _rollout_policy(frozen, X[0], X, U, k, K, alphas, lower, upper, 0, max_norm)
    want = _rollout_policy(StepOnly(), X[0], X, U, k, K, alphas, lower, upper, 0, max_norm)
    for g, w in zip(got, want):
        np.testing.assert_allclose(g, w, rtol=1e-13, atol=1e-13)
    if max_norm < 10:
        assert not got[2].all()  # some rows were declared dead, identically


# ------------------------------------------------------------------------------------------
# the scaled model: per-member batches, probabilistic members, trajectory sampling, sizing
# ------------------------------------------------------------------------------------------


def test_per_member_batches_equal_each_member_on_its_own_batch():
    """``stacked_forward`` with one batch per member ``[K, B, n+m]`` gives member ``k`` exactly
    what the shared-input forward gives it on batch ``k`` (outputs and Jacobians), for mixed
    depths, padded widths and layer norm."""
    model = make_model(MIXED_MEMBERS, "g")
    K = model.n_members
    rng = np.random.default_rng(4)
    xu = torch.tensor(rng.normal(size=(K, 6, N_STATE + N_INPUT)) * 2, dtype=torch.float32)
    y, J = model.stacked_forward(xu, jac_rows=6)
    for i in range(K):
        y_i, J_i = model.stacked_forward(xu[i], jac_rows=6)
        torch.testing.assert_close(y[i], y_i[i], rtol=1e-6, atol=1e-6)
        torch.testing.assert_close(J[i], J_i[i], rtol=1e-5, atol=1e-5)


def make_probabilistic(members=DEEP_MEMBERS, seed=0):
    model = make_model(members, "g", seed=seed, probabilistic=True)
    with torch.no_grad():  # spread the log-variance head's inputs over its whole range
        for g in model.groups:
            g.Wv.mul_(8.0)
    return model


def test_probabilistic_members_have_a_soft_bounded_log_variance():
    """The log-variance head: PETS' soft bounds (``min <= logvar <= max + log(1 + e^(min -
    max))``, the formula increasing in the raw output; exactly mbrl-lib's), the frozen std
    ``out_std * exp(logvar / 2)`` equals the torch head's, and the mean (and its Jacobian) is
    the deterministic network's."""
    model = make_probabilistic()
    x, u = sample_points(T=40)
    xu = torch.tensor(np.concatenate([x, u], 1), dtype=torch.float32)
    y, _, lv = model.stacked_forward(xu, logvar=True)
    g = model.groups[0]
    assert lv.shape == y.shape == (len(DEEP_MEMBERS), 40, N_STATE)
    hi = g.max_logvar + torch.log1p(torch.exp(g.min_logvar - g.max_logvar))
    assert bool((lv <= hi + 1e-6).all()) and bool((lv >= g.min_logvar).all())
    assert float(lv.detach().max() - lv.detach().min()) > 5.0  # softly reached bounds
    with torch.no_grad():
        h = model.normalize_inputs(xu)
        for i in range(1, g.depth + 1):
            h = torch.baddbmm(getattr(g, f"b{i}"), h.expand(len(DEEP_MEMBERS), -1, -1)
                              if h.dim() == 2 else h, getattr(g, f"W{i}") * g.mask
                              if i == 1 else getattr(g, f"W{i}") * g.mask.mT * g.mask)
            parts = h.split([b - a for _, a, b in g.runs])
            h = torch.cat([ACTIVATIONS[name][0](p) for (name, _, _), p in zip(g.runs, parts)])
        raw = torch.baddbmm(g.bv, h, g.Wv * g.mask.mT)
        want = g.max_logvar - F.softplus(g.max_logvar - raw)
        want = g.min_logvar + F.softplus(want - g.min_logvar)
    torch.testing.assert_close(lv.detach(), want, rtol=1e-5, atol=1e-5)
    frozen = model.freeze("float64")
    std = frozen.member_std(x, u)
    want_std = model.out_std.numpy() * np.exp(0.5 * model._config_order(lv).detach().numpy())
    np.testing.assert_allclose(std, want_std, rtol=1e-4)
    # the mean: the member predictions and Jacobians of the same weights without the head
    det = DynamicsEnsemble(dataclasses.replace(model.config, probabilistic=False))
    det.load_state_dict({k: v for k, v in model.state_dict().items()
                         if k.rsplit(".", 1)[-1] not in ("Wv", "bv", "max_logvar", "min_logvar")})
    np.testing.assert_array_equal(frozen.member_predictions(x, u), det.member_predictions(x, u))
    np.testing.assert_allclose(np.concatenate(frozen.jacobians(x, u), -1),
                               finite_difference_jacobians(frozen, x, u).mean(0), atol=1e-7)
    with pytest.raises(ValueError, match="probabilistic"):
        det.freeze("float64").member_std(x, u)


def test_refit_normalization_keeps_the_mean_and_the_variance_of_probabilistic_members():
    model = make_probabilistic()
    x, u = sample_points(T=9)
    mean, std = model.member_predictions(x, u), model.member_std(x, u)
    model.refit_normalization([random_trajectory(25, N_STATE, N_INPUT, 9, scale_x=7.0)])
    np.testing.assert_allclose(model.member_predictions(x, u), mean, rtol=2e-5,
                               atol=2e-5 * np.abs(mean).max())
    np.testing.assert_allclose(model.member_std(x, u), std, rtol=2e-5)


def test_probabilistic_model_saves_and_old_configs_load(tmp_path):
    model = make_probabilistic(MIXED_MEMBERS)
    save_model(model, tmp_path / "p.pt")
    loaded = load_model(tmp_path / "p.pt")
    x, u = sample_points()
    assert loaded.config.probabilistic
    np.testing.assert_array_equal(loaded.member_std(x, u), model.member_std(x, u))
    # a config written before the field existed (no "probabilistic" key) is deterministic
    old = json.loads(EnsembleConfig(N_STATE, N_INPUT).to_json())
    del old["probabilistic"]
    assert EnsembleConfig.from_json(json.dumps(old)) == EnsembleConfig(N_STATE, N_INPUT)


@pytest.mark.parametrize("members", [DEEP_MEMBERS, MIXED_MEMBERS], ids=["deep", "mixed"])
@pytest.mark.parametrize("B", [1, 7, 14])
def test_trajectory_sampling_sends_row_r_to_member_r_mod_k(members, B):
    """Row ``r`` of a batch is member ``r mod K``'s prediction (config order, any group
    structure, batches not a multiple of K), with the batch shape kept."""
    frozen = make_model(members, "nominal", perturb=0.5).freeze("float64")
    K = frozen.n_members
    ts = frozen.trajectory_sampling(seed=3)
    rng = np.random.default_rng(B)
    x, u = rng.normal(size=(B, N_STATE)) * 2, rng.normal(size=(B, N_INPUT))
    every = frozen.member_predictions(x, u)  # [K, B, n]
    got = ts.step(x, u, t=4)
    want = every[np.arange(B) % K, np.arange(B)]
    _normwise_close(got, want, 1e-13)
    assert ts.step(x.reshape(1, B, N_STATE), u.reshape(1, B, N_INPUT)).shape == (1, B, N_STATE)
    with pytest.raises(TypeError, match="no Jacobians"):
        ts.jacobians(x, u)


@pytest.mark.parametrize("members", [DEEP_MEMBERS, MIXED_MEMBERS], ids=["deep", "mixed"])
@pytest.mark.parametrize("probabilistic", [False, True])
def test_disagreement_is_the_member_variance_in_output_units(members, probabilistic):
    """``disagreement`` = the variance over members of their predictions (the means, for
    probabilistic members), divided by ``out_std^2`` and averaged over the state: computed here
    from ``member_predictions`` and the torch model's statistics, on the folded fast path
    (deep) and the generic one (mixed); the batch shape is kept; the trajectory-sampling view
    gives the same; one member disagrees with nobody."""
    model = make_model(members, "g", perturb=0.5, probabilistic=probabilistic)
    frozen = model.freeze("float64")
    rng = np.random.default_rng(5)
    x, u = rng.normal(size=(3, 4, N_STATE)) * 2, rng.normal(size=(3, 4, N_INPUT))
    preds = frozen.member_predictions(x, u)  # [K, 3, 4, n]
    scale = model.out_std.double().numpy()
    want = (preds.var(0) / scale**2).mean(-1)
    got = frozen.disagreement(x, u)
    assert got.shape == (3, 4)
    np.testing.assert_allclose(got, want, rtol=1e-10, atol=1e-14)
    assert np.all(got > 0)
    ts = frozen.trajectory_sampling(seed=1)  # what CEM's explore options call on the view
    np.testing.assert_array_equal(ts.disagreement(x, u), got)
    np.testing.assert_array_equal(ts.member_predictions(x, u), preds)
    one = make_model([MemberSpec("tanh", 5)], "g").freeze("float64")
    np.testing.assert_array_equal(one.disagreement(x, u), 0.0)
    with pytest.raises(ValueError, match="x"):
        frozen.disagreement(x[..., :2], u)


def test_trajectory_sampling_of_probabilistic_members_samples_seeded_noise():
    frozen = make_probabilistic().freeze("float64")
    K = frozen.n_members
    B = 3 * K
    rng = np.random.default_rng(0)
    x, u = rng.normal(size=(B, N_STATE)), rng.normal(size=(B, N_INPUT))
    rows = np.arange(B) % K, np.arange(B)
    mean = frozen.member_predictions(x, u)[rows]
    std = frozen.member_std(x, u)[rows]
    ts = frozen.trajectory_sampling(seed=5)
    eps = np.random.default_rng([5, 7]).standard_normal((B, N_STATE))
    np.testing.assert_allclose(ts.step(x, u, 7), mean + std * eps, rtol=1e-12, atol=1e-12)
    np.testing.assert_array_equal(ts.step(x, u, 7), frozen.trajectory_sampling(5).step(x, u, 7))
    assert not np.allclose(ts.step(x, u, 8), ts.step(x, u, 7))
    np.testing.assert_allclose(frozen.trajectory_sampling(5, noise=False).step(x, u, 7), mean,
                               rtol=1e-12, atol=1e-12)
    for bad, match in (({"seed": -1}, "seed"), ({"noise": "yes"}, "noise")):
        with pytest.raises(ValueError, match=match):
            frozen.trajectory_sampling(**bad)


def test_model_config_sizes_by_the_rule_and_keeps_the_paper_preset():
    from mbtsr.ensemble import PAPER_ACTIVATIONS, ModelConfig, default_size

    cfg = ModelConfig().ensemble_config(11, 2, seed=1)
    layers, width = default_size(11, 2)
    assert {(s.depth, s.width) for s in cfg.members} == {(layers, width)}
    assert ModelConfig(hidden_width=33, hidden_layers=5).size(11, 2) == (5, 33)
    assert ModelConfig(hidden_layers=2).size(11, 2) == (2, width)
    paper = ModelConfig.paper().ensemble_config(4, 2, seed=5)
    assert paper == EnsembleConfig(4, 2, seed=5)  # the paper's nominal ensemble
    assert paper.members == tuple(MemberSpec(a, 20, 1) for a in PAPER_ACTIVATIONS)
    assert ModelConfig(probabilistic=True).ensemble_config(3, 1).probabilistic
    for kwargs, match in (({"hidden_layers": 0}, "hidden_layers must be an integer >= 1, got 0"),
                          ({"hidden_width": 0}, "hidden_width must be an integer >= 1, got 0"),
                          ({"ensemble_size": 0}, "ensemble_size must be"),
                          ({"probabilistic": 1}, "probabilistic must be a bool")):
        with pytest.raises(ValueError, match=match):
            ModelConfig(**kwargs)


# ------------------------------------------------------------------------------------------
# planning precision: float32 kernels against the float64 reference
# ------------------------------------------------------------------------------------------


def _default_sized(seed=0):
    """The default-sized model (3 x 64 units here), normalized."""
    model = ModelConfig().build(N_STATE, N_INPUT, seed=seed)
    model.set_normalization([random_trajectory(40, N_STATE, N_INPUT, seed)])
    return model


@pytest.mark.parametrize("members", [None, WIDE_MEMBERS, DEEP_MEMBERS],
                         ids=["default-size", "wide", "deep"])
def test_float32_planning_kernels_match_the_float64_reference(members):
    """Every planning kernel of a float32 freeze (step on 1 and many rows, Jacobians, CEM's
    open-loop rollouts, iLQR's closed-loop rollouts) agrees with the float64 freeze to float32
    rounding (normwise 1e-5: about 100 ulps through three layers), and returns float64."""
    from mbtsr.dynamics import rollout
    from mbtsr.ilqr import _rollout_policy

    model = _default_sized() if members is None else make_model(members, "g", perturb=0.5)
    f32, f64 = model.freeze(), model.freeze("float64")
    assert f32.precision == "float32" and f64.precision == "float64"
    rng = np.random.default_rng(3)
    for B in (1, 2, 64):
        x, u = rng.normal(size=(B, N_STATE)), rng.normal(size=(B, N_INPUT))
        got = f32.step(x, u)
        assert got.dtype == np.float64
        _normwise_close(got, f64.step(x, u), 1e-5)
        x[0, 0] = np.nan  # the compiled kernel's clamped tanh keeps a NaN, as numpy's
        np.testing.assert_array_equal(np.isnan(f32._step(x, u)), np.isnan(f64._step(x, u)))
        assert np.isnan(f32._step(x, u)[0]).all() and not np.isnan(f32._step(x, u)[1:]).any()
    T = 12
    x, u = rng.normal(size=(T, N_STATE)), rng.normal(size=(T, N_INPUT))
    for a, b in zip(f32.jacobians(x, u), f64.jacobians(x, u)):
        assert a.dtype == np.float64
        _normwise_close(a, b, 1e-5)
    U = rng.uniform(-1, 1, size=(16, T, N_INPUT))
    out32, out64 = f32._rollout_open_loop(x[0], U, 1e8), f64._rollout_open_loop(x[0], U, 1e8)
    if out32 is not None:
        assert out32[1].all() and out64[1].all()
        _normwise_close(out32[0], out64[0], 1e-5)
    K = 0.1 * rng.normal(size=(T, N_INPUT, N_STATE))
    k, alphas = rng.normal(size=(T, N_INPUT)), np.array([1.0, 0.3, 0.1])
    X = rollout(f64, x[0], U[0])  # the nominal trajectory [T+1, n]
    lo, hi = np.full(N_INPUT, -1.0), np.full(N_INPUT, 1.0)
    got = _rollout_policy(f32, x[0], X, U[0], k, K, alphas, lo, hi, 0, 1e8)
    want = _rollout_policy(f64, x[0], X, U[0], k, K, alphas, lo, hi, 0, 1e8)
    np.testing.assert_array_equal(got[2], want[2])
    _normwise_close(got[0], want[0], 1e-5)


@pytest.mark.parametrize("cut", [False, True])
def test_open_loop_rollout_kernel_equals_stepping_the_model(cut):
    """CEM's batched rollout kernel (float64) gives the states of stepping the same model row
    by row (``mbtsr.dynamics._rollout``), NaN from the same first state beyond ``max_norm``, and
    the same dead rows; it declines batches of the compiled step kernel."""
    from mbtsr.dynamics import _rollout

    frozen = _default_sized(1).freeze("float64")
    rng = np.random.default_rng(8)
    x0, U = rng.normal(size=N_STATE), rng.uniform(-3, 3, size=(24, 10, N_INPUT))
    max_norm = 1e8
    if cut:  # half the rows exceed it at some step
        max_norm = np.median(np.abs(frozen._rollout_open_loop(x0, U, np.inf)[0]).max((1, 2)))
    X, alive = frozen._rollout_open_loop(x0, U, max_norm)

    class StepOnly:  # the same model seen only through its step: the generic path
        state_dim, action_dim = frozen.state_dim, frozen.action_dim
        step = staticmethod(frozen.step)

    want_X, want_alive = _rollout(StepOnly(), x0, U, 0, max_norm)
    np.testing.assert_array_equal(alive, want_alive)
    np.testing.assert_array_equal(np.isnan(X), np.isnan(want_X))
    np.testing.assert_allclose(X, want_X, rtol=1e-12, atol=1e-12)
    if cut:
        assert 0 < alive.sum() < len(alive)
    assert frozen._rollout_open_loop(x0, U[:frozen.kernel_rows], max_norm) is None


def test_freeze_names_an_unknown_precision():
    with pytest.raises(ValueError, match="precision must be one of"):
        make_model(WIDE_MEMBERS, "g").freeze("float16")


@pytest.mark.parametrize("swish", [False, True])
def test_float32_tanh_kernel_matches_float64_tanh(swish):
    """The frozen model's float32 tanh (a rational form, clamped beyond |z| = 9) against numpy's
    float64 tanh: within 3.5e-7 of tanh (about 3 float32 ulp near 1); ``z (tanh(z) + 1)`` within
    4e-7 (1 + |z|) (numpy's float32 path: 1.8e-7 (1 + |z|), cancellation where tanh is near -1);
    odd, and exactly +-1 far out. Without ``fast`` (float64 plans) it is numpy's tanh."""
    from mbtsr.ensemble import _act_runs

    def act(z, fast=True):
        h = z.copy()
        _act_runs(h, np.array([[0, 1, 2 if swish else 1]]), fast, len(h))
        return h

    z = np.concatenate([np.linspace(-12, 12, 2_000_001), [-1e30, -9.0, 0.0, 9.0, 1e30],
                        np.random.default_rng(0).standard_normal(5000)]).astype(np.float32)
    h = act(z)
    t = np.tanh(z.astype(np.float64))
    ref = z * (t + 1.0) if swish else t
    assert np.all(np.abs(h - ref) <= (4e-7 * (1 + np.abs(z)) if swish else 3.5e-7))
    special = np.array([np.nan, np.inf, -np.inf], np.float32)  # as numpy: NaN stays NaN
    with np.errstate(invalid="ignore"):  # -inf (tanh + 1) = -inf * 0
        want = special * (np.tanh(special) + 1) if swish else np.tanh(special)
    np.testing.assert_array_equal(act(special), want)
    if not swish:
        np.testing.assert_array_equal(h, -act(-z))
        assert h[z == 1e30][0] == 1.0 and h[z == -1e30][0] == -1.0
    z64 = z[:5000].astype(np.float64)
    want = z64 * (np.tanh(z64) + 1) if swish else np.tanh(z64)  # libm's tanh, not numpy's:
    assert np.all(np.abs(act(z64, False) - want) <= 4.5e-16 * (1 + np.abs(z64)))  # 2 ulp


def test_every_folded_frozen_model_gets_the_chunked_line_search():
    """A rollout of the folded frozen model costs more with more step sizes, so iLQR rolls the
    step sizes out in chunks of the compiled kernel's rows (tests/test_lqr_kernels.py: the same
    iterates) and stops at the first acceptable one; small and task-sized members alike."""
    small, wide = make_model(WIDE_MEMBERS, "g").freeze(), _default_sized(1).freeze()
    assert small.kernel_rows == wide.kernel_rows == 4
    assert small.line_search_chunks == wide.line_search_chunks == (0, 2, 4, 7)
    from mbtsr.costs import quadratic_cost
    from mbtsr.ilqr import ilqr

    class Skipping:  # chunk starts that would skip the largest step sizes
        state_dim, action_dim, line_search_chunks = N_STATE, N_INPUT, (1, 3)
        step, jacobians = staticmethod(wide.step), staticmethod(wide.jacobians)

    cost = quadratic_cost(np.eye(N_STATE), np.eye(N_INPUT), np.zeros(N_STATE))
    with pytest.raises(ValueError, match=r"line_search_chunks must start at 0 and increase"):
        ilqr(cost, Skipping(), np.zeros(N_STATE), np.zeros((5, N_INPUT)), u_min=-1, u_max=1)
