"""The AgentConfig tree: the library's own configs as its sections (no translation), JSON round
trips, and errors name the dotted field."""

from __future__ import annotations

import dataclasses
import json

import gymnasium as gym
import pytest
from hypothesis import given, settings
from hypothesis import strategies as st

import envs  # noqa: F401  (registers mbtsr/TwoLinkArm-v0)
from agents.config import (
    SECTIONS,
    AgentConfig,
    EvaluationConfig,
    PlannerConfig,
)
from agents.jacprop_agent import JacPropAgent
from mbtsr.ensemble import EnsembleConfig, MemberSpec, ModelConfig, default_size
from mbtsr.training import RegularizationConfig, TrainConfig


def test_the_sections_are_the_library_configs():
    cfg = AgentConfig()
    assert type(cfg.model) is ModelConfig and type(cfg.training) is TrainConfig
    assert type(cfg.regularization) is RegularizationConfig
    assert {name: type(getattr(cfg, name)) for name in SECTIONS} == SECTIONS
    # the plain baseline (no regularizer); a step budget with early stopping; a model sized by
    # the task
    assert cfg.training == TrainConfig(steps=4000, lr=1e-3, batch=256, holdout=0.1,
                                       eval_every=50, patience=10, early_stopping="member",
                                       member_data="order", progress=False)
    assert cfg.regularization == RegularizationConfig(sampled_weight=0.0, ltv_lambda=None)
    assert cfg.regularization.kind == "none"
    layers, width = default_size(11, 2)
    assert cfg.model.ensemble_config(11, 2, seed=5) == EnsembleConfig(
        state_dim=11, action_dim=2, seed=5, formulation="g", normalize=True,
        members=(MemberSpec("swish", width, layers),) * 4)
    assert AgentConfig(model=ModelConfig.paper()).model.ensemble_config(4, 2, seed=5) == \
        EnsembleConfig(state_dim=4, action_dim=2, seed=5)  # the paper's nominal ensemble


def test_the_agent_uses_the_sections_as_they_are():
    cfg = AgentConfig.default({"model.ensemble_size": 3, "model.hidden_width": 9,
                               "model.hidden_layers": 1,
                               "model.activations": ("tanh", "elu"), "training.batch": 32,
                               "regularization.ltv_lambda": 2.0}, regularization="exact", seed=5,
                              progress=False, tensorboard=False, checkpoint=False)
    agent = JacPropAgent(gym.make("mbtsr/TwoLinkArm-v0"), cfg)
    assert agent.ensemble_config.members == (
        MemberSpec("tanh", 9, 1), MemberSpec("elu", 9, 1), MemberSpec("tanh", 9, 1))
    assert agent.ensemble_config.seed == 5
    assert agent.trainer.configs(3) == (dataclasses.replace(cfg.training, seed=3),
                                       cfg.regularization)
    assert agent.trainer.configs(3)[1] == RegularizationConfig(exact_weight=0.01, ltv_lambda=2.0)


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
    # a name, then fields of the section; a field without effect under it is refused
    if name == "sampled":
        cfg = AgentConfig().replace({"regularization": name, "regularization.sigma": 0.3})
        assert cfg.regularization == dataclasses.replace(reg, sigma=0.3)
    else:
        with pytest.raises(ValueError, match=r"^regularization\.sigma=0\.3 has no effect: "):
            AgentConfig().replace({"regularization": name, "regularization.sigma": 0.3})


def test_kind_of_combined_regularizers():
    assert RegularizationConfig(sampled_weight=1.0, smooth_weight=0.1).kind == "sampled+smooth"


def test_short_calls():
    cfg = AgentConfig(regularization="none", planner="cem")
    assert cfg.planner == PlannerConfig(kind="cem") and cfg.regularization.kind == "none"
    assert cfg.replace({"planner.horizon": 50}).planner == PlannerConfig(kind="cem", horizon=50)
    assert AgentConfig.default({"planner.horizon": 50}, regularization="none", seed=3) == \
        AgentConfig(regularization="none", planner=PlannerConfig(horizon=50), seed=3)


def test_unknown_fields_are_named():
    with pytest.raises(ValueError, match="nonsense"):
        AgentConfig.from_dict({**AgentConfig().to_dict(), "nonsense": 1})
    with pytest.raises(ValueError, match=r"model\.depth"):
        AgentConfig.from_dict({**AgentConfig().to_dict(), "model": {"depth": 2}})
    with pytest.raises(ValueError, match=r"unknown AgentConfig field 'planner\.depth'"):
        AgentConfig().replace({"planner.depth": 2})
    with pytest.raises(ValueError, match=r"'horizon'; the closest valid field is "
                                         r"'planner\.horizon'"):
        AgentConfig().replace({"horizon": 2})


def test_a_config_saved_before_the_step_budget_is_refused_as_such():
    """A whole saved config whose training section predates ``training.steps`` (2026-12-02) is
    refused with a message that says so, not read under today's training defaults; a user's
    partial dict that sets the epoch schedule is still read."""
    old = AgentConfig().to_dict()
    del old["training"]["steps"]
    with pytest.raises(ValueError, match=r"training\.epochs without training\.steps"):
        AgentConfig.from_dict(old)
    cfg = AgentConfig.from_dict({"training": {"steps": None, "epochs": 30}})
    assert cfg.training.epochs == 30 and cfg.training.steps is None
    with pytest.raises(ValueError, match=r"training\.epochs without training\.steps"):
        AgentConfig.from_dict(old, base=AgentConfig())  # as train_agent --config FILE does
    assert AgentConfig.from_dict(old, base=cfg).training.epochs == old["training"]["epochs"]


@pytest.mark.parametrize("bad", [[1, 2], "horizon", 3, None])
def test_from_dict_refuses_a_non_dict(bad):
    with pytest.raises(ValueError, match="AgentConfig.from_dict needs a dict"):
        AgentConfig.from_dict(bad)
    with pytest.raises(ValueError, match="AgentConfig.from_dict needs a dict"):
        AgentConfig.from_dict(json.loads(json.dumps(bad)))


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
    with pytest.raises(ValueError, match="planner.proposal.explore_weight must be 0.0: set "
                                         "collection.explore_weight"):
        AgentConfig().replace({"planner.proposal.explore_weight": 1.0})


@pytest.mark.parametrize("dotted", sorted(AgentConfig.FIXED))
def test_a_fixed_field_is_refused_naming_itself_and_why(dotted):
    """The fields the agent sets itself keep their section's default; another value is refused
    (also where the field would act, e.g. planner.cem.seed with planner.kind='cem')."""
    other = {"seed": 3, "explore_weight": 1.0, "explore_on": "cost", "ltv_affine": True}
    changes = {dotted: other[dotted.rpartition(".")[2]], "planner.kind": "cem"}
    with pytest.raises(ValueError) as err:
        AgentConfig.default(changes)
    assert str(err.value).startswith(f"{dotted} must be "), str(err.value)
    assert str(err.value).endswith(f"{AgentConfig.FIXED[dotted]}, got {changes[dotted]!r}")


# ---------------------------------------------------------------------------- partial dicts
#: valid values of every leaf of the tree (cross-field rules kept: replan_every <= 2 <= horizon,
#: elites <= 20 <= samples; training.seed, planner.cem.seed and ltv_affine are fixed)
LEAVES = {
    "collection.n_excitation_episodes": st.integers(1, 5),
    "collection.excitation": st.sampled_from(["filtered_gaussian", "multisine"]),
    "collection.excitation_scale": st.floats(0.01, 1.0),
    "collection.excitation_window": st.integers(1, 20),
    "collection.exploration_std": st.floats(0.0, 2.0),
    "collection.episode_steps": st.none() | st.integers(2, 500),
    "collection.rollout_steps": st.none() | st.integers(2, 500),
    "collection.continue_rollouts": st.booleans(),
    "collection.exploration_window": st.integers(1, 20),
    "collection.explore_weight": st.floats(0.0, 3.0),
    "collection.explore_on": st.sampled_from(["state", "cost"]),
    "model.formulation": st.sampled_from(["g", "f"]),
    "model.ensemble_size": st.integers(1, 8),
    "model.hidden_width": st.none() | st.integers(1, 64),
    "model.hidden_layers": st.none() | st.sampled_from([1, 2, 3]),
    "model.probabilistic": st.booleans(),
    "model.activations": st.lists(st.sampled_from(["elu", "tanh", "relu", "swish"]),
                                  min_size=1, max_size=4).map(tuple),
    "training.epochs": st.integers(1, 500),
    "training.lr": st.floats(1e-6, 1.0),
    "training.batch": st.just("trajectory") | st.integers(1, 512),
    "training.weight_decay": st.floats(0.0, 1.0),
    "training.decoupled_weight_decay": st.booleans(),
    "training.betas": st.tuples(st.floats(0.0, 0.99), st.floats(0.0, 0.999)),
    "training.adam_eps": st.floats(1e-12, 1.0),
    "training.shuffle": st.booleans(),
    "training.progress": st.booleans(),
    "training.steps": st.none() | st.integers(1, 2000),
    "training.holdout": st.floats(0.0, 0.5),
    "training.eval_every": st.integers(1, 500),
    "training.patience": st.none() | st.integers(1, 10),
    "training.early_stopping": st.sampled_from(["member", "ensemble"]),
    "training.member_data": st.sampled_from(["shared", "order", "bootstrap"]),
    "regularization.sampled_weight": st.floats(0.0, 10.0),
    "regularization.sigma": st.floats(0.0, 1.0),
    "regularization.n_copies": st.integers(1, 4),
    "regularization.copies_batch": st.sampled_from(["shared", "own"]),
    "regularization.exact_weight": st.floats(0.0, 1.0),
    "regularization.smooth_weight": st.floats(0.0, 1.0),
    "regularization.ltv_lambda": st.none() | st.floats(1e-3, 1e6),
    "planner.horizon": st.none() | st.integers(2, 60),
    "planner.replan_every": st.integers(1, 2),
    "planner.replan_feedback": st.booleans(),
    "planner.kind": st.sampled_from(["ilqr", "cem", "cem-ilqr"]),
    "planner.terminal_weight": st.none() | st.floats(0.0, 10.0),
    "planner.ilqr_iterations": st.integers(1, 5),
    "planner.first_plan_iterations": st.integers(1, 30),
    "planner.cem.samples": st.integers(20, 500),
    "planner.cem.elites": st.integers(1, 20),
    "planner.cem.iterations": st.integers(1, 10),
    "planner.cem.init_std": st.floats(0.0, 2.0),
    "planner.cem.smoothing": st.floats(0.0, 1.0),
    "planner.cem.tol_std": st.floats(0.0, 1.0),
    "planner.cem.max_state_norm": st.floats(0.0, 1e10),
    "planner.cem.termination_cost": st.floats(-1e3, 1e3),
    "planner.cem.particles": st.integers(1, 8),
    "planner.propagation": st.sampled_from(["mean", "ts"]),
    "planner.proposal.samples": st.integers(8, 500),
    "planner.proposal.elites": st.integers(1, 8),
    "planner.proposal.iterations": st.integers(1, 10),
    "planner.proposal.init_std": st.floats(0.0, 2.0),
    "planner.proposal.smoothing": st.floats(0.0, 1.0),
    "planner.proposal.tol_std": st.floats(0.0, 1.0),
    "planner.proposal.max_state_norm": st.floats(0.0, 1e10),
    "planner.proposal.termination_cost": st.floats(-1e3, 1e3),
    "planner.proposal.particles": st.integers(1, 8),
    "planner.warm_samples": st.none() | st.integers(2, 64),
    "evaluation.every": st.integers(0, 10),
    "evaluation.every_steps": st.integers(0, 5000),
    "evaluation.episodes": st.integers(1, 10),
    "evaluation.seed": st.integers(0, 10_000),
    "evaluation.early_exit": st.booleans(),
    "evaluation.solved_ratio": st.floats(1.0, 5.0),
    "evaluation.solved_return": st.none() | st.floats(-1e3, 1e3),
    "evaluation.stop_when_solved": st.booleans(),
    "evaluation.oracle_cache_dir": st.none() | st.text("abc/_", min_size=1, max_size=8),
    "seed": st.integers(0, 2**31),
    "renormalize": st.booleans(),
    "ltv_prior": st.floats(0.0, 1.0),
    "run_dir": st.none() | st.text("abc/_", min_size=1, max_size=8),
    "checkpoint": st.booleans(),
    "tensorboard": st.booleans(),
    "video": st.booleans(),
    "video_every": st.integers(1, 10),
    "jacobian_error": st.booleans(),
    "progress": st.booleans(),
    "torch_threads": st.integers(0, 8),
    "reward.members": st.integers(1, 8),
    "reward.hidden": st.integers(1, 64),
    "reward.steps": st.integers(1, 5000),
    "reward.batch": st.integers(1, 1024),
    "reward.lr": st.floats(1e-5, 1.0),
    "reward.weight_decay": st.floats(0.0, 1.0),
    "reward.holdout": st.floats(0.0, 0.9),
    "reward.eval_every": st.integers(1, 500),
    "reward.patience": st.integers(1, 20),
}
#: the documented rule: these fields act only when ... (docs/agent.md, "Settings without effect")
ACTS_ONLY_WHEN = {
    "regularization.sigma": lambda v: v["regularization.sampled_weight"] > 0,
    "regularization.n_copies": lambda v: v["regularization.sampled_weight"] > 0,
    "regularization.copies_batch": lambda v: v["regularization.sampled_weight"] > 0,
    "regularization.ltv_lambda": lambda v: max(v["regularization.sampled_weight"],
                                               v["regularization.exact_weight"]) > 0,
    "ltv_prior": lambda v: max(v["regularization.sampled_weight"],
                               v["regularization.exact_weight"]) > 0,
    **{k: (lambda v: v["planner.kind"] == "cem") for k in LEAVES if k.startswith("planner.cem.")},
    **{k: (lambda v: v["planner.kind"] == "cem-ilqr") for k in LEAVES
       if k.startswith("planner.proposal.")},
    "planner.warm_samples": lambda v: v["planner.kind"] == "cem-ilqr",
    "planner.ilqr_iterations": lambda v: v["planner.kind"] != "cem",
    "planner.replan_feedback": lambda v: (v["planner.replan_every"] > 1
                                          and v["planner.kind"] != "cem"),
    "collection.excitation_window": lambda v: v["collection.excitation"] == "filtered_gaussian",
    "collection.exploration_window": lambda v: v["collection.exploration_std"] > 0,
    "collection.explore_on": lambda v: v["collection.explore_weight"] > 0,
    "collection.explore_weight": lambda v: (v["planner.kind"] != "ilqr"
                                            and v["model.ensemble_size"] > 1),
    "video_every": lambda v: v["video"],
    "evaluation.solved_ratio": lambda v: v["evaluation.solved_return"] is None,
    "evaluation.early_exit": lambda v: v["evaluation.solved_return"] is None,
    "training.epochs": lambda v: v["training.steps"] is None,
    "training.early_stopping": lambda v: v["training.patience"] is not None,
}
#: combinations that are refused as invalid (not just without effect): dropped from the draws
INVALID_WHEN = {
    "planner.propagation": lambda v: (v["planner.propagation"] == "ts"
                                      and v["planner.kind"] != "cem"),
    "training.batch": lambda v: v["training.batch"] == "trajectory" and (
        v["training.steps"] is not None or v["training.holdout"] > 0
        or v["training.patience"] is not None or v["training.member_data"] != "shared"),
    "training.holdout": lambda v: v["training.holdout"] == 0 and v["training.patience"] is not None,
    "collection.rollout_steps": lambda v: (
        v["collection.rollout_steps"] is not None and v["collection.episode_steps"] is not None
        and v["collection.rollout_steps"] >= v["collection.episode_steps"]),
    "collection.continue_rollouts": lambda v: (v["collection.continue_rollouts"]
                                               and v["collection.rollout_steps"] is None),
}
def leaves(cfg: AgentConfig, tree: dict | None = None, prefix: str = "") -> dict:
    """``{dotted field: value}`` of every leaf, from ``to_dict`` (lists as tuples)."""
    out = {}
    for k, v in (cfg.to_dict() if tree is None else tree).items():
        if isinstance(v, dict):
            out.update(leaves(cfg, v, f"{prefix}{k}."))
        else:
            out[prefix + k] = tuple(v) if isinstance(v, list) else v
    return out


def changed(cfg: AgentConfig) -> dict:
    return {k: v for k, v in leaves(cfg).items() if v != DEFAULTS[k]}


DEFAULTS = leaves(AgentConfig())


@st.composite
def partial_changes(draw) -> dict:
    """Random valid changes (dotted) of a random subset of the tree's leaves; a field that would
    have no effect under the drawn choices is not drawn."""
    names = draw(st.lists(st.sampled_from(sorted(LEAVES)), unique=True, max_size=len(LEAVES)))
    changes = {k: draw(LEAVES[k]) for k in names}
    for k, invalid in INVALID_WHEN.items():
        if k in changes and invalid({**DEFAULTS, **changes}):
            del changes[k]
    while True:  # to a fixed point: dropping a field can leave another without effect
        values = {**DEFAULTS, **changes}  # (explore_on after explore_weight at one member)
        kept = {k: v for k, v in changes.items()
                if k not in ACTS_ONLY_WHEN or ACTS_ONLY_WHEN[k](values)}
        if kept == changes:
            return kept
        changes = kept


def nested(changes: dict) -> dict:
    """``{"model.hidden_width": 3}`` -> ``{"model": {"hidden_width": 3}}``."""
    out: dict = {}
    for key, value in changes.items():
        *heads, last = key.split(".")
        node = out
        for h in heads:
            node = node.setdefault(h, {})
        node[last] = value
    return out


def assert_exactly(cfg: AgentConfig, changes: dict) -> None:
    """Every given field has its given value, every other field the agent's default."""
    got = leaves(cfg)
    assert got == cfg.dotted()
    for key, default in DEFAULTS.items():
        assert got[key] == changes.get(key, default), key


@settings(max_examples=150, deadline=None)
@given(changes=partial_changes())
def test_a_partial_dict_loads_as_exactly_its_changes_and_round_trips(changes):
    import yaml

    fixed = {"training.seed", "planner.cem.seed", "planner.proposal.seed",
             "planner.cem.explore_weight", "planner.proposal.explore_weight",
             "planner.cem.explore_on", "planner.proposal.explore_on",
             "regularization.ltv_affine", "reward.seed"}
    assert set(LEAVES) | fixed == set(DEFAULTS)  # the strategies cover the whole tree
    cfg = AgentConfig.from_dict(nested(changes))
    assert_exactly(cfg, changes)
    assert AgentConfig.from_dict(changes) == cfg  # dotted keys: the same
    assert AgentConfig.default(cfg.changes()) == cfg
    text = cfg.to_json()
    assert isinstance(json.loads(text)["model"], dict)  # nested, not flat
    assert AgentConfig.from_dict(json.loads(text)) == cfg
    assert AgentConfig.from_dict(yaml.safe_load(yaml.safe_dump(cfg.to_dict()))) == cfg


def swapped(value):
    """A number as its string, a bool as "true"/"false", a string as a number."""
    if isinstance(value, bool):
        return str(value).lower()
    if isinstance(value, (int, float)):
        return repr(value)
    return 7


@settings(max_examples=150, deadline=None)
@given(changes=partial_changes(), data=st.data())
def test_string_number_swaps_load_exactly_or_fail_naming_the_field(changes, data):
    keys = [k for k, v in changes.items() if v is not None and not isinstance(v, tuple)]
    swap = data.draw(st.lists(st.sampled_from(keys), unique=True, min_size=1)) if keys else []
    given_ = {k: swapped(v) if k in swap else v for k, v in changes.items()}
    try:
        cfg = AgentConfig.from_dict(nested(given_))
    except ValueError as err:
        assert any(str(err).startswith(k + " ") for k in swap), (str(err), swap)
        return
    # loaded: a swapped-in numeric string is its number, a swapped-in number a valid value
    expected = {k: (changes[k] if isinstance(given_[k], str) else given_[k]) if k in swap
                else v for k, v in changes.items()}
    assert_exactly(cfg, expected)


@settings(max_examples=60, deadline=None)
@given(path=st.sampled_from(sorted(DEFAULTS)), data=st.data())
def test_an_unknown_key_names_itself_and_its_closest_valid_field(path, data):
    i = data.draw(st.integers(0, len(path) - 1))
    typo = path[:i] + data.draw(st.sampled_from(["x", "", "_"])) + path[i + 1:]
    if typo in DEFAULTS or typo.strip(".") != typo or ".." in typo or typo in (
            "collection", "model", "training", "regularization", "planner", "evaluation",
            "planner.cem") or typo.split(".")[0] not in {p.split(".")[0] for p in DEFAULTS} \
            and "." in typo:
        return  # another valid field, a malformed path, or an unknown section name
    with pytest.raises(ValueError) as err:
        AgentConfig.from_dict(nested({typo: 1}))
    message = str(err.value)
    assert f"unknown AgentConfig field {typo!r}" in message, message
    if "not a section" not in message:
        closest = message.split("the closest valid field is ")[1].strip("'")
        assert closest in DEFAULTS or closest in {p.rpartition(".")[0] for p in DEFAULTS}


# the cases of issue 22, each with its new behaviour
def test_a_partial_section_changes_only_what_it_names():
    assert changed(AgentConfig.from_dict({"regularization": {"sampled_weight": 1.0,
                                                             "sigma": 0.2}})) == {
        "regularization.sampled_weight": 1.0, "regularization.sigma": 0.2}  # ltv_lambda: auto
    assert changed(AgentConfig.from_dict({"training": {"steps": 50}})) == {
        "training.steps": 50}  # lr, batch and progress keep the agent's values


def test_names_and_sections_mix():
    cfg = AgentConfig.from_dict({"regularization": "none", "model": {"hidden_width": 32}})
    assert cfg.regularization.kind == "none" and cfg.model.hidden_width == 32
    assert cfg == AgentConfig(regularization="none").replace({"model.hidden_width": 32})
    cfg = AgentConfig.from_dict({"planner": "cem", "planner.cem.samples": 50})
    assert (cfg.planner.kind, cfg.planner.cem.samples) == ("cem", 50)


@pytest.mark.parametrize("load", [
    lambda v: AgentConfig.from_dict({"training": {"lr": v}}),
    lambda v: AgentConfig().replace({"training.lr": v}),
    lambda v: AgentConfig.from_dict(json.loads(json.dumps({"training": {"lr": v}}))),
])
def test_a_number_in_a_string_is_parsed_and_a_word_refused(load):
    assert load("1e-3").training.lr == 0.001  # YAML 1.1 reads an unquoted 1e-3 as a string
    assert isinstance(load("1e-3").training.lr, float)
    with pytest.raises(ValueError, match=r"^training\.lr must be a number, got 'fast'$"):
        load("fast")


@pytest.mark.parametrize("changes, message", [
    ({"training": {"eval_every": "2.5"}}, "training.eval_every must be an integer, got '2.5'"),
    ({"model": {"ensemble_size": True}}, "model.ensemble_size must be an integer, got True"),
    ({"evaluation": {"early_exit": "no"}}, "evaluation.early_exit must be true or false, got 'no'"),
    ({"evaluation": {"early_exit": 0}}, "evaluation.early_exit must be true or false, got 0"),
    ({"training": {"batch": "all"}},
     "training.batch must be an integer or 'trajectory', got 'all'"),
    ({"training": {"betas": [0.9]}}, "training.betas must be a list of 2 numbers, got [0.9]"),
    ({"model": {"activations": ["tanh", 3]}},
     "model.activations must be a list of strings, got ['tanh', 3]"),
    ({"run_dir": 2024}, "run_dir must be a string or null, got 2024"),
    ({"regularization": {"ltv_lambda": "auto"}},
     "regularization.ltv_lambda must be a number or null, got 'auto'"),
    ({"model": 3}, "model must be a mbtsr.ensemble.ModelConfig (or a dict of its fields), got int"),
])
def test_a_value_of_the_wrong_type_is_refused_naming_the_field(changes, message):
    with pytest.raises(ValueError) as err:
        AgentConfig.from_dict(changes)
    assert str(err.value) == message


def test_unambiguous_values_are_coerced():
    cfg = AgentConfig.from_dict({"training": {"steps": "50", "batch": 64.0, "betas": [0.8, "0.9"]},
                                 "evaluation": {"stop_when_solved": "True", "solved_return": "-5"},
                                 "regularization": {"ltv_lambda": "none"},
                                 "model": {"activations": "tanh"}})
    assert (cfg.training.steps, cfg.training.batch, cfg.training.betas) == (50, 64, (0.8, 0.9))
    assert type(cfg.training.steps) is int and type(cfg.training.batch) is int
    assert cfg.evaluation.stop_when_solved is True and cfg.evaluation.solved_return == -5.0
    assert cfg.regularization.ltv_lambda is None and cfg.model.activations == ("tanh",)


def test_a_section_built_with_a_value_of_the_wrong_type_is_refused_by_the_tree():
    """The library's own configs accept some of these (TrainConfig(lr="1e-3") is stored and fails
    in torch's Adam later); the tree checks every leaf."""
    with pytest.raises(ValueError, match=r"^training\.lr must be a number, got '1e-3'$"):
        AgentConfig(training=TrainConfig(lr="1e-3"))
    with pytest.raises(ValueError, match=r"^evaluation\.early_exit must be true or false"):
        AgentConfig(evaluation=EvaluationConfig(early_exit="no"))


@pytest.mark.parametrize("changes, field", [
    ({"regularization": "none", "regularization.sampled_weight": 2}, None),  # the weight wins
    ({"regularization": "none", "regularization.sigma": 0.2}, "regularization.sigma"),
    ({"regularization": "smooth", "regularization.ltv_lambda": 3.0}, "regularization.ltv_lambda"),
    ({"regularization": "none", "ltv_prior": 0.5}, "ltv_prior"),
    ({"regularization": "exact", "regularization.n_copies": 2}, "regularization.n_copies"),
    ({"planner.cem.samples": 50}, "planner.cem.samples"),
    ({"planner": {"kind": "ilqr", "cem": {"elites": 5}}}, "planner.cem.elites"),
    ({"collection": {"excitation": "multisine", "excitation_window": 3}},
     "collection.excitation_window"),
    ({"collection": {"exploration_std": 0.0, "exploration_window": 4}},
     "collection.exploration_window"),
    ({"video_every": 2}, "video_every"),
    ({"planner.kind": "ilqr", "collection.explore_weight": 1.0}, "collection.explore_weight"),
    ({"model.ensemble_size": 1, "collection.explore_weight": 1.0}, "collection.explore_weight"),
    ({"collection.explore_on": "cost"}, "collection.explore_on"),
    ({"planner.replan_feedback": True}, "planner.replan_feedback"),  # replan_every is 1
    ({"planner": {"kind": "cem", "replan_every": 4, "replan_feedback": True}},
     "planner.replan_feedback"),
    ({"evaluation": {"solved_return": -4.0, "solved_ratio": 1.1}}, "evaluation.solved_ratio"),
    ({"evaluation": {"solved_return": -4.0, "early_exit": False}}, "evaluation.early_exit"),
])
def test_a_setting_without_effect_is_refused_with_the_reason(changes, field):
    if field is None:  # a name and a weight of that section: the weight is a change, not dropped
        assert AgentConfig.from_dict(changes).regularization.sampled_weight == 2
        return
    with pytest.raises(ValueError, match=rf"^{field}=\S+ has no effect: \S.*: remove it"):
        AgentConfig.from_dict(changes)


def test_defaults_never_count_as_settings_without_effect():
    for name in ("none", "smooth", "exact"):
        AgentConfig.from_dict({**AgentConfig().to_dict(), "regularization": name})
    AgentConfig.from_dict(AgentConfig(regularization="none", planner="ilqr").to_dict())
    AgentConfig(regularization=RegularizationConfig())  # its own ltv_lambda default (31.6)
    AgentConfig.default({"collection.excitation": "multisine",
                         "evaluation.solved_return": -3.0, "video": False})


def test_a_section_given_twice_or_a_leaf_as_a_section_is_named():
    with pytest.raises(ValueError, match=r"^model\.hidden_width is given twice$"):
        AgentConfig.from_dict({"model": {"hidden_width": 3}, "model.hidden_width": 4})
    with pytest.raises(ValueError, match=r"'seed\.x' \(seed is a field, not a section\)"):
        AgentConfig.from_dict({"seed.x": 1})
    with pytest.raises(ValueError, match=r"field names are strings, got 1 in 'model'"):
        AgentConfig.from_dict({"model": {1: 2}})


def test_step_budget_settings_without_effect_are_refused():
    with pytest.raises(ValueError, match=r"^training\.epochs=50 has no effect: it acts only "
                                         r"when training\.steps is None: remove it"):
        AgentConfig.default({"training.epochs": 50})
    assert AgentConfig.default({"training.epochs": 50, "training.steps": None,
                                "training.holdout": 0.1}).training.uses_step_loop
    with pytest.raises(ValueError, match=r"^training\.patience=10 has no effect: early stopping "
                                         r"needs held-out data"):
        AgentConfig.default({"training.holdout": 0.0})
    assert AgentConfig.default({"training.holdout": 0.0, "training.patience": None})
    with pytest.raises(ValueError, match=r"^training\.early_stopping='ensemble' has no effect"):
        AgentConfig.default({"training.early_stopping": "ensemble", "training.patience": None})
