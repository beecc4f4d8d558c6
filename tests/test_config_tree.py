"""The AgentConfig tree: the library's own configs as its sections (no translation), JSON round
trips, the old flat format (before the tree) loads to the same tree, errors name the dotted
field, and an old-format checkpoint resumes exactly."""

from __future__ import annotations

import dataclasses
import json
from pathlib import Path

import gymnasium as gym
import pytest
from hypothesis import given, settings
from hypothesis import strategies as st

import envs  # noqa: F401  (registers mbtsr/TwoLinkArm-v0)
from agents.checkpoint import load_checkpoint, save_checkpoint
from agents.config import (
    SECTIONS,
    AgentConfig,
    CollectionConfig,
    EvaluationConfig,
    PlannerConfig,
    from_flat,
)
from agents.jacprop_agent import JacPropAgent
from mbtsr.cem import CEMOptions
from mbtsr.ensemble import EnsembleConfig, MemberSpec, ModelConfig, default_size
from mbtsr.training import RegularizationConfig, TrainConfig

REPO = Path(__file__).resolve().parents[1]

#: ``AgentConfig().to_dict()`` before the tree (the old flat format, as checkpoints stored it)
OLD_DEFAULTS = {
    "n_excitation_episodes": 2, "excitation": "filtered_gaussian", "excitation_scale": 0.3,
    "excitation_window": 8, "exploration_std": 0.1, "episode_steps": None, "formulation": "g",
    "ensemble_size": 4, "hidden_width": 20, "hidden_layers": 1,
    "activations": ["elu", "sigmoid", "tanh", "swish"], "epochs_per_episode": 150, "lr": 0.003,
    "batch_size": 256, "weight_decay": 0.0, "regularization": "sampled", "jacprop_weight": 1.0,
    "jacobian_penalty": 0.01, "perturbation_sigma": 0.1, "n_perturbed_copies": 1,
    "renormalize": True, "ltv_lambda": "auto", "ltv_prior": 0.01, "planner": "ilqr",
    "cem_samples": 200, "cem_elites": 20, "cem_iterations": 3, "replan_every": 1, "horizon": 30,
    "ilqr_iterations": 2, "first_plan_iterations": 20, "terminal_weight": 1.0, "eval_every": 4,
    "eval_episodes": 3, "eval_seed": 1000, "solved_ratio": 1.2, "solved_return": None,
    "stop_when_solved": False, "eval_early_exit": True, "oracle_cache_dir": None, "seed": 0,
    "run_dir": None, "checkpoint": True, "tensorboard": True, "video": False, "video_every": 5,
    "jacobian_error": True, "progress": True, "torch_threads": 0,
}


def test_the_sections_are_the_library_configs():
    cfg = AgentConfig()
    assert type(cfg.model) is ModelConfig and type(cfg.training) is TrainConfig
    assert type(cfg.regularization) is RegularizationConfig
    assert {name: type(getattr(cfg, name)) for name in SECTIONS} == SECTIONS
    # the paper's sampled JacProp; a step budget with early stopping; a model sized by the task
    assert cfg.training == TrainConfig(steps=500, lr=1e-3, batch=256, holdout=0.1,
                                       eval_every=50, patience=5, early_stopping="member",
                                       member_data="order", progress=False)
    assert cfg.regularization == RegularizationConfig(sampled_weight=1.0, ltv_lambda=None)
    layers, width = default_size(11, 2)
    assert cfg.model.ensemble_config(11, 2, seed=5) == EnsembleConfig(
        state_dim=11, action_dim=2, seed=5, formulation="g", normalize=True,
        members=(MemberSpec("swish", width, layers),) * 4)
    assert AgentConfig(model=ModelConfig.paper()).model.ensemble_config(4, 2, seed=5) == \
        EnsembleConfig(state_dim=4, action_dim=2, seed=5)  # the paper's nominal ensemble


#: ``AgentConfig().to_dict()`` of the tree before the scaled model and the step budget (as
#: checkpoints of that time stored it)
OLD_TREE = {
    "collection": {"n_excitation_episodes": 2, "excitation": "filtered_gaussian",
                   "excitation_scale": 0.3, "excitation_window": 8, "exploration_std": 0.1,
                   "episode_steps": None},
    "model": {"formulation": "g", "ensemble_size": 4, "hidden_width": 20, "hidden_layers": 1,
              "activations": ["elu", "sigmoid", "tanh", "swish"]},
    "training": {"epochs": 150, "lr": 0.003, "batch": 256, "weight_decay": 0.0,
                 "decoupled_weight_decay": False, "betas": [0.9, 0.999], "adam_eps": 1e-08,
                 "shuffle": True, "seed": 0, "progress": False},
    "regularization": {"sampled_weight": 1.0, "sigma": 0.1, "n_copies": 1,
                       "copies_batch": "shared", "exact_weight": 0.0, "smooth_weight": 0.0,
                       "ltv_lambda": None, "ltv_affine": False},
    "planner": {"horizon": 30, "replan_every": 1, "kind": "ilqr", "terminal_weight": 1.0,
                "ilqr_iterations": 2, "first_plan_iterations": 20,
                "cem": {"samples": 200, "elites": 20, "iterations": 3, "init_std": 0.5,
                        "smoothing": 0.1, "tol_std": 0.001, "seed": 0,
                        "max_state_norm": 100000000.0, "termination_cost": 0.0}},
    "evaluation": {"every": 4, "episodes": 3, "seed": 1000, "early_exit": True,
                   "solved_ratio": 1.2, "solved_return": None, "stop_when_solved": False,
                   "oracle_cache_dir": None},
    "seed": 0, "renormalize": True, "ltv_prior": 0.01, "run_dir": None, "checkpoint": True,
    "tensorboard": True, "video": False, "video_every": 5, "jacobian_error": True,
    "progress": True, "torch_threads": 0,
}


def test_an_old_tree_config_keeps_its_model_and_epoch_schedule():
    """A config saved before the step budget (no ``training.steps`` and no
    ``model.probabilistic``) loads to what it meant: the paper's ensemble trained 150 epochs per
    update, CEM with one particle, planning on the mean."""
    cfg = AgentConfig.from_dict(OLD_TREE)
    assert cfg.training == TrainConfig(epochs=150, lr=3e-3, batch=256, progress=False)
    assert cfg.training.steps is None
    assert cfg.model == ModelConfig.paper()
    assert cfg.planner == PlannerConfig()
    assert cfg.planner.cem.particles == 1 and cfg.planner.propagation == "mean"
    assert from_flat(OLD_DEFAULTS) == cfg  # the old flat format means the same


def test_the_agent_uses_the_sections_as_they_are():
    cfg = AgentConfig.default({"model.ensemble_size": 3, "model.hidden_width": 9,
                               "model.hidden_layers": 1,
                               "model.activations": ("tanh", "elu"), "training.batch": 32,
                               "regularization.sigma": 0.2}, regularization="exact", seed=5,
                              progress=False, tensorboard=False, checkpoint=False)
    agent = JacPropAgent(gym.make("mbtsr/TwoLinkArm-v0"), cfg)
    assert agent.ensemble_config.members == (
        MemberSpec("tanh", 9, 1), MemberSpec("elu", 9, 1), MemberSpec("tanh", 9, 1))
    assert agent.ensemble_config.seed == 5
    assert agent._train_configs(3) == (dataclasses.replace(cfg.training, seed=3),
                                       cfg.regularization)
    assert agent._train_configs(3)[1] == RegularizationConfig(exact_weight=0.01, sigma=0.2,
                                                              ltv_lambda=None)


def test_model_config_builds_the_ensemble():
    cfg = ModelConfig(formulation="f", ensemble_size=2, hidden_width=5,
                      activations=("elu", "sigmoid"))
    model = cfg.build(3, 1, seed=2)
    assert model.config == cfg.ensemble_config(3, 1, seed=2)
    assert model.config.n_members == 2 and model.config.members[1].activation == "sigmoid"


@pytest.mark.parametrize("name, weights", [
    ("sampled", {"sampled_weight": 1.0}), ("exact", {"exact_weight": 0.01}),
    ("smooth", {"smooth_weight": 0.01}), ("none", {}),
])
def test_the_regularizer_by_name(name, weights):
    reg = AgentConfig(regularization=name).regularization
    assert reg == RegularizationConfig(ltv_lambda=None, **weights)
    assert reg.kind == name
    assert RegularizationConfig.named(name, **({} if name == "none" else {"weight": 0.5})).kind \
        == name
    cfg = AgentConfig().replace({"regularization": name, "regularization.sigma": 0.3})
    assert cfg.regularization == dataclasses.replace(reg, sigma=0.3)


def test_kind_of_combined_regularizers():
    assert RegularizationConfig(sampled_weight=1.0, smooth_weight=0.1).kind == "sampled+smooth"


def test_short_calls():
    cfg = AgentConfig(regularization="none", planner="cem")
    assert cfg.planner == PlannerConfig(kind="cem") and cfg.regularization.kind == "none"
    assert cfg.replace({"planner.horizon": 50}).planner == PlannerConfig(kind="cem", horizon=50)
    assert AgentConfig.default({"planner.horizon": 50}, regularization="none", seed=3) == \
        AgentConfig(regularization="none", planner=PlannerConfig(horizon=50), seed=3)


# ---------------------------------------------------------------------------- JSON round trip
@settings(max_examples=30, deadline=None)
@given(
    width=st.integers(1, 64), batch=st.one_of(st.just("trajectory"), st.integers(1, 512)),
    reg=st.sampled_from(["sampled", "exact", "smooth", "none"]),
    lam=st.one_of(st.none(), st.floats(1e-3, 1e3)), planner=st.sampled_from(["ilqr", "cem"]),
    solved_return=st.one_of(st.none(), st.floats(-1e3, 1e3)),
    acts=st.lists(st.sampled_from(["elu", "tanh", "relu"]), min_size=1, max_size=3),
    betas=st.tuples(st.floats(0, 0.99), st.floats(0, 0.999)),
)
def test_the_tree_round_trips_through_json(width, batch, reg, lam, planner, solved_return,
                                           acts, betas):
    cfg = AgentConfig.default({
        "model.hidden_width": width, "model.activations": tuple(acts),
        **({"training": TrainConfig(batch=batch, epochs=5, progress=False)}
           if batch == "trajectory" else {"training.batch": batch}),
        "training.betas": betas, "regularization.ltv_lambda": lam,
        "evaluation.solved_return": solved_return, "collection.episode_steps": 40,
    }, regularization=reg, planner=planner, run_dir="runs/x")
    text = cfg.to_json()
    assert isinstance(json.loads(text)["model"], dict)  # nested, not flat
    assert AgentConfig.from_json(text) == cfg
    assert AgentConfig.from_dict(json.loads(text)) == cfg


def test_unknown_fields_are_named():
    with pytest.raises(ValueError, match="nonsense"):
        AgentConfig.from_dict({**AgentConfig().to_dict(), "nonsense": 1})
    with pytest.raises(ValueError, match=r"model\.depth"):
        AgentConfig.from_dict({**AgentConfig().to_dict(), "model": {"depth": 2}})
    with pytest.raises(ValueError, match=r"unknown AgentConfig field 'planner\.depth'"):
        AgentConfig().replace({"planner.depth": 2})
    with pytest.raises(ValueError, match=r"'horizon' \(a field before the tree: now "
                                         r"'planner\.horizon'\)"):
        AgentConfig().replace({"horizon": 2})


@pytest.mark.parametrize("bad", [[1, 2], "horizon", 3, None])
def test_from_dict_and_from_json_refuse_a_non_dict(bad):
    with pytest.raises(ValueError, match="AgentConfig.from_dict needs a dict"):
        AgentConfig.from_dict(bad)
    with pytest.raises(ValueError, match="AgentConfig.from_dict needs a dict"):
        AgentConfig.from_json(json.dumps(bad))


# ---------------------------------------------------------------------------- the old flat format
def test_the_old_flat_defaults_load_to_the_default_tree_of_their_time():
    then = AgentConfig(model=ModelConfig.paper(),
                       training=TrainConfig(epochs=150, lr=3e-3, batch=256, progress=False))
    assert from_flat(OLD_DEFAULTS) == then
    assert AgentConfig.from_dict(OLD_DEFAULTS) == then  # detected
    assert from_flat({}) == then  # missing keys: the defaults of that time


def test_every_old_flat_field_lands_on_its_tree_field():
    old = {**OLD_DEFAULTS, "n_excitation_episodes": 3, "excitation": "multisine",
           "excitation_scale": 0.5, "excitation_window": 4, "exploration_std": 0.0,
           "episode_steps": 50, "formulation": "f", "ensemble_size": 2, "hidden_width": 7,
           "hidden_layers": 2, "activations": ["tanh"], "epochs_per_episode": 11, "lr": 0.01,
           "batch_size": 0, "weight_decay": 1e-4, "regularization": "smooth",
           "jacprop_weight": 0.3, "jacobian_penalty": 0.2, "perturbation_sigma": 0.05,
           "n_perturbed_copies": 2, "renormalize": False, "ltv_lambda": 4.0, "ltv_prior": 0.0,
           "planner": "cem", "cem_samples": 50, "cem_elites": 5, "cem_iterations": 2,
           "replan_every": 3, "horizon": 12, "ilqr_iterations": 4, "first_plan_iterations": 9,
           "terminal_weight": 2.0, "eval_every": 2, "eval_episodes": 5, "eval_seed": 7,
           "solved_ratio": 1.5, "solved_return": -10.0, "stop_when_solved": True,
           "eval_early_exit": False, "oracle_cache_dir": "cache", "seed": 9, "run_dir": "r",
           "checkpoint": False, "tensorboard": False, "video": True, "video_every": 2,
           "jacobian_error": False, "progress": False, "torch_threads": 1}
    expected = AgentConfig(
        collection=CollectionConfig(3, "multisine", 0.5, 4, 0.0, 50),
        model=ModelConfig("f", 2, 7, 2, ("tanh",)),
        training=TrainConfig(epochs=11, lr=0.01, batch="trajectory", weight_decay=1e-4,
                             progress=False),
        regularization=RegularizationConfig(smooth_weight=0.2, sigma=0.05, n_copies=2,
                                            ltv_lambda=4.0),
        planner=PlannerConfig(kind="cem", horizon=12, replan_every=3, ilqr_iterations=4,
                              first_plan_iterations=9, terminal_weight=2.0,
                              cem=CEMOptions(samples=50, elites=5, iterations=2)),
        evaluation=EvaluationConfig(every=2, episodes=5, seed=7, solved_ratio=1.5,
                                    solved_return=-10.0, stop_when_solved=True,
                                    early_exit=False, oracle_cache_dir="cache"),
        seed=9, renormalize=False, ltv_prior=0.0, run_dir="r", checkpoint=False,
        tensorboard=False, video=True, video_every=2, jacobian_error=False, progress=False,
        torch_threads=1)
    assert from_flat(old) == expected
    # the weight follows the method: jacprop_weight for sampled, jacobian_penalty for exact
    assert from_flat({**old, "regularization": "sampled"}).regularization.sampled_weight == 0.3
    assert from_flat({**old, "regularization": "exact"}).regularization.exact_weight == 0.2
    with pytest.raises(ValueError, match="unknown AgentConfig field"):
        from_flat({**old, "hidden_widht": 3})


def test_the_stored_benchmark_configs_load():
    """docs/benchmark.json stores the old flat agent configs of its runs."""
    saved = json.loads((REPO / "docs" / "benchmark.json").read_text())["methods"]
    for method, kind in (("jacprop", "sampled"), ("none", "none")):
        flat = saved[method]["agent_config"]
        cfg = AgentConfig.from_dict(flat)
        assert cfg.regularization.kind == kind
        assert cfg.training.epochs == flat["epochs_per_episode"]
        assert cfg.planner.horizon == flat["horizon"]
        assert cfg.evaluation.solved_ratio == flat["solved_ratio"]


def test_an_old_format_checkpoint_resumes_exactly(tmp_path):
    """A checkpoint whose agent_config is the old flat JSON loads to the same tree, and the
    next episode is bit-identical to resuming the new-format checkpoint."""
    flat = {**OLD_DEFAULTS, "n_excitation_episodes": 1, "episode_steps": 20,
            "ensemble_size": 2, "hidden_width": 8, "epochs_per_episode": 5, "horizon": 5,
            "ilqr_iterations": 1, "first_plan_iterations": 3, "eval_every": 0,
            "ltv_lambda": 2.0, "tensorboard": False, "progress": False, "torch_threads": 1,
            "checkpoint": False}
    cfg = from_flat(flat)
    env = gym.make("mbtsr/TwoLinkArm-v0")
    agent = JacPropAgent(env, cfg)
    agent.learn(2, progress_bar=False)
    new = agent.save(tmp_path / "new.pt")
    payload = load_checkpoint(new)
    assert json.loads(payload["agent_config"]) == cfg.to_dict()
    payload["agent_config"] = json.dumps(flat)
    old = save_checkpoint(tmp_path / "old.pt", payload)
    rows = []
    for path in (new, old):
        resumed = JacPropAgent.load(path, env=gym.make("mbtsr/TwoLinkArm-v0"))
        assert resumed.config == cfg
        resumed.learn(1, progress_bar=False)
        rows.append({k: v for k, v in resumed.logger_rows[-1].items()
                     if not k.startswith("time")})
    assert rows[0] == rows[1]
    assert rows[0]["phase"] == "mpc"


# ---------------------------------------------------------------------------- errors
INT_MINIMA = {"model.hidden_width": 1, "model.ensemble_size": 1, "training.epochs": 1,
              "planner.horizon": 2, "planner.cem.samples": 2, "evaluation.episodes": 1,
              "collection.excitation_window": 1, "regularization.n_copies": 1}


@settings(max_examples=40, deadline=None)
@given(field=st.sampled_from(sorted(INT_MINIMA)), below=st.integers(1, 10**9))
def test_bad_values_name_the_dotted_field(field, below):
    with pytest.raises(ValueError) as err:
        AgentConfig().replace({field: INT_MINIMA[field] - below})
    assert str(err.value).startswith(field + " must be")


@settings(max_examples=12, deadline=None)
@given(field=st.sampled_from(sorted(INT_MINIMA)), below=st.integers(1, 10**6))
def test_bad_nested_cli_values_exit_2_with_one_line_naming_the_field(field, below):
    import contextlib
    import io

    from agents.experiments import train_agent

    flag = "--" + field.replace("_", "-")
    err = io.StringIO()
    with contextlib.redirect_stderr(err), pytest.raises(SystemExit) as exc:
        train_agent.parse([flag, str(INT_MINIMA[field] - below)])
    text = err.getvalue()
    assert exc.value.code == 2 and text.count("\n") == 1 and "Traceback" not in text
    assert f"error: {field} must be" in text, text


def test_sections_reject_the_wrong_type_and_training_seed():
    with pytest.raises(ValueError, match="model must be a mbtsr.ensemble.ModelConfig"):
        AgentConfig(model={"hidden_width": 3})
    with pytest.raises(ValueError, match="training.seed must be 0"):
        AgentConfig().replace({"training.seed": 1})
    with pytest.raises(ValueError, match="regularization.ltv_affine"):
        AgentConfig().replace({"regularization.ltv_affine": True})
