"""Generated CLIs (agents.cli over tyro): every config field in --help with its docstring, nested
fields settable, bad arguments end in exit code 2 naming the flag (no traceback; a bad value: ONE
line naming the dotted field), output paths checked before any work."""

from __future__ import annotations

import dataclasses
import importlib
import inspect
import os
import subprocess
import sys
from dataclasses import dataclass, field
from pathlib import Path

import pytest

from agents.cli import _plain_help, check_output_path, main, parse

REPO = Path(__file__).resolve().parents[1]
sys.path.append(str(REPO))  # agents/experiments/ (until the editable install is refreshed)

#: every experiments module behind a script in scripts/ (the exp_* ones: every one there is)
EXPERIMENTS = sorted({"bench_ilqr", "bench_ltv", "bench_models",
                      "bench_planning", "bench_suite", "collect_excitation", "ilqr_with_model",
                      *(p.stem for p in (REPO / "agents" / "experiments").glob("exp_*.py"))})


@dataclass(frozen=True)
class Model:
    hidden_width: int = 20
    """width of each hidden layer"""

    def __post_init__(self) -> None:
        if self.hidden_width < 1:
            raise ValueError(f"hidden_width must be >= 1, got {self.hidden_width}")


@dataclass(frozen=True)
class Config:
    """A toy config."""

    seed: int = 0
    """the seed"""
    out: str | None = None
    """output file"""
    model: Model = field(default_factory=Model)
    """the model"""


def fields_of(cls, prefix: str = "") -> list[tuple[str, dataclasses.Field]]:
    """Dotted names of every (nested) field, as tyro spells them on the command line."""
    out = []
    for f in dataclasses.fields(cls):
        name = prefix + f.name.replace("_", "-")
        if dataclasses.is_dataclass(f.type if not isinstance(f.type, str) else None):
            out += fields_of(f.type, name + ".")
        else:
            out.append((name, f))
    return out


def help_text(cls, capsys) -> str:
    """The ``--help`` output, laid out 200 columns wide (a narrow terminal splits words)."""
    with pytest.MonkeyPatch.context() as mp, pytest.raises(SystemExit) as exit_:
        mp.setenv("COLUMNS", "200")
        parse(cls, args=["--help"], prog="x")
    assert exit_.value.code == 0
    return capsys.readouterr().out


def errors(cls, args, capsys, one_line: bool = True, **kw) -> str:
    """stderr of a refused command line (exit code 2), as one line of words (tyro's own reports
    of a malformed command line, ``one_line=False``, are boxes: the box drawn out)."""
    with pytest.MonkeyPatch.context() as mp, pytest.raises(SystemExit) as exit_:
        mp.setenv("COLUMNS", "200")
        parse(cls, args=args, prog="x", **kw)
    assert exit_.value.code == 2
    err = capsys.readouterr().err
    assert "Traceback" not in err
    if one_line:
        assert err.count("\n") == 1 and err.startswith("x: error: "), err
    return " ".join(err.translate(str.maketrans("", "", "│╭╮╰╯─")).split())


def test_nested_fields_are_settable_and_documented(capsys):
    cfg = parse(Config, args=["--seed", "3", "--model.hidden-width", "64"])
    assert cfg == Config(seed=3, model=Model(hidden_width=64))
    text = " ".join(help_text(Config, capsys).split())
    for flag in ("--seed", "--out", "--model.hidden-width"):
        assert flag in text
    for doc in ("the seed", "output file", "width of each hidden layer"):
        assert doc in text


@dataclass(frozen=True)
class Marked:
    steps: int | None = None
    """Adam steps (``None``: the epoch schedule, :func:`mbtsr.training.train_ensemble`;
    :class:`~agents.config.AgentConfig` has ``training.steps``)"""


def test_help_shows_the_docstrings_markup_as_plain_names(capsys):
    text = " ".join(help_text(Marked, capsys).split())
    assert ("Adam steps (None: the epoch schedule, mbtsr.training.train_ensemble; "
            "agents.config.AgentConfig has training.steps)") in text
    assert "``" not in text and ":func:" not in text and ":class:" not in text


@pytest.mark.parametrize("args, message", [
    (["--seed", "x"], "Error parsing --seed"),
    (["--bogus", "1"], "Unrecognized options: --bogus"),
    (["--seed"], "Missing value for argument '--seed'"),
    (["--model.hiden-width", "3"], "Perhaps you meant: --model.hidden-width INT"),
])
def test_a_malformed_command_line_exits_2_naming_the_flag(args, message, capsys):
    assert message in errors(Config, args, capsys, one_line=False)


def test_a_bad_value_is_one_line_naming_the_dotted_field(capsys):
    """tyro builds the dataclasses unchecked; parse builds them again (their __post_init__)."""
    assert errors(Config, ["--model.hidden-width", "0"], capsys) == \
        "x: error: model.hidden_width must be >= 1, got 0"


def test_output_paths_are_checked_before_any_work(tmp_path, capsys):
    (tmp_path / "file").write_text("x")
    out = {"outputs": ("out",)}
    assert "is a folder" in errors(Config, ["--out", str(tmp_path)], capsys, **out)
    assert "is not a folder" in errors(Config, ["--out", str(tmp_path / "file" / "o.json")],
                                       capsys, **out)
    ran = []
    with pytest.raises(SystemExit):
        main(Config, ran.append, outputs=("out",), args=["--out", str(tmp_path)])
    assert ran == []  # run never started
    assert check_output_path(tmp_path / "new" / "deeper" / "o.json", name="--out")
    assert not (tmp_path / "new").exists()  # checking creates nothing


def test_value_errors_of_the_run_are_one_line_too(capsys):
    def run(cfg):
        raise ValueError("episode_steps must be\nan integer >= 1, got 0")

    with pytest.raises(SystemExit) as exit_:
        main(Config, run, args=[])
    assert exit_.value.code == 2
    err = capsys.readouterr().err
    assert err.count("\n") == 1 and "episode_steps must be an integer" in err


@pytest.mark.parametrize("name", EXPERIMENTS)
def test_every_script_help_lists_every_field_with_its_help(name, capsys):
    module = importlib.import_module(f"agents.experiments.{name}")
    assert (REPO / "scripts" / f"{name}.py").exists()
    text = " ".join(help_text(module.Args, capsys).split())
    for flag, f in fields_of(module.Args):
        assert f"--{flag}" in text, flag
        doc = f.metadata.get("help")  # a shared base's field (paper_common.ExperimentArgs)
        if doc is None:  # the docstring under the field, in the class that declares it
            owner = next(c for c in module.Args.__mro__
                         if f.name in c.__dict__.get("__annotations__", {}))
            after = inspect.getsource(owner).split(f"    {f.name}:", 1)[1].split('"""')
            assert len(after) > 2 and after[0].count("\n") == 1, f"{name}.{f.name}: no docstring"
            doc = after[1]
        assert doc.strip(), f"{name}.{f.name} has no help"
        assert " ".join(doc.split()[:3]) in text, f.name  # its first words, as tyro wraps lines


def test_no_script_builds_an_argparse_parser():
    for path in [*(REPO / "scripts").glob("*.py"), *(REPO / "agents" / "experiments").glob("*.py")]:
        assert "argparse" not in path.read_text(), path


def test_file_system_errors_of_the_run_are_one_line_too(tmp_path, capsys):
    def run(cfg):  # an output the system refuses although the parser's check passed
        (tmp_path / "file").write_text("x")
        (tmp_path / "file" / "sub").mkdir()

    with pytest.raises(SystemExit) as exit_:
        main(Config, run, args=[])
    err = capsys.readouterr().err
    assert exit_.value.code == 2 and err.count("\n") == 1 and "Not a directory" in err


def test_train_agent_checks_its_run_dir_before_any_work(tmp_path, capsys):
    from agents.experiments.train_agent import parse as parse_train_agent

    (tmp_path / "file").write_text("x")
    with pytest.raises(SystemExit) as exit_:
        parse_train_agent(["--run-dir", str(tmp_path / "file" / "run")])
    err = capsys.readouterr().err
    assert exit_.value.code == 2 and err.count("\n") == 1 and "--run-dir" in err
    assert "is not a folder" in err


def test_a_real_script_fails_naming_the_flag_without_traceback():
    for args in (["--repeats", "many"], ["--out", "/"]):
        proc = subprocess.run([sys.executable, str(REPO / "scripts" / "bench_ltv.py"), *args],
                              capture_output=True, text=True, timeout=120,
                              env={**os.environ, "COLUMNS": "200", "PYTHONPATH": str(REPO)})
        assert proc.returncode == 2 and "Traceback" not in proc.stderr, proc.stderr
        assert args[0] in proc.stderr, proc.stderr
    assert proc.stderr.startswith("bench_ltv.py: error: --out: ")  # a bad value: one line
    assert proc.stderr.count("\n") == 1


@dataclass(frozen=True)
class Sweep:
    """A toy sweep."""

    quick: bool = False
    """smoke test"""
    seeds: int = 5
    """seeds"""
    model: Model = field(default_factory=Model)
    """the model"""


def test_a_preset_flag_changes_the_defaults_but_not_the_given_options():
    presets = {"--quick": {"quick": True, "seeds": 1, "model": Model(hidden_width=2)}}
    assert parse(Sweep, args=[], presets=presets) == Sweep()
    assert parse(Sweep, args=["--quick"], presets=presets) == Sweep(True, 1, Model(2))
    got = parse(Sweep, args=["--quick", "--seeds", "3"], presets=presets)
    assert got == Sweep(True, 3, Model(2))


def _param_docs(cls) -> dict[str, str]:
    """``{field: first three words}`` of the ``:param field:`` entries of a class docstring, as
    ``--help`` shows them (reST markup as plain names)."""
    chunks = (cls.__doc__ or "").split(":param ")[1:]
    return {k: " ".join(_plain_help(v).split()[:3]) for k, v in (c.split(":", 1) for c in chunks)}


def _tree_docs(obj, prefix: str = "") -> list[tuple[str, str, bool]]:
    """``(dotted name, first words of its doc, is a section)`` of every field of a config tree
    (sections found from the default instance, at any depth)."""
    out = []
    for f in dataclasses.fields(obj):
        value = getattr(obj, f.name)
        section = dataclasses.is_dataclass(value)
        out.append((prefix + f.name, _param_docs(type(obj))[f.name], section))
        if section:
            out += _tree_docs(value, f"{prefix}{f.name}.")
    return out


def test_train_agent_help_lists_every_agent_config_field_with_its_doc(capsys):
    """Every field of the tree is a flag named by its dotted path (no --agent. prefix), with the
    first words of its documentation; the sections' own docs head their groups. The fields the
    agent fixes are not offered, and refused as unknown options."""
    import re

    from agents.config import AgentConfig
    from agents.experiments import train_agent

    text = " ".join(help_text(train_agent.Args, capsys).split())
    fields = _tree_docs(AgentConfig())
    assert len(fields) >= 70 and ("planner.cem.samples", "action sequences sampled",
                                 False) in fields
    assert {"training.seed", "planner.cem.seed", "regularization.ltv_affine"} <= set(
        AgentConfig.FIXED)
    for name, doc, section in fields:
        flag = "--" + name.replace("_", "-")
        offered = re.search(re.escape(flag) + r"(?![\w.-])", text)
        if name in AgentConfig.FIXED:
            assert not offered, flag
            with pytest.MonkeyPatch.context() as mp, pytest.raises(SystemExit):
                mp.setenv("COLUMNS", "200")
                train_agent.parse([flag, "1"])
            assert f"Unrecognized options: {flag}," in capsys.readouterr().err
            continue
        if not section:
            assert offered, flag
        assert doc in text, (name, doc)


@pytest.mark.parametrize("flag, says", [
    ("--training.lr", "the default here"),  # the agent's lr is not TrainConfig's
    ("--model.hidden-width", "None: default_size"),  # read as "the default size"
    ("--planner.kind", "the default"),  # train_agent plans with ilqr
    ("--planner.replan-every", "the default"),
])
def test_train_agent_help_does_not_restate_defaults(flag, says, capsys):
    """The CLI prints each flag's default; a help text that names another is a contradiction."""
    from agents.experiments import train_agent

    text = help_text(train_agent.Args, capsys)
    entry = text.split(f"  {flag} ", 1)[1].split("(default: ", 1)[0]
    assert says not in " ".join(entry.split()), entry


def test_train_agent_sets_nested_fields_and_the_regularizer_by_name():
    from agents.experiments import train_agent

    args = train_agent.parse(["--model.hidden-width", "8", "--training.batch", "64",
                              "--planner.kind", "cem", "--regularization.sigma", "0.2"])
    cfg = args.agent
    assert (cfg.model.hidden_width, cfg.training.batch, cfg.planner.kind) == (8, 64, "cem")
    assert cfg.regularization.kind == "sampled" and cfg.regularization.sigma == 0.2
    none = train_agent.parse(["--regularization", "none"]).agent.regularization
    assert none.kind == "none" and none.ltv_lambda is None
    exact = train_agent.parse(["--regularization", "exact"]).agent.regularization
    assert (exact.kind, exact.exact_weight) == ("exact", 0.01)
    heavier = train_agent.parse(["--regularization", "exact",
                                 "--regularization.exact-weight", "0.5"]).agent.regularization
    assert (heavier.kind, heavier.exact_weight) == ("exact", 0.5)


@pytest.mark.parametrize("argv, field", [
    (["--model.hidden-width", "0"], "model.hidden_width"),
    (["--training.epochs", "0"], "training.epochs"),
    (["--regularization.sigma", "-1"], "regularization.sigma"),
    (["--planner.replan-every", "99"], "planner.replan_every"),
    (["--evaluation.solved-ratio", "0.5"], "evaluation.solved_ratio"),
    (["--collection.excitation", "chirp"], "--collection.excitation"),
])
def test_train_agent_bad_nested_value_exits_2_naming_the_field(argv, field, capsys):
    """A value out of range: one line; a value that is not among the choices: tyro's report."""
    from agents.experiments import train_agent

    with pytest.MonkeyPatch.context() as mp, pytest.raises(SystemExit) as exc:
        mp.setenv("COLUMNS", "200")
        train_agent.parse(argv)
    err = capsys.readouterr().err
    assert exc.value.code == 2 and "Traceback" not in err and field in err, err
    if not field.startswith("--"):
        assert err.count("\n") == 1, err


@pytest.mark.parametrize("summary, verdict", [
    ({"env_steps_to_solve": 200, "solved_criterion": "oracle_ratio", "eval_curve": [{}]},
     "solved at 200 env steps"),
    ({"env_steps_to_solve": None, "solved_criterion": "oracle_ratio", "eval_curve": [{}]},
     "not solved within the budget"),
    ({"env_steps_to_solve": None, "solved_criterion": "mean_return", "eval_curve": []},
     "not evaluated"),
    ({"env_steps_to_solve": None, "solved_criterion": None, "eval_curve": [{}]},
     "no solved criterion"),
])
def test_train_agent_summary_says_whether_and_when_the_run_solved(summary, verdict, capsys):
    from types import SimpleNamespace

    from agents.experiments.train_agent import print_summary

    agent = SimpleNamespace(env_id="x", logger_rows=[],
                            config=SimpleNamespace(run_dir="runs/x"))
    print_summary(agent, summary)
    out = " ".join(capsys.readouterr().out.split())
    assert f"{verdict}" in out and "run folder: runs/x" in out


@pytest.mark.parametrize("kind", ["ilqr", "cem", "cem-ilqr"])
def test_train_agent_smoke_takes_every_planner(kind):
    """``--smoke`` sets only fields that act under every planner: with ``--planner.kind cem``
    it once set ``ilqr_iterations`` and was refused as a setting without effect."""
    from agents.experiments import train_agent

    args = train_agent.parse(["--smoke", "--planner.kind", kind, "--regularization", "none"])
    assert args.smoke and args.episodes == 2 and args.agent.planner.kind == kind
    assert args.agent.training.steps == train_agent.SMOKE["agent"]["training.steps"]
