"""Config files: ``AgentConfig.load`` / ``read_config_file`` (JSON and YAML, hand-written or a
run's ``config.json``), ``--config PATH`` on every script that takes an AgentConfig, and a run's
saved ``config.json`` reproducing the run."""

from __future__ import annotations

import csv
import json
from pathlib import Path

import pytest

from agents.config import AgentConfig
from agents.episode_log import TIMING_COLUMNS
from agents.experiments import train_agent

TINY = [
    "--episodes", "4", "--seed", "4", "--collection.episode-steps", "20",
    "--collection.n-excitation-episodes", "1", "--training.steps", "10",
    "--training.batch", "32", "--model.ensemble-size", "2", "--model.hidden-width", "8",
    "--planner.horizon", "5", "--planner.ilqr-iterations", "1",
    "--planner.first-plan-iterations", "3", "--evaluation.every", "2",
    "--evaluation.episodes", "1", "--evaluation.no-early-exit", "--evaluation.oracle-cache-dir",
    "none", "--torch-threads", "1", "--no-progress", "--no-plots", "--no-summary-table",
    "--no-tensorboard",
]


def rows(run_dir: Path) -> list[dict]:
    with open(run_dir / "episodes.csv") as fh:
        return [{k: v for k, v in r.items() if k not in TIMING_COLUMNS}
                for r in csv.DictReader(fh)]


def test_a_run_reruns_from_its_saved_config_json(tmp_path, monkeypatch, capsys):
    """``train_agent.py --config runs/x/config.json`` is run x again (in a new folder): the same
    episodes.csv in every non-timing column."""
    monkeypatch.chdir(tmp_path)
    first = train_agent.main(["--run-dir", "x", "--regularization", "exact", *TINY])
    again = train_agent.main(["--config", "x/config.json"])
    assert "--config x/config.json: this run goes to runs/train_agent/" in capsys.readouterr().out
    second = Path(again["run_dir"])
    assert second.resolve() != Path(first["run_dir"]).resolve()
    assert len(rows(Path("x"))) == 4 and rows(second) == rows(Path("x"))
    saved = [json.loads((d / "config.json").read_text()) for d in (Path("x"), second)]
    assert saved[1]["agent"] == {**saved[0]["agent"], "run_dir": str(second)}
    assert saved[1]["agent"]["regularization"]["exact_weight"] == 0.01
    # flags apply on top of the file
    third = train_agent.main(["--config", "x/config.json", "--run-dir", "y", "--episodes", "1"])
    assert third["run_dir"] == "y" and len(rows(Path("y"))) == 1
    assert rows(Path("y")) == rows(Path("x"))[:1]  # the excitation episode: the same


def test_a_yaml_file_written_by_hand_is_changes_to_the_script_defaults(tmp_path):
    path = tmp_path / "arm.yaml"
    path.write_text("regularization: none\n"
                    "model: {hidden_width: 32}\n"
                    "training:\n  lr: 1e-3        # YAML 1.1: the string '1e-3'\n"
                    "seed: 3\n")
    args = train_agent.parse(["--config", str(path), "--seed", "5"])
    assert args.agent == train_agent.Args().agent.replace(
        {"regularization": "none", "model.hidden_width": 32, "training.lr": 0.001}, seed=5)
    assert args.agent.evaluation.oracle_cache_dir == "runs/oracle_cache"  # the script's default
    assert AgentConfig.load(path) == AgentConfig.default(
        {"regularization": "none", "model.hidden_width": 32, "training.lr": 0.001}, seed=3)


def test_the_manuals_yaml_example_is_read_as_it_says(tmp_path):
    """docs/agent.md's arm.yaml, copied from the page, gives the changes its comments name."""
    import re

    text = (Path(__file__).parents[1] / "docs" / "agent.md").read_text()
    block = re.search(r"```yaml\n(# arm.yaml.*?)```", text, re.S).group(1)
    (path := tmp_path / "arm.yaml").write_text(block)
    args = train_agent.parse(["--config", str(path), "--seed", "3"])
    assert args.agent == train_agent.Args().agent.replace(
        {"regularization": "exact", "planner.horizon": 40, "training.steps": 2000,
         "training.lr": 0.001, "model.hidden_width": 32}, seed=3)


def test_help_shows_config(capsys):
    with pytest.raises(SystemExit):
        train_agent.parse(["--help"])
    text = " ".join(capsys.readouterr().out.split())
    assert "--config" in text and "the flags given with it on top" in text


BAD_FILES = [  # (file name, content, the one line the script prints after "error: --config ")
    ("a.yaml", "training:\n  lr: fast\n", "{p}: training.lr must be a number, got 'fast'"),
    ("a.yaml", "model:\n  hiden_width: 3\n", "{p}: unknown AgentConfig field "
     "'model.hiden_width'; the closest valid field is 'model.hidden_width'"),
    ("a.yaml", "planner:\n  cem: {samples: 50}\n", "{p}: planner.cem.samples=50 has no effect: "
     "it acts only when planner.kind == 'cem': remove it, or set that"),
    ("a.yaml", "seed: 1\nseed: 2\n", "{p}: the key 'seed' is given twice (line 2)"),
    ("a.yaml", "model: [1, 2\n", "{p} is not valid YAML: expected ',' or ']', but got '<stream "
     "end>' (line 2, column 1)"),
    ("a.yaml", "", "{p} is empty (a dict of AgentConfig fields expected)"),
    ("a.yaml", "- seed: 1\n", "{p} holds a list, not a dict of AgentConfig fields"),
    ("a.json", '{"seed": 1,}', "{p} is not valid JSON: Expecting property name enclosed in "
     "double quotes (line 1, column 12)"),
    ("a.json", '{"seed": 1, "seed": 2}', "{p}: the key 'seed' is given twice"),
    ("a.json", '{"agent": {"seed": 1}, "scrpt": {}}', "{p}: unknown key(s) ['scrpt'] beside "
     "'agent' (a run's config.json holds 'agent' and ['script', 'command', 'ensemble', "
     "'env_spec'])"),
    ("a.json", '{"agent": {}, "script": {"episodez": 3}}', "{p}: unknown script setting(s) "
     "['episodez'] (this script has ['config', 'env_id', 'episodes', 'out', 'plots', "
     "'regularization', 'resume', 'smoke', 'summary_table'])"),
    ("missing.yaml", None, "{p}: no such file or directory"),
    ("folder.yaml", "/", "{p}: is a directory"),
]


@pytest.mark.parametrize("name, content, message", BAD_FILES)
def test_a_bad_file_is_one_line_naming_the_file_and_the_problem(tmp_path, capsys, name, content,
                                                                 message):
    path = tmp_path / name
    if content == "/":
        path.mkdir()
    elif content is not None:
        path.write_text(content)
    with pytest.raises(SystemExit) as exc:
        train_agent.parse(["--config", str(path)])
    err = capsys.readouterr().err
    assert exc.value.code == 2 and err.count("\n") == 1
    assert err.split("error: ", 1)[1].rstrip("\n") == "--config " + message.format(p=path)


def test_read_config_file_refuses_yaml_objects_and_binary(tmp_path):
    from agents.config import read_config_file

    evil = tmp_path / "evil.yaml"
    evil.write_text("seed: !!python/object/apply:os.system ['echo hacked']\n")
    with pytest.raises(ValueError, match=r"evil\.yaml is not valid YAML: .*python/object"):
        read_config_file(evil)
    binary = tmp_path / "b.json"
    binary.write_bytes(b"\x80\x81\xff")
    with pytest.raises(ValueError, match=r"b\.json is not a text file"):
        read_config_file(binary)


def test_config_and_resume_and_a_dropped_weight_are_refused(tmp_path, capsys):
    path = tmp_path / "c.json"
    path.write_text("{}")
    for argv, message in (
        (["--config", str(path), "--resume"], "--config starts a new run and --resume"),
        (["--regularization", "none", "--regularization.sampled-weight", "2"],
         "--regularization none turns regularization.sampled_weight off"),
        (["--regularization", "none", "--regularization.sigma", "0.2"],
         "regularization.sigma=0.2 has no effect"),
        (["--planner.cem.samples", "50"], "planner.cem.samples=50 has no effect"),
    ):
        with pytest.raises(SystemExit) as exc:
            train_agent.parse(argv)
        err = capsys.readouterr().err
        assert exc.value.code == 2 and err.count("\n") == 1 and message in err, err


def test_smoke_goes_on_top_of_a_config_file(tmp_path):
    """``--config FILE --smoke``: the smoke sizes, and the file's other settings kept."""
    path = tmp_path / "arm.yaml"
    path.write_text("seed: 7\ntraining: {lr: 0.005}\n")
    args = train_agent.parse(["--config", str(path), "--smoke"])
    assert (args.agent.seed, args.agent.training.lr) == (7, 0.005)
    assert args.smoke and args.agent.training.steps == 20 and args.episodes == 2
