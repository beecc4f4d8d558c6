"""Tests of mbtsr.training: real torch training on small random stable linear systems.

Linear systems follow the paper's Algorithm 2 (A0 ~ N(0, 1), A = A0 - A0^T - dt I,
Ad = expm(dt A), B = dt randn) and data the original code's recipe (a causal 5-tap moving
average of 10 N(0, 1) inputs, measurement noise 0.01 on the training states), built here with
numpy so the tests do not depend on ``envs``. References are independent: the objective's terms
are recomputed from the float64 prediction/Jacobian path, and an optimizer step is recomputed
with Adam's closed-form first step.
"""

import numpy as np
import pytest
import torch
from hypothesis import given, settings
from hypothesis import strategies as st
from scipy.linalg import expm

from mbtsr import Trajectory
from mbtsr.ensemble import DynamicsEnsemble, EnsembleConfig, MemberSpec
from mbtsr.ltv import fit_ltv
from mbtsr.metrics import jacobian_error, prediction_rms
from mbtsr.training import (
    RegularizationConfig,
    TrainConfig,
    TrainHistory,
    _MemberStreams,
    holdout_mask,
    train_ensemble,
)

torch.set_num_threads(1)


def random_stable_system(n, m, dt, seed):
    rng = np.random.default_rng(seed)
    A0 = rng.normal(size=(n, n))
    A = A0 - A0.T - dt * np.eye(n)
    return expm(dt * A), dt * rng.normal(size=(n, m))


def linear_trajectory(A, B, T, seed, noise=0.01):
    rng = np.random.default_rng(seed)
    n, m = B.shape
    w = 10 * rng.normal(size=(T + 4, m))
    u = np.stack([w[t : t + 5].mean(0) for t in range(T)])  # causal 5-tap moving average
    x = np.zeros((T + 1, n))
    x[0] = rng.normal(size=n)
    for t in range(T):
        x[t + 1] = A @ x[t] + B @ u[t]
    return Trajectory(x + noise * rng.normal(size=x.shape), u)


QUIET = {"progress": False}


def small_model(n=3, m=2, seed=0, **kw):
    members = kw.pop("members", (MemberSpec("tanh", 8), MemberSpec("elu", 6, 2)))
    return DynamicsEnsemble(EnsembleConfig(n, m, members=members, seed=seed, **kw))

def two_trajectory_problem():
    """``(n, m, trajs, ltv, model)``: two noisy 30-step trajectories of a 3 x 2 stable linear
    system, their LTV fits and a small model normalized on them."""
    n, m = 3, 2
    A, B = random_stable_system(n, m, 0.1, seed=1)
    trajs = [linear_trajectory(A, B, 30, seed=s, noise=0.05) for s in (0, 1)]
    ltv = [fit_ltv(tr, 3.0) for tr in trajs]
    model = small_model(n, m)
    model.set_normalization(trajs)
    return n, m, trajs, ltv, model



# ------------------------------------------------------------------------------------------
# the paper's claim on a random stable linear system
# ------------------------------------------------------------------------------------------


def test_tangent_space_regularization_lowers_jacobian_error_on_linear_system():
    """Few short noisy trajectories and long training: the unregularized nominal ensemble
    overfits; sampled Jacobian propagation (paper settings: one copy, sigma 0.1, weight 1) and the
    exact penalty (weight 1) both give a lower paper Jacobian error (eq. (jacerr)) along a held-out
    noise-free trajectory. Measured: none 0.0351, sampled 0.0301, exact 0.0166 (also seeds 1-4:
    sampled/none 0.75-0.86, exact/none 0.22-0.47)."""
    n, m, dt = 4, 2, 0.02
    A, B = random_stable_system(n, m, dt, seed=0)
    train = [linear_trajectory(A, B, 100, seed=s) for s in (0, 1)]
    val = linear_trajectory(A, B, 200, seed=50, noise=0.0)
    J_true = np.broadcast_to(np.concatenate([A, B], 1), (val.T, n, n + m))
    errors, histories = {}, {}
    for name, reg in [
        ("none", RegularizationConfig()),
        ("sampled", RegularizationConfig.paper()),
        ("exact", RegularizationConfig(exact_weight=1.0)),
    ]:
        model = DynamicsEnsemble(EnsembleConfig(n, m, seed=0))  # the paper's nominal g ensemble
        histories[name] = train_ensemble(model, train, TrainConfig(epochs=1000, **QUIET), reg)
        errors[name] = jacobian_error(J_true, model.member_jacobians(val.x[:-1], val.u))
    print("Jacobian errors:", {k: round(v, 4) for k, v in errors.items()})
    assert errors["sampled"] < 0.95 * errors["none"]
    assert errors["exact"] < 0.75 * errors["none"]
    # the LTV models used as regularizers are better than the unregularized network
    ltv = histories["exact"].ltv_models[0]
    assert jacobian_error(J_true[: ltv.T], (ltv.A, ltv.B)) < errors["none"]
    # the regularized models fit the training data less closely (paper Sec. "Randomized
    # linear system": the unregularized model reaches a lower training error)
    assert histories["none"].train_loss[-1] < histories["exact"].train_loss[-1]


def test_training_learns_the_linear_system():
    n, m, dt = 3, 2, 0.05
    A, B = random_stable_system(n, m, dt, seed=3)
    train = [linear_trajectory(A, B, 100, seed=s, noise=0.0) for s in (0, 1, 2)]
    val = [linear_trajectory(A, B, 100, seed=9, noise=0.0)]
    model = small_model(n, m)
    before = prediction_rms(model, val)
    hist = train_ensemble(model, train, TrainConfig(epochs=300, **QUIET), validation=val)
    after = prediction_rms(model, val)
    hold = np.sqrt(np.mean((val[0].x[1:] - val[0].x[:-1]) ** 2))  # "x+ = x" predictor
    assert after < 0.1 * hold and after < 0.1 * before
    assert hist.val_loss[-1] < 0.05 * hist.val_loss[0]
    assert hist.train_loss.shape == hist.val_loss.shape == (300,)
    assert hist.steps == 300 * 3


# ------------------------------------------------------------------------------------------
# the objective's terms, recomputed independently
# ------------------------------------------------------------------------------------------


def normalized_sq_error(model, x, u, x_next):
    """Mean over members and points of ||(pred - x+) / out_std||^2 (float64 path)."""
    pred = model.member_predictions(x, u)
    return float(np.mean(np.sum(((pred - x_next) / model.out_std.numpy()) ** 2, -1)))


@pytest.mark.parametrize("batch", ["trajectory", "all"])
def test_recorded_losses_and_penalties_match_independent_computation(batch):
    """One optimizer step with a negligible step size, so every recorded term is the value at the
    initial weights; recomputed from the float64 predictions and Jacobians. Two trajectories:
    the smoothness pairs must not cross the trajectory boundary."""
    n, m, trajs, ltv, model = two_trajectory_problem()
    reg = RegularizationConfig(sampled_weight=1.0, sigma=0.3, n_copies=2, exact_weight=0.5,
                               smooth_weight=2.0)
    cfg = TrainConfig(epochs=1, lr=1e-12, batch="trajectory" if batch == "trajectory" else 60,
                      shuffle=False, seed=11, **QUIET)

    data = np.mean([normalized_sq_error(model, tr.x[:-1], tr.u, tr.x[1:]) for tr in trajs])
    exact, smooth = [], []
    for tr, lm in zip(trajs, ltv):
        Ah, Bh = model.member_jacobians(tr.x[:-1], tr.u)
        J = np.concatenate([Ah, Bh], -1)  # [K, T, n, n+m]
        J_ltv = np.concatenate([lm.A, lm.B], -1)
        exact.append(np.mean(np.sum((J - J_ltv) ** 2, axis=(1, 2, 3))))
        smooth.append(np.mean(np.sum((J[:, 1:] - J[:, :-1]) ** 2, axis=(1, 2, 3))))
    rng = np.random.default_rng(11)  # the same stream train_ensemble draws the copies from
    copies = [lm.sample_perturbed(tr.x, tr.u, sigma=0.3, n_copies=2, seed=rng)
              for lm, tr in zip(ltv, trajs)]
    sampled = [normalized_sq_error(model, xt, ut, xnt) for xt, ut, xnt in copies]

    hist = train_ensemble(model, trajs, cfg, reg, ltv_models=ltv)
    assert hist.steps == (2 if batch == "trajectory" else 1)
    np.testing.assert_allclose(hist.train_loss[0], data, rtol=1e-4)
    np.testing.assert_allclose(hist.penalties["exact"][0], np.mean(exact), rtol=1e-4)
    np.testing.assert_allclose(hist.penalties["smooth"][0], np.mean(smooth), rtol=1e-4)
    np.testing.assert_allclose(hist.penalties["sampled"][0], np.mean(sampled), rtol=1e-4)


@pytest.mark.parametrize("decoupled", [False, True])
def test_one_step_equals_closed_form_adam_with_weight_decay_on_weights_only(decoupled):
    """Adam's first step is ``p - lr * g / (|g| + eps)`` (bias corrections cancel). Coupled L2
    adds ``wd * W`` to the gradient of weight matrices; decoupled (AdamW) shrinks ``W`` by
    ``lr * wd * W`` first. Biases are never decayed. The gradient is taken here by autograd of
    the objective written from the public forward pass."""
    n, m = 3, 2
    A, B = random_stable_system(n, m, 0.1, seed=2)
    tr = linear_trajectory(A, B, 25, seed=0)
    model = small_model(n, m, members=(MemberSpec("sigmoid", 5), MemberSpec("swish", 4, 2)))
    model.set_normalization([tr])
    with torch.no_grad():  # nonzero biases, so decaying them would show
        for p in model.parameters():
            p.add_(0.1 * torch.randn(p.shape, generator=torch.Generator().manual_seed(3)))
    lr, wd, eps = 1e-3, 0.7, 1.0  # a large eps makes the step depend on the gradient size

    start = {k: v.detach().clone() for k, v in model.named_parameters()}
    xu = torch.tensor(np.concatenate(tr.inputs, 1), dtype=torch.float32)
    target = torch.tensor(tr.targets, dtype=torch.float32)
    pred = model.forward_torch(xu)
    loss = (((pred - target) / model.out_std) ** 2).sum(-1).mean(-1).sum()
    grads = dict(zip(start, torch.autograd.grad(loss, list(model.parameters()))))

    train_ensemble(model, [tr], TrainConfig(epochs=1, lr=lr, weight_decay=wd,
                                            decoupled_weight_decay=decoupled, adam_eps=eps,
                                            **QUIET))
    for name, p in model.named_parameters():
        is_weight = name.rsplit(".", 1)[-1] in ("W1", "W2", "Wo")
        g, p0 = grads[name], start[name]
        if is_weight and not decoupled:
            g = g + wd * p0
        expected = p0 - lr * g / (g.abs() + eps)
        if is_weight and decoupled:
            expected = expected - lr * wd * p0
        torch.testing.assert_close(p.detach(), expected, rtol=1e-5, atol=1e-6, msg=name)


def test_validation_loss_matches_independent_computation():
    n, m = 3, 2
    A, B = random_stable_system(n, m, 0.1, seed=4)
    train = [linear_trajectory(A, B, 40, seed=s) for s in (0, 1)]
    val = [linear_trajectory(A, B, 30, seed=s, noise=0.0) for s in (5, 6)]
    model = small_model(n, m)
    hist = train_ensemble(model, train, TrainConfig(epochs=5, **QUIET), validation=val)
    x = np.concatenate([v.x[:-1] for v in val])
    u = np.concatenate([v.u for v in val])
    x_next = np.concatenate([v.x[1:] for v in val])
    np.testing.assert_allclose(hist.val_loss[-1], normalized_sq_error(model, x, u, x_next),
                               rtol=1e-4)
    # the epochs record the same per-member and ensemble losses as a step budget
    pred = model.member_predictions(x, u)
    member = np.mean(np.sum(((pred - x_next) / model.out_std.numpy()) ** 2, -1), -1)
    np.testing.assert_allclose(hist.val_member_loss[-1], member, rtol=1e-4)
    ensemble = np.mean(np.sum(((pred.mean(0) - x_next) / model.out_std.numpy()) ** 2, -1))
    np.testing.assert_allclose(hist.val_ensemble_loss[-1], ensemble, rtol=1e-4)
    assert hist.eval_steps.tolist() == [2, 4, 6, 8, 10] and hist.n_train == 80


# ------------------------------------------------------------------------------------------
# warm start, resume, reproducibility
# ------------------------------------------------------------------------------------------


def test_resuming_with_optimizer_state_equals_continuous_training():
    n, m = 3, 2
    A, B = random_stable_system(n, m, 0.1, seed=5)
    trajs = [linear_trajectory(A, B, 30, seed=s) for s in (0, 1)]
    cfg = dict(batch="trajectory", shuffle=False, **QUIET)
    a = small_model(n, m)
    train_ensemble(a, trajs, TrainConfig(epochs=20, **cfg))
    b = small_model(n, m)
    h1 = train_ensemble(b, trajs, TrainConfig(epochs=12, **cfg))
    train_ensemble(b, trajs, TrainConfig(epochs=8, **cfg), optimizer_state=h1.optimizer_state)
    for (name, pa), (_, pb) in zip(a.named_parameters(), b.named_parameters()):
        torch.testing.assert_close(pa, pb, rtol=1e-6, atol=1e-7, msg=name)
    # without the optimizer state the run differs (Adam restarts)
    c = small_model(n, m)
    train_ensemble(c, trajs, TrainConfig(epochs=12, **cfg))
    train_ensemble(c, trajs, TrainConfig(epochs=8, **cfg))
    assert not torch.allclose(a.groups[0].W1, c.groups[0].W1, atol=1e-6)


def test_warm_start_on_grown_data_keeps_normalization():
    n, m = 3, 2
    A, B = random_stable_system(n, m, 0.1, seed=6)
    t1, t2 = (linear_trajectory(A, B, 30, seed=s) for s in (0, 1))
    model = small_model(n, m)
    h1 = train_ensemble(model, [t1], TrainConfig(epochs=3, **QUIET), RegularizationConfig.paper())
    stats = model.in_mean.clone()
    h2 = train_ensemble(model, [t1, t2], TrainConfig(epochs=3, **QUIET),
                        RegularizationConfig.paper(), optimizer_state=h1.optimizer_state)
    torch.testing.assert_close(model.in_mean, stats, rtol=0, atol=0)
    assert h2.steps == 6 and len(h2.ltv_models) == 2
    assert h2.optimizer_state["state"][0]["step"] == 3 + 6


def test_same_seed_same_result_with_every_random_component():
    n, m = 3, 2
    A, B = random_stable_system(n, m, 0.1, seed=7)
    trajs = [linear_trajectory(A, B, 30, seed=s) for s in (0, 1)]
    members = (MemberSpec("tanh", 8, dropout=0.2), MemberSpec("relu", 6, 2))
    reg = RegularizationConfig(sampled_weight=1.0, n_copies=2, smooth_weight=0.1)

    def run(seed):
        model = small_model(n, m, members=members)
        train_ensemble(model, trajs, TrainConfig(epochs=4, batch=16, seed=seed, **QUIET), reg)
        return model.groups[0].W1.detach().clone()

    torch.testing.assert_close(run(1), run(1), rtol=0, atol=0)
    assert not torch.equal(run(1), run(2))


def test_explicit_ltv_models_equal_fitted_ones():
    n, m = 3, 2
    A, B = random_stable_system(n, m, 0.1, seed=8)
    trajs = [linear_trajectory(A, B, 30, seed=s) for s in (0, 1)]
    reg = RegularizationConfig.paper(exact_weight=0.1, ltv_lambda=5.0)
    a, b = small_model(n, m), small_model(n, m)
    ha = train_ensemble(a, trajs, TrainConfig(epochs=3, **QUIET), reg)
    train_ensemble(b, trajs, TrainConfig(epochs=3, **QUIET), reg,
                   ltv_models=[fit_ltv(tr, 5.0) for tr in trajs])
    torch.testing.assert_close(a.groups[0].W1, b.groups[0].W1, rtol=0, atol=0)
    assert isinstance(ha, TrainHistory) and set(ha.penalties) == {"sampled", "exact"}


def test_progress_bar_and_zero_epochs(capsys):
    n, m = 3, 2
    A, B = random_stable_system(n, m, 0.1, seed=9)
    tr = linear_trajectory(A, B, 20, seed=0)
    model = small_model(n, m)
    hist = train_ensemble(model, [tr], TrainConfig(epochs=2, progress=True))
    assert "train_ensemble" in capsys.readouterr().err
    hist = train_ensemble(model, [tr], TrainConfig(epochs=0, **QUIET))
    assert hist.steps == 0 and hist.train_loss.shape == (0,)


# ------------------------------------------------------------------------------------------
# bad input
# ------------------------------------------------------------------------------------------


@pytest.mark.parametrize(
    "kwargs, match",
    [
        ({"epochs": -1}, "epochs"),
        ({"epochs": 2.5}, "epochs"),
        ({"lr": 0.0}, "lr"),
        ({"lr": float("nan")}, "lr"),
        ({"batch": "episode"}, "batch"),
        ({"batch": 0}, "batch"),
        ({"weight_decay": -1e-3}, "weight_decay"),
        ({"betas": (0.9, 1.0)}, "betas"),
        ({"adam_eps": 0.0}, "adam_eps"),
        ({"seed": "a"}, "seed"),
    ],
)
def test_train_config_rejects_bad_values(kwargs, match):
    with pytest.raises(ValueError, match=match):
        TrainConfig(**kwargs)


@pytest.mark.parametrize(
    "kwargs, match",
    [
        ({"sampled_weight": -1.0}, "sampled_weight"),
        ({"exact_weight": float("nan")}, "exact_weight"),
        ({"smooth_weight": -0.1}, "smooth_weight"),
        ({"sigma": -0.1}, "sigma"),
        ({"n_copies": 0}, "n_copies"),
        ({"ltv_lambda": -2.0}, "ltv_lambda"),
    ],
)
def test_regularization_config_rejects_bad_values(kwargs, match):
    with pytest.raises(ValueError, match=match):
        RegularizationConfig(**kwargs)


def test_train_ensemble_rejects_bad_inputs():
    n, m = 3, 2
    A, B = random_stable_system(n, m, 0.1, seed=10)
    tr = linear_trajectory(A, B, 20, seed=0)
    model = small_model(n, m)
    cfg = TrainConfig(epochs=1, **QUIET)
    with pytest.raises(ValueError, match="non-empty"):
        train_ensemble(model, [], cfg)
    with pytest.raises(ValueError, match="Trajectory"):
        train_ensemble(model, [(tr.x, tr.u)], cfg)
    with pytest.raises(ValueError, match=r"\(n, m\)"):
        train_ensemble(model, [Trajectory(np.zeros((5, 2)), np.zeros((4, 2)))], cfg)
    with pytest.raises(ValueError, match="validation"):
        train_ensemble(model, [tr], cfg, validation=[tr.x])
    with pytest.raises(ValueError, match="non-finite"):
        Trajectory(np.where(tr.x > 1, np.nan, tr.x), tr.u)  # NaN data never reach training
    with pytest.raises(ValueError, match="one LTV model per training trajectory"):
        train_ensemble(model, [tr], cfg, RegularizationConfig.paper(), ltv_models=[])
    short = fit_ltv(Trajectory(tr.x[:11], tr.u[:10]), 1.0)
    with pytest.raises(ValueError, match="needs at least"):
        train_ensemble(model, [tr], cfg, RegularizationConfig.paper(), ltv_models=[short])
    with pytest.raises(ValueError, match="optimizer_state"):
        train_ensemble(model, [tr], cfg, optimizer_state={"state": {}, "param_groups": []})
    with pytest.raises(ValueError, match="config must be a TrainConfig"):
        train_ensemble(model, [tr], {"epochs": 1})
    with pytest.raises(ValueError, match="model must be a DynamicsEnsemble"):
        train_ensemble(torch.nn.Linear(2, 2), [tr], cfg)


@settings(max_examples=40, deadline=None)
@given(
    name=st.sampled_from(["sampled_weight", "exact_weight", "smooth_weight", "sigma"]),
    value=st.floats(allow_nan=True, allow_infinity=True),
)
def test_regularization_weights_must_be_finite_and_nonnegative(name, value):
    if np.isfinite(value) and value >= 0:
        assert getattr(RegularizationConfig(**{name: value}), name) == value
    else:
        with pytest.raises(ValueError, match=name):
            RegularizationConfig(**{name: value})


# ------------------------------------------------------------------------------------------
# where the perturbed copies go (RegularizationConfig.copies_batch), and the diagnostic callback
# ------------------------------------------------------------------------------------------


def _copies_setup():
    n, m = 3, 2
    A, B = random_stable_system(n, m, 0.1, seed=3)
    trajs = [linear_trajectory(A, B, 30, seed=s, noise=0.05) for s in (0, 1)]
    ltv = [fit_ltv(tr, 3.0) for tr in trajs]
    model = small_model(n, m, seed=2)
    model.set_normalization(trajs)
    return trajs, ltv, model


@pytest.mark.parametrize("n_copies", [1, 2])
def test_own_copy_batches_take_the_originals_steps_and_losses(n_copies):
    """``copies_batch="own"`` (the original code): per epoch first one step per trajectory on
    its data, then one step per copy of each trajectory on the LTV-labelled copy alone. The
    per-step objective is recomputed by an independent loop: a copy of the initial model,
    torch's own Adam, the differentiable public forward pass and the same random stream."""
    import copy as copy_module

    trajs, ltv, model = _copies_setup()
    ref = copy_module.deepcopy(model)
    epochs, lr, seed, sigma, w = 3, 0.01, 7, 0.2, 0.7
    reg = RegularizationConfig(sampled_weight=w, sigma=sigma, n_copies=n_copies,
                               copies_batch="own")
    cfg = TrainConfig(epochs=epochs, lr=lr, shuffle=False, seed=seed, **QUIET)
    hist = train_ensemble(model, trajs, cfg, reg, ltv_models=ltv)
    assert hist.steps == epochs * len(trajs) * (1 + n_copies)
    assert hist.step_loss.shape == (hist.steps,)

    opt = torch.optim.Adam(ref.parameters(), lr=lr)
    out_std = ref.out_std.detach()
    rng = np.random.default_rng(seed)

    def objective(x, u, x_next):
        pred = ref.forward_torch(torch.tensor(x, dtype=torch.float32),
                                 torch.tensor(u, dtype=torch.float32))  # [K, T, n]
        err = (pred - torch.tensor(x_next, dtype=torch.float32)) / out_std
        return (err ** 2).sum(-1).mean(-1).sum()  # sum over members of the mean over points

    losses = []
    for _ in range(epochs):
        copies = [lm.sample_perturbed(tr.x, tr.u, sigma=sigma, n_copies=n_copies, seed=rng)
                  for lm, tr in zip(ltv, trajs)]
        batches = [(tr.x[:-1], tr.u, tr.x[1:], 1.0) for tr in trajs]
        batches += [(xt[c], ut[c], xnt[c], w) for xt, ut, xnt in copies for c in range(n_copies)]
        for x, u, x_next, weight in batches:
            loss = weight * objective(x, u, x_next)
            opt.zero_grad()
            loss.backward()
            opt.step()
            losses.append(float(loss.detach()))
    np.testing.assert_allclose(hist.step_loss, losses, rtol=1e-4)
    np.testing.assert_allclose(model.member_predictions(trajs[0].x[:-1], trajs[0].u),
                               ref.member_predictions(trajs[0].x[:-1], trajs[0].u), rtol=1e-4,
                               atol=1e-5)


def test_shared_copy_batches_keep_the_baselines_step_count():
    """Default ``"shared"``: copies join their trajectory's batch, so sampled JacProp takes as
    many optimizer steps as no regularization; ``"own"`` takes ``1 + n_copies`` times as many."""
    trajs, ltv, _ = _copies_setup()
    steps = {}
    for name, reg in [("none", RegularizationConfig()),
                      ("shared", RegularizationConfig.paper(n_copies=2)),
                      ("own", RegularizationConfig.paper(n_copies=2, copies_batch="own"))]:
        _, _, model = _copies_setup()
        for batch in ("trajectory", 25):
            cfg = TrainConfig(epochs=2, batch=batch, seed=1, **QUIET)
            steps[name, batch] = train_ensemble(model, trajs, cfg, reg, ltv_models=ltv).steps
    assert steps["none", "trajectory"] == steps["shared", "trajectory"] == 4
    assert steps["own", "trajectory"] == 3 * 4
    assert steps["none", 25] == steps["shared", 25] == 2 * 3  # 60 transitions in batches of 25
    assert steps["own", 25] == 3 * 6


def test_copies_batch_is_validated():
    with pytest.raises(ValueError, match="copies_batch"):
        RegularizationConfig(copies_batch="separate")


def test_callback_sees_every_epoch_in_eval_mode_and_changes_nothing():
    trajs, ltv, model = _copies_setup()
    _, _, twin = _copies_setup()
    seen = []

    def callback(epoch, m):
        seen.append((epoch, m.training))
        m.jacobians(trajs[0].x[:-1], trajs[0].u)  # a typical diagnostic

    cfg = TrainConfig(epochs=4, seed=3, **QUIET)
    reg = RegularizationConfig.paper()
    h1 = train_ensemble(model, trajs, cfg, reg, ltv_models=ltv, callback=callback)
    h2 = train_ensemble(twin, trajs, cfg, reg, ltv_models=ltv)
    assert seen == [(e, False) for e in range(4)]
    np.testing.assert_array_equal(h1.step_loss, h2.step_loss)
    with pytest.raises(ValueError, match="callback"):
        train_ensemble(twin, trajs, cfg, reg, ltv_models=ltv, callback=3)


def test_fast_copy_sampling_equals_the_ltv_models_own_sampling():
    """train_ensemble draws the copies of an ``LTVModel`` without per-call validation; a wrapper
    that only has ``A``, ``B`` and ``sample_perturbed`` takes the public method. Both must give
    bit-identical training (same draws, same arithmetic)."""

    class Wrapped:
        def __init__(self, lm):
            self.lm, self.A, self.B = lm, lm.A, lm.B

        def sample_perturbed(self, *a, **kw):
            return self.lm.sample_perturbed(*a, **kw)

    trajs, ltv, model = _copies_setup()
    _, _, twin = _copies_setup()
    cfg = TrainConfig(epochs=3, seed=4, **QUIET)
    reg = RegularizationConfig.paper(n_copies=2, sigma=0.3)
    h1 = train_ensemble(model, trajs, cfg, reg, ltv_models=ltv)
    h2 = train_ensemble(twin, trajs, cfg, reg, ltv_models=[Wrapped(lm) for lm in ltv])
    np.testing.assert_array_equal(h1.step_loss, h2.step_loss)
    np.testing.assert_array_equal(model.member_predictions(trajs[0].x[:-1], trajs[0].u),
                                  twin.member_predictions(trajs[0].x[:-1], trajs[0].u))


# ------------------------------------------------------------------------------------------
# the step budget: hold-out, early stopping, member data, probabilistic members
# ------------------------------------------------------------------------------------------


def test_step_budget_recorded_terms_match_independent_computation():
    """One step on a full batch with a negligible step size: the recorded data term and the
    exact and smoothness penalties are the values at the initial weights, recomputed from the
    float64 predictions and Jacobians (pairs never cross the trajectory boundary; a penalty of
    a minibatch is scaled to the mean terms per trajectory)."""
    n, m, trajs, ltv, model = two_trajectory_problem()
    data = np.mean([normalized_sq_error(model, tr.x[:-1], tr.u, tr.x[1:]) for tr in trajs])
    J = [np.concatenate(model.member_jacobians(tr.x[:-1], tr.u), -1) for tr in trajs]
    J_ltv = [np.concatenate([lm.A, lm.B], -1) for lm in ltv]
    exact = np.mean(np.concatenate([np.sum((j - jl) ** 2, (2, 3)) for j, jl in zip(J, J_ltv)],
                                   1)) * 30
    smooth = np.mean(np.concatenate([np.sum((j[:, 1:] - j[:, :-1]) ** 2, (2, 3)) for j in J],
                                    1)) * 29
    reg = RegularizationConfig(exact_weight=0.5, smooth_weight=2.0)
    hist = train_ensemble(model, trajs, TrainConfig(steps=1, batch=60, lr=1e-12, seed=3, **QUIET),
                          reg, ltv_models=ltv)
    assert hist.steps == 1 and list(hist.eval_steps) == [0, 1]
    np.testing.assert_allclose(hist.train_loss[1], data, rtol=1e-4)
    np.testing.assert_allclose(hist.penalties["exact"][1], exact, rtol=1e-4)
    np.testing.assert_allclose(hist.penalties["smooth"][1], smooth, rtol=1e-4)


def test_probabilistic_members_minimize_the_gaussian_nll_with_bound_penalty():
    """The objective of probabilistic members at the initial weights: ``mean_t sum_i
    (y - r)^2 exp(-logvar) + logvar`` summed over members, plus ``0.01 (sum max_logvar - sum
    min_logvar)``, recomputed from the float64 frozen model (mean and std in raw units)."""
    n, m = 3, 2
    A, B = random_stable_system(n, m, 0.1, seed=2)
    trajs = [linear_trajectory(A, B, 40, seed=s, noise=0.05) for s in (0, 1)]
    model = small_model(n, m, probabilistic=True)
    model.set_normalization(trajs)
    x = np.concatenate([tr.x[:-1] for tr in trajs])
    u = np.concatenate([tr.u for tr in trajs])
    x_next = np.concatenate([tr.x[1:] for tr in trajs])
    mean, std = model.member_predictions(x, u), model.member_std(x, u)
    out_std = model.out_std.numpy()
    lv = 2 * np.log(std / out_std)  # normalized log-variance
    nll = np.sum(((mean - x_next) / out_std) ** 2 * np.exp(-lv) + lv, -1).mean(-1).sum()
    bound = 0.01 * sum(float((g.max_logvar.sum() - g.min_logvar.sum()).detach())
                       for g in model.groups)
    hist = train_ensemble(model, trajs, TrainConfig(steps=1, batch=80, lr=1e-12, **QUIET))
    np.testing.assert_allclose(hist.step_loss[0], nll + bound, rtol=1e-4)
    np.testing.assert_allclose(hist.train_loss[1], nll / 2, rtol=1e-4)  # mean over members


def test_probabilistic_members_learn_a_state_dependent_noise_level():
    """Known solution: x+ = 0.8 x + 0.5 u + s(x) e with s = 0.02 for x < 0 and 0.12 for x > 0;
    the learned aleatoric std recovers s on both sides (within 25 %)."""
    rng = np.random.default_rng(0)
    trajs = []
    for _ in range(8):
        x, u = np.zeros((101, 1)), rng.uniform(-1, 1, (100, 1))
        for t in range(100):
            s = 0.02 + 0.1 * (x[t, 0] > 0)
            x[t + 1] = 0.8 * x[t] + 0.5 * u[t] + s * rng.standard_normal()
        trajs.append(Trajectory(x, u))
    model = DynamicsEnsemble(EnsembleConfig(1, 1, members=(MemberSpec("swish", 32, 2),) * 2,
                                            probabilistic=True))
    train_ensemble(model, trajs, TrainConfig(steps=800, batch=128, lr=5e-3, **QUIET))
    std = model.member_std(np.array([[-0.4], [-0.2], [0.2], [0.4]]), np.zeros((4, 1)))[..., 0]
    np.testing.assert_allclose(std, np.broadcast_to([0.02, 0.02, 0.12, 0.12], std.shape),
                               rtol=0.25)


@pytest.mark.parametrize("N_traj", [2, 20])
def test_a_step_budget_takes_its_steps_whatever_the_data_size(N_traj):
    A, B = random_stable_system(3, 2, 0.1, seed=4)
    trajs = [linear_trajectory(A, B, 30, seed=s) for s in range(N_traj)]
    model = small_model()
    hist = train_ensemble(model, trajs, TrainConfig(steps=37, batch=16, eval_every=10, **QUIET))
    assert hist.steps == 37 and len(hist.step_loss) == 37
    assert list(hist.eval_steps) == [0, 10, 20, 30, 37]
    assert all(int(s["step"]) == 37 for s in hist.optimizer_state["state"].values())


def test_the_holdout_split_is_stable_and_never_trained_on():
    """The split is a prefix-stable function of the transition index; changing the next states
    of held-out transitions changes nothing in training (normalization set beforehand), while
    changing one trained transition does."""
    big, small = holdout_mask(500, 0.2), holdout_mask(300, 0.2)
    np.testing.assert_array_equal(big[:300], small)
    assert 0.15 < big.mean() < 0.25
    A, B = random_stable_system(3, 2, 0.1, seed=5)
    trajs = [linear_trajectory(A, B, 40, seed=s) for s in (0, 1, 2)]
    held = holdout_mask(120, 0.25)

    def trained(x_next_change):
        xs = [tr.x.copy() for tr in trajs]
        for j in x_next_change:
            xs[j // 40][j % 40 + 1] += 5.0
        data = [Trajectory(x, tr.u) for x, tr in zip(xs, trajs)]
        model = small_model(seed=1)
        model.set_normalization(trajs)
        h = train_ensemble(model, data, TrainConfig(steps=30, batch=16, holdout=0.25, **QUIET))
        assert (h.n_train, h.n_holdout) == (120 - held.sum(), held.sum())
        return torch.cat([p.detach().flatten() for p in model.parameters()])

    base = trained([])
    # held-out rows whose successor is not itself a trained row's input (x[t+1] is the input
    # of transition t+1)
    change = [j for j in np.flatnonzero(held) if j % 40 == 39 or held[j + 1]]
    assert change
    torch.testing.assert_close(trained(change), base, rtol=0, atol=0)
    kept = int(np.flatnonzero(~held)[0])
    assert not torch.equal(trained([kept]), base)


def overfitting_setup():
    """Few noisy transitions, a wide network, a large step size: the validation loss turns up."""
    A, B = random_stable_system(3, 2, 0.1, seed=6)
    trajs = [linear_trajectory(A, B, 25, seed=s, noise=0.2) for s in (0, 1)]
    model = small_model(members=(MemberSpec("tanh", 64, 2), MemberSpec("elu", 48, 2),
                                 MemberSpec("swish", 64, 2)), seed=2)
    return model, trajs


@pytest.mark.parametrize("mode", ["member", "ensemble"])
def test_early_stopping_stops_and_restores_the_best_weights(mode):
    model, trajs = overfitting_setup()
    cfg = TrainConfig(steps=3000, batch=16, lr=1e-2, holdout=0.3, eval_every=20, patience=5,
                      early_stopping=mode, **QUIET)
    hist = train_ensemble(model, trajs, cfg)
    assert hist.stopped_early and hist.steps < 3000
    assert hist.steps == hist.eval_steps[-1]
    held = holdout_mask(50, 0.3)
    data = [tr for tr in trajs]
    x = np.concatenate([tr.x[:-1] for tr in data])[held]
    u = np.concatenate([tr.u for tr in data])[held]
    x_next = np.concatenate([tr.x[1:] for tr in data])[held]
    pred = model.member_predictions(x, u)
    sq = ((pred - x_next) / model.out_std.numpy()) ** 2
    if mode == "member":  # every member at its own best evaluation
        np.testing.assert_allclose(sq.sum(-1).mean(-1), hist.val_member_loss.min(0), rtol=1e-4)
        best = hist.val_member_loss.argmin(0)
        np.testing.assert_array_equal(hist.best_steps, hist.eval_steps[best])
    else:  # the whole ensemble at the evaluation of the best ensemble-mean loss
        ens = (((pred.mean(0) - x_next) / model.out_std.numpy()) ** 2).sum(-1).mean()
        np.testing.assert_allclose(ens, hist.val_ensemble_loss.min(), rtol=1e-4)
        assert len(set(hist.best_steps)) == 1
    assert hist.val_member_loss.min(0).max() < hist.val_member_loss[-1].max()  # it overfitted


def test_members_differ_by_data_order_or_bootstrap():
    """Members with identical initial weights stay identical with shared minibatches and
    become different with their own order or bootstrap sample."""
    A, B = random_stable_system(3, 2, 0.1, seed=7)
    trajs = [linear_trajectory(A, B, 40, seed=s) for s in (0, 1)]
    spread = {}
    for mode in ("shared", "order", "bootstrap"):
        model = small_model(members=(MemberSpec("tanh", 8),) * 3)
        with torch.no_grad():
            for p in model.parameters():
                p.copy_(p[:1].expand_as(p))
        train_ensemble(model, trajs, TrainConfig(steps=20, batch=16, member_data=mode, **QUIET))
        spread[mode] = float(model.groups[0].W1.detach().std(0).max())
    # (shared: identical up to the rounding of the batched products)
    assert spread["shared"] < 1e-6 and spread["order"] > 1e-3 and spread["bootstrap"] > 1e-3
    gen = torch.Generator().manual_seed(0)
    rows = torch.arange(50)
    boot = _MemberStreams(rows, 3, 10, "bootstrap", gen)
    assert all(p.numel() == 50 and p.unique().numel() < 50 for p in boot.pools)
    order = _MemberStreams(rows, 3, 10, "order", gen)
    passes = torch.cat([order.next() for _ in range(5)], 1)  # one pass each, own permutation
    assert all(sorted(r.tolist()) == list(range(50)) for r in passes)
    assert not torch.equal(passes[0], passes[1])


@pytest.mark.parametrize("mode", ["order", "bootstrap"])
def test_step_budget_same_seed_same_result(mode):
    A, B = random_stable_system(3, 2, 0.1, seed=8)
    trajs = [linear_trajectory(A, B, 30, seed=s) for s in (0, 1)]
    reg = RegularizationConfig(sampled_weight=1.0, smooth_weight=0.1)
    out = []
    for seed in (4, 4, 5):
        model = small_model(members=(MemberSpec("tanh", 8, dropout=0.1), MemberSpec("elu", 6, 3)),
                            probabilistic=True)
        train_ensemble(model, trajs, TrainConfig(steps=15, batch=8, seed=seed, holdout=0.2,
                                                 patience=2, eval_every=5, member_data=mode,
                                                 **QUIET), reg)
        out.append(torch.cat([p.detach().flatten() for p in model.parameters()]))
    torch.testing.assert_close(out[0], out[1], rtol=0, atol=0)
    assert not torch.equal(out[0], out[2])


@pytest.mark.slow
def test_sampled_jacprop_with_a_step_budget_lowers_the_jacobian_error():
    """The paper's claim (the first test of this file) with the step budget: 2000 steps of 100
    transitions (the epochs' optimizer steps), fresh perturbations every step. Measured: none
    0.0371, sampled 0.0295 (1000 steps: 0.0344, 0.0316, the overfitting not yet there)."""
    n, m, dt = 4, 2, 0.02
    A, B = random_stable_system(n, m, dt, seed=0)
    train = [linear_trajectory(A, B, 100, seed=s) for s in (0, 1)]
    val = linear_trajectory(A, B, 200, seed=50, noise=0.0)
    J_true = np.broadcast_to(np.concatenate([A, B], 1), (val.T, n, n + m))
    errors = {}
    for name, reg in [("none", RegularizationConfig()), ("sampled", RegularizationConfig.paper())]:
        model = DynamicsEnsemble(EnsembleConfig(n, m, seed=0))
        train_ensemble(model, train, TrainConfig(steps=2000, batch=100, **QUIET), reg)
        errors[name] = jacobian_error(J_true, model.member_jacobians(val.x[:-1], val.u))
    print("Jacobian errors:", errors)
    assert errors["sampled"] < 0.9 * errors["none"]


@pytest.mark.parametrize("kwargs, match", [
    ({"steps": 0}, "steps must be an integer >= 1"),
    ({"steps": 10, "batch": 8, "holdout": 1.0}, "holdout must be in"),
    ({"steps": 10, "batch": 8, "holdout": -0.1}, "holdout"),
    ({"steps": 10, "batch": 8, "patience": 0}, "patience must be an integer >= 1"),
    ({"steps": 10, "batch": 8, "eval_every": 0}, "eval_every"),
    ({"steps": 10, "batch": 8, "member_data": "bagging"}, "member_data must be one of"),
    ({"steps": 10, "batch": 8, "early_stopping": "all"}, "early_stopping must be one of"),
    ({"holdout": 0.1}, "batch='trajectory' is the epoch schedule's; holdout=0.1 need an int"),
    ({"steps": 5, "member_data": "order"}, "member_data='order' need an int minibatch size"),
])
def test_step_budget_settings_are_validated(kwargs, match):
    with pytest.raises(ValueError, match=match):
        TrainConfig(**kwargs)


def test_patience_needs_held_out_data():
    A, B = random_stable_system(3, 2, 0.1, seed=9)
    with pytest.raises(ValueError, match="patience needs held-out data"):
        train_ensemble(small_model(), [linear_trajectory(A, B, 10, seed=0)],
                       TrainConfig(steps=5, batch=4, patience=2, **QUIET))


def test_epochs_with_early_stopping_run_the_step_loop_for_epochs_passes():
    """The hold-out / early-stopping / member-data machinery with the epoch schedule: the step
    loop with a budget of ``epochs`` passes over the training rows."""
    A, B = random_stable_system(3, 2, 0.1, seed=10)
    trajs = [linear_trajectory(A, B, 30, seed=s) for s in (0, 1)]
    cfg = TrainConfig(epochs=3, batch=16, holdout=0.2, member_data="order", **QUIET)
    assert cfg.uses_step_loop and not TrainConfig(epochs=3, batch=16).uses_step_loop
    hist = train_ensemble(small_model(), trajs, cfg)
    assert hist.steps == 3 * int(np.ceil(hist.n_train / 16)) and hist.n_holdout > 0


@pytest.mark.parametrize("reg, exact", [(RegularizationConfig(), True),
                                        (RegularizationConfig(exact_weight=0.1), True),
                                        (RegularizationConfig(smooth_weight=0.1), False)])
def test_the_epoch_schedule_is_a_step_budget_of_the_same_loop(reg, exact):
    """``epochs=E`` with shared shuffled minibatches of ``b`` rows (``N`` a multiple of ``b``)
    and ``steps=E N / b`` draw the same permutations from the same seed, so the one loop takes
    the same batches: bit-identical step losses, weights and per-epoch records. The smoothness
    term's pairs are gathered by the epochs and masked by the step budget: the step losses
    agree to float rounding."""
    A, B = random_stable_system(3, 2, 0.1, seed=1)
    trajs = [linear_trajectory(A, B, 30, seed=s, noise=0.05) for s in (0, 1)]  # N = 60
    epochs, steps = small_model(), small_model()
    h_e = train_ensemble(epochs, trajs, TrainConfig(epochs=4, batch=20, seed=3, **QUIET), reg)
    h_s = train_ensemble(steps, trajs, TrainConfig(steps=12, batch=20, eval_every=3, seed=3,
                                                   **QUIET), reg)
    assert h_e.steps == h_s.steps == 12
    assert h_e.eval_steps.tolist() == h_s.eval_steps[1:].tolist() == [3, 6, 9, 12]
    if exact:
        np.testing.assert_array_equal(h_e.step_loss, h_s.step_loss)
        np.testing.assert_array_equal(h_e.train_loss, h_s.train_loss[1:])
        for p_e, p_s in zip(epochs.parameters(), steps.parameters()):
            torch.testing.assert_close(p_e, p_s, rtol=0, atol=0)
    else:
        np.testing.assert_allclose(h_e.step_loss, h_s.step_loss, rtol=1e-5)
        np.testing.assert_allclose(h_e.penalties["smooth"], h_s.penalties["smooth"][1:],
                                   rtol=1e-5)
