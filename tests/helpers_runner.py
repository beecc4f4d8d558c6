"""Module-level run functions for the runner tests (workers must be able to import them)."""

import os

import numpy as np


def noisy_mean(config: dict, seed: int) -> dict:
    rng = np.random.default_rng(seed)
    x = rng.normal(config["mu"], 1.0, size=config.get("n", 100))
    log = config.get("log_dir")
    if log:  # count executions, to check that resumed sweeps do not redo work
        with open(os.path.join(log, f"{config['mu']}_{seed}_{os.getpid()}"), "a") as fh:
            fh.write("x")
    return {"mean": float(x.mean()), "first": x[:3]}


def fail_on_odd(config: dict, seed: int) -> dict:
    if seed % 2:
        raise RuntimeError(f"odd seed {seed}")
    return {"seed": seed}


def torch_threads(config: dict, seed: int) -> dict:
    import torch

    return {"threads": torch.get_num_threads()}


def raise_or_die(config: dict, seed: int) -> dict:
    """Raises for ``config["raise_seed"]``, SIGKILLs its own worker for ``config["kill_seed"]``."""
    if seed == config.get("raise_seed"):
        raise ValueError(f"bad seed {seed}")
    if seed == config.get("kill_seed"):
        os.kill(os.getpid(), 9)
    if seed == config.get("exit_seed"):
        os._exit(3)
    return noisy_mean({"mu": config.get("mu", 0.0), "n": 10}, seed)


def sleep_forever(config: dict, seed: int) -> dict:
    """Writes its pid to ``config["pid_dir"]`` and sleeps (for the orphan test)."""
    import time

    with open(os.path.join(config["pid_dir"], f"{seed}.pid"), "w") as fh:
        fh.write(str(os.getpid()))
    time.sleep(600)
    return {}
