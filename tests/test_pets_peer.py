"""The PETS peer (agents/experiments/pets_peer.py): the parts that run without mbrl (the reward
and termination bridge from agents.tasks against the envs' own rewards, the settings, the JSON
records and their resume logic, the report) and, when the PETS venv exists, a tiny real run of
mbrl's PETS in it (slow)."""

from __future__ import annotations

import json
import subprocess
import sys
from pathlib import Path

import numpy as np
import pytest

from agents.experiments import pets_peer
from agents.tasks import make_task

REPO = Path(__file__).resolve().parents[1]


def _random_steps(name: str, n_episodes: int = 4, steps: int = 40, **make):
    """Transitions of uniform random actions: obs, next_obs, actions, rewards, terminated,
    infos."""
    task = make_task(name, **make)
    env = task.make_env()
    rng = np.random.default_rng(0)
    out: dict[str, list] = {k: [] for k in ("obs", "next", "act", "rew", "term", "info")}
    try:
        for ep in range(n_episodes):
            obs, _ = env.reset(seed=ep)
            for _ in range(steps):
                a = rng.uniform(env.action_space.low, env.action_space.high)
                nxt, r, term, trunc, info = env.step(a)
                for k, v in zip(out, (obs, nxt, a, r, term, info)):
                    out[k].append(v)
                obs = nxt
                if term or trunc:
                    break
    finally:
        env.close()
    arrays = {k: np.asarray(v) for k, v in out.items() if k != "info"}
    return task, arrays, out["info"]


@pytest.mark.parametrize("name", ["reacher", "pusher"])
def test_bridge_reward_is_the_env_reward(name):
    """Reacher and Pusher: -cost(next_obs, a) is the env's reward up to the norm's smoothing."""
    task, d, _ = _random_steps(name)
    bridge = pets_peer.TaskBridge(task)
    r = bridge.rewards(d["next"], d["act"])
    assert r.shape == d["rew"].shape
    np.testing.assert_allclose(r, d["rew"], atol=0.01)
    assert not bridge.terminated(d["next"]).any()


def test_bridge_arm_cost_is_the_env_reward():
    """The project's arm has no cost_fn: the bridge scores with the quadratic cost its env
    states (cost_Q, cost_R), which is exactly the env's reward on the clipped action."""
    task, d, info = _random_steps("two-link-arm", target_limit=0.85 * np.pi)
    assert task.cost_fn is None
    bridge = pets_peer.TaskBridge(task)
    np.testing.assert_allclose(bridge.rewards(d["next"], d["act"]), d["rew"], rtol=1e-12)
    parts = np.array([i["cost_state"] + i["cost_action"] for i in info])
    np.testing.assert_allclose(bridge.costs(d["next"], d["act"]), parts, rtol=1e-12)


def test_arm_tasks_run_the_suite_arm_and_replan_as_it():
    far, open_loop = (pets_peer.task_settings(n) for n in ("arm-far", "arm-open-loop"))
    assert far["agent_task"] == open_loop["agent_task"] == "two-link-arm"
    assert far["make"]["target_limit"] == pytest.approx(0.85 * np.pi)
    assert far["planner"]["replan_freq"] == 1 and open_loop["planner"]["replan_freq"] == 10
    assert far["budget_env_steps"] == 800
    env = make_task(far["agent_task"], **far["make"]).make_env()
    assert env.unwrapped.target_limit == pytest.approx(0.85 * np.pi)
    env.close()
    # a checkpoint written before agent_task existed (its own name) still resumes
    old = {k: v for k, v in pets_peer.task_settings("reacher").items() if k != "agent_task"}
    assert pets_peer._resume_view(old) == pets_peer._resume_view(
        pets_peer.task_settings("reacher"))


def test_bridge_half_cheetah_differs_only_by_the_velocity_term():
    """HalfCheetah: the reward's forward term is the displacement over the step; the cost uses
    the observation's velocity at its end. Everything else (control cost) is exact."""
    task, d, info = _random_steps("half-cheetah")
    r = pets_peer.TaskBridge(task).rewards(d["next"], d["act"])
    x_vel = np.array([i["x_velocity"] for i in info])
    np.testing.assert_allclose(d["rew"] - r, x_vel - d["next"][:, 8], atol=1e-6)
    assert np.corrcoef(r, d["rew"])[0, 1] > 0.85


@pytest.mark.parametrize("name,make", [("inverted-pendulum", {"max_episode_steps": 200}),
                                       ("inverted-double-pendulum", {})])
def test_bridge_termination_is_the_env_termination(name, make):
    task, d, _ = _random_steps(name, n_episodes=8, **make)
    bridge = pets_peer.TaskBridge(task)
    assert d["term"].any() and not d["term"].all()
    np.testing.assert_array_equal(bridge.terminated(d["next"]), d["term"])
    if name == "inverted-double-pendulum":
        # its reward terms minus the alive bonus: equal to the reward while alive
        r, alive = bridge.rewards(d["next"], d["act"]), ~d["term"]
        np.testing.assert_allclose(r[alive], d["rew"][alive], atol=1e-3)


def test_bridge_torch_signatures():
    torch = pytest.importorskip("torch")
    task = make_task("inverted-pendulum")
    reward_fn, term_fn = pets_peer.TaskBridge(task).torch_fns()
    obs = torch.tensor([[0.0, 0.0, 0.0, 0.0], [0.0, 0.5, 0.0, 0.0]])
    act = torch.zeros(2, 1)
    r, t = reward_fn(act, obs), term_fn(act, obs)
    assert r.shape == (2, 1) and r.dtype == torch.float32
    assert t.shape == (2, 1) and t.dtype == torch.bool
    assert t[:, 0].tolist() == [False, True]
    assert r[0, 0].item() == pytest.approx(1.0)  # upright at rest: the alive bonus, no cost


def test_settings_record_published_values_and_every_shrink():
    s = pets_peer.task_settings("reacher")
    assert s["model"]["ensemble_size"] == 7 and s["model"]["num_elites"] == 5
    assert s["model"]["num_layers"] == 4 and s["model"]["hid_size"] == 200
    assert s["planner"]["num_particles"] == 20 and s["planner"]["planning_horizon"] == 15
    assert s["planner"]["cem_published"]["population_size"] == 350
    assert s["planner"]["cem"]["population_size"] == 105
    assert any("350 -> 105" in x for x in s["shrinks"])
    assert s["budget_env_steps"] == 2000 and s["eval_episodes"] == 3 and s["eval_seed"] == 1000
    # the published inverted-pendulum population (480) is rounded up to a multiple of the
    # 7 members (x 20 particles), and that is recorded
    ip = pets_peer.task_settings("inverted-pendulum", cem={"population_size": 480,
                                                            "num_iterations": 5})
    assert ip["planner"]["cem"]["population_size"] == 483
    assert any("480 -> 483" in x for x in ip["shrinks"])
    json.dumps(s)  # serializable
    for name in pets_peer.TASKS:
        st = pets_peer.task_settings(name)
        assert st["planner"]["cem"]["population_size"] * 20 % 7 == 0
    with pytest.raises(ValueError, match="unknown task"):
        pets_peer.task_settings("cartpole")


def test_eval_points_end_at_the_budget():
    s = pets_peer.task_settings("reacher")
    assert pets_peer._eval_points(s) == list(range(200, 2001, 200))
    s = pets_peer.task_settings("reacher", budget=450, eval_every=200)
    assert pets_peer._eval_points(s) == [200, 400, 450]


def _record(task: str, seed: int, steps: list[int], finished: bool) -> dict:
    rec = pets_peer.new_record(task, seed, pets_peer.task_settings(task))
    rec["curve"] = [{"env_steps": s, "score": -10.0 + s / 100, "returns": [-10.0 + s / 100] * 3}
                    for s in steps]
    rec.update(env_steps=steps[-1], finished=finished, plan_seconds_per_step=0.5,
               wall_seconds=12.0)
    return rec


def test_records_are_replaced_per_task_and_seed(tmp_path):
    path = tmp_path / "pets.json"
    assert pets_peer.load_results(path) == {"method": "pets", "runs": []}
    pets_peer.upsert_run(path, _record("pusher", 0, [500], False), {"mbrl_version": "0.2.0"})
    pets_peer.upsert_run(path, _record("reacher", 1, [200], False))
    pets_peer.upsert_run(path, _record("reacher", 1, [200, 400], True))
    saved = json.loads(path.read_text())
    assert saved["mbrl_version"] == "0.2.0"
    assert [(r["task"], r["seed"]) for r in saved["runs"]] == [("reacher", 1), ("pusher", 0)]
    rec = pets_peer.find_run(saved, "reacher", 1)
    assert [p["env_steps"] for p in rec["curve"]] == [200, 400]
    assert set(rec) >= {"task", "method", "seed", "settings", "curve", "plan_seconds_per_step",
                        "wall_seconds", "env_steps"}
    assert rec["method"] == "pets" and rec["finished"]
    assert not pets_peer.find_run(saved, "pusher", 0)["finished"]
    assert pets_peer.find_run(saved, "pusher", 3) is None
    assert not list(tmp_path.glob(".*tmp*"))  # atomic writes leave no temporary file


def test_resume_skips_a_finished_run_without_mbrl(tmp_path):
    """A finished (task, seed) is returned as stored: nothing is imported or run."""
    path = tmp_path / "pets.json"
    rec = _record("reacher", 0, [200, 400], True)
    pets_peer.upsert_run(path, rec)
    seen: list[str] = []
    out = pets_peer.run_task("reacher", 0, rec["settings"], path, tmp_path / "ck", resume=True,
                             log=seen.append)
    assert out == json.loads(path.read_text())["runs"][0]
    assert seen == ["reacher seed 0: finished, skipped"]


def test_report_on_a_synthetic_json(tmp_path, capsys):
    path = tmp_path / "pets.json"
    for seed in (0, 1):
        pets_peer.upsert_run(path, _record("reacher", seed, [200, 400, 600], seed == 0))
    pets_peer.upsert_run(path, _record("pusher", 0, [500], False))
    figs = pets_peer.report(path, tmp_path / "fig")
    assert sorted(f.name for f in figs) == ["pets_pusher.png", "pets_reacher.png"]
    assert all(f.stat().st_size > 1000 for f in figs)
    table = capsys.readouterr().out
    assert "| reacher | 0 | 600 | 200: -8.00, 400: -6.00, 600: -4.00 | 0.50 | 12 | yes |" in table
    assert "| pusher | 0 | 500 |" in table


def test_command_help_says_it_runs_in_the_pets_venv():
    out = subprocess.run([sys.executable, str(REPO / "scripts" / "pets_peer.py"), "--help"],
                         capture_output=True, text=True, check=True).stdout
    assert "PETS venv" in out and "setup_pets_venv.py" in out


def test_setup_check_fails_clearly_without_a_venv(tmp_path):
    res = subprocess.run([sys.executable, str(REPO / "scripts" / "setup_pets_venv.py"),
                          "--check", "--venv", str(tmp_path / "none")],
                         capture_output=True, text=True)
    assert res.returncode == 1


VENV_PY = REPO / ".venv-pets" / "bin" / "python"


@pytest.mark.slow
@pytest.mark.skipif(not VENV_PY.exists(),
                    reason="the PETS venv is absent: build it with "
                           "`python scripts/setup_pets_venv.py`")
def test_tiny_pets_run_in_the_venv_resumes_bit_for_bit(tmp_path):
    """mbrl's real PETS on Reacher-v5 (tiny CEM, 150 env steps), once straight and once
    interrupted after its first evaluation point and resumed: the same numbers."""
    common = ["--tasks", "reacher", "--seeds", "0", "--budget", "150", "--eval-every", "50",
              "--population", "14", "--iterations", "2", "--epochs", "2", "--horizon", "5"]
    script = str(REPO / "scripts" / "pets_peer.py")

    def run(name: str, *extra: str) -> dict:
        subprocess.run([str(VENV_PY), script, *common, "--out", str(tmp_path / f"{name}.json"),
                        "--checkpoints", str(tmp_path / name), *extra], check=True,
                       capture_output=True, text=True, env={"OMP_NUM_THREADS": "1",
                                                            "PATH": "/usr/bin:/bin"})
        return json.loads((tmp_path / f"{name}.json").read_text())

    straight = run("a")
    run("b", "--stop-after", "1")
    partial = json.loads((tmp_path / "b.json").read_text())["runs"][0]
    assert len(partial["curve"]) == 1 and not partial["finished"]
    resumed = run("b", "--resume")
    a, b = straight["runs"][0], resumed["runs"][0]
    assert straight["mbrl_version"] == "0.2.0"
    assert [p["env_steps"] for p in a["curve"]] == [50, 100, 150]
    assert [p["returns"] for p in a["curve"]] == [p["returns"] for p in b["curve"]]
    assert a["train_episode_returns"] == b["train_episode_returns"]
    assert a["finished"] and b["finished"] and a["plan_seconds_per_step"] > 0
    assert any("population_size 350 -> 14" in s for s in a["settings"]["shrinks"])


def test_report_draws_the_agents_median_curves_beside_pets(tmp_path):
    suite = tmp_path / "bench_suite.json"
    runs = [{"task": "reacher", "planner": "cem", "regularization": "none", "seed": s,
             "curve": [{"env_steps": 100, "score": -12.0 + s}, {"env_steps": 200, "score": s}]}
            for s in range(3)]
    suite.write_text(json.dumps({"runs": runs}))
    (tmp_path / "bench_suite_baselines.json").write_text(
        json.dumps({"tasks": {"reacher": {"zero_return": -12.0, "oracle_return": -3.9}}}))
    assert pets_peer.agent_curves(suite, "reacher") == {"cem/none": [(100, -11.0), (200, 1.0)]}
    assert pets_peer.agent_curves(suite, "pusher") == {}
    assert pets_peer.suite_oracle(suite, "reacher") == -3.9
    assert pets_peer.suite_oracle(suite, "pusher") is None
    path = tmp_path / "pets.json"
    pets_peer.upsert_run(path, _record("reacher", 0, [200, 400], True))
    (fig,) = pets_peer.report(path, tmp_path / "fig", suite)
    assert fig.name == "pets_reacher.png" and fig.stat().st_size > 1000


def test_the_command_reexecutes_itself_in_the_venv_only_where_mbrl_is_missing(monkeypatch,
                                                                             tmp_path):
    """Outside the venv a run re-executes ``python -m agents.experiments.pets_peer`` with the
    venv's python and this checkout on PYTHONPATH; the report, ``--help`` and the venv's own
    python do not (a venv without mbrl would otherwise re-execute itself forever)."""
    import importlib.util
    import os

    venv_python = tmp_path / "python"
    venv_python.touch()
    calls = []
    monkeypatch.setattr(pets_peer, "VENV_PYTHON", venv_python)
    monkeypatch.setattr(importlib.util, "find_spec", lambda name: None)
    monkeypatch.setattr(os, "execv", lambda path, argv: calls.append((path, argv)))
    monkeypatch.delenv("PYTHONPATH", raising=False)
    for argv in (["--report-only"], ["--help"]):
        pets_peer._reexec_in_venv(argv)
    assert calls == []
    pets_peer._reexec_in_venv(["--smoke"])
    assert calls == [(str(venv_python), [str(venv_python), "-m", "agents.experiments.pets_peer",
                                         "--smoke"])]
    assert os.environ["PYTHONPATH"] == str(REPO)
    monkeypatch.setattr(sys, "executable", str(venv_python))
    pets_peer._reexec_in_venv(["--smoke"])
    assert len(calls) == 1
