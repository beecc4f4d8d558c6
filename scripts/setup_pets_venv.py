"""Build the virtual environment of the PETS peer (mbrl-lib 0.2.0) from the registry.

Why a venv of its own, what it installs and which pins it works around: docs/pets_peer.md,
"Setting up and running". Idempotent; ``--check`` only verifies the venv (exit 1 if broken).
"""

from __future__ import annotations

import json
import subprocess
import sys
import time
import venv
from dataclasses import dataclass
from pathlib import Path

REPO = Path(__file__).resolve().parents[1]
DEFAULT_VENV = REPO / ".venv-pets"

#: (step name, pip arguments, requirements that must hold afterwards as {dist: version or None})
STEPS: list[tuple[str, list[str], dict[str, str | None]]] = [
    ("torch (CPU wheel, first)", ["torch==2.13.0"], {"torch": "2.13.0"}),
    ("mbrl 0.2.0 (without its pins)", ["--no-deps", "mbrl==0.2.0"], {"mbrl": "0.2.0"}),
    ("mbrl's runtime dependencies",
     ["termcolor>=1.1.0", "tqdm>=4.48.2", "imageio>=2.9.0", "matplotlib>=3.3.1",
      "tensorboard>=2.4.0", "pyyaml"],
     {"termcolor": None, "tqdm": None, "imageio": None, "matplotlib": None, "tensorboard": None}),
    ("workaround 1: hydra-core 1.3 / omegaconf 2.3 (1.0.3 fails on Python 3.11)",
     ["hydra-core==1.3.2", "omegaconf==2.3.0"], {"hydra-core": "1.3.2", "omegaconf": "2.3.0"}),
    ("workaround 2: gymnasium 1.4 + mujoco 4.0 (0.26.3 has no -v5 envs)",
     ["gymnasium==1.4.0", "mujoco==4.0.0"], {"gymnasium": "1.4.0", "mujoco": "4.0.0"}),
    ("casadi + numpy for agents.tasks", ["casadi==3.8.2", "numpy"], {"casadi": "3.8.2",
                                                                       "numpy": None}),
]

CHECK = r"""
import warnings; warnings.filterwarnings("ignore")
import hydra, omegaconf, torch, gymnasium, mujoco, casadi, numpy
import mbrl, mbrl.models, mbrl.planning, mbrl.util, mbrl.util.common
cfg = omegaconf.OmegaConf.create({"_target_": "mbrl.planning.CEMOptimizer", "num_iterations": 1,
    "elite_ratio": 0.1, "population_size": 8, "alpha": 0.1, "lower_bound": [-1.0],
    "upper_bound": [1.0], "return_mean_elites": True, "device": "cpu"})
opt = hydra.utils.instantiate(cfg)
assert isinstance(opt, mbrl.planning.CEMOptimizer)
env = gymnasium.make("Reacher-v5"); env.reset(seed=0); env.step(env.action_space.sample())
print("mbrl", mbrl.__version__, "| torch", torch.__version__, "| hydra", hydra.__version__,
      "| omegaconf", omegaconf.__version__, "| gymnasium", gymnasium.__version__,
      "| mujoco", mujoco.__version__, "| casadi", casadi.__version__, "| numpy", numpy.__version__)
"""


def installed(py: Path, dists: list[str]) -> dict[str, str | None]:
    """Installed versions of ``dists`` in the interpreter ``py`` (``None``: not installed)."""
    code = ("import importlib.metadata as m, json, sys\nout = {}\n"
            "for d in sys.argv[1:]:\n    try: out[d] = m.version(d)\n"
            "    except m.PackageNotFoundError: out[d] = None\nprint(json.dumps(out))")
    res = subprocess.run([str(py), "-c", code, *dists], capture_output=True, text=True,
                         check=True)
    return json.loads(res.stdout)


def satisfied(have: dict[str, str | None], want: dict[str, str | None]) -> bool:
    """Whether every wanted distribution is installed (at the wanted version if one is given;
    a local version label such as torch's ``+cpu`` is ignored)."""
    return all(have.get(d) is not None and (v is None or str(have[d]).split("+")[0] == v)
               for d, v in want.items())


def check(py: Path) -> bool:
    """Import mbrl's PETS components inside the venv and step Reacher-v5."""
    print("check: mbrl's PETS components, hydra instantiate, Reacher-v5", flush=True)
    res = subprocess.run([str(py), "-c", CHECK], capture_output=True, text=True)
    if res.returncode != 0:
        print("FAILED: the venv's check did not pass:\n" + res.stderr[-3000:], flush=True)
        return False
    print("  ok:", res.stdout.strip(), flush=True)
    return True


@dataclass(frozen=True)
class Args:
    """Build (or only check) the PETS peer's venv."""

    venv: Path = DEFAULT_VENV
    """venv folder (outside git)"""
    check: bool = False
    """only verify the venv (exit code 1 if broken)"""


def build(args: Args) -> int:
    """Build (or only ``--check``) the PETS venv; return the process exit code."""
    t0 = time.perf_counter()
    py = args.venv / "bin" / "python"
    if args.check:
        return 0 if py.exists() and check(py) else 1
    if py.exists():
        print(f"venv: {args.venv} exists (kept)", flush=True)
    else:
        print(f"venv: creating {args.venv} with {sys.executable}", flush=True)
        venv.EnvBuilder(with_pip=True).create(args.venv)
    for name, pip_args, want in STEPS:
        have = installed(py, list(want))
        if satisfied(have, want):
            print(f"{name}: already installed ({', '.join(f'{d} {have[d]}' for d in want)})",
                  flush=True)
            continue
        cmd = [str(py), "-m", "pip", "install", "--disable-pip-version-check", *pip_args]
        print(f"{name}: installing\n  $", " ".join(cmd), flush=True)
        code = subprocess.run(cmd).returncode
        have = installed(py, list(want))
        if code != 0 or not satisfied(have, want):
            print(f"FAILED at step {name!r}: pip exit code {code}, installed {have}, "
                  f"wanted {want}", flush=True)
            return 1
    print("note: pip's 'dependency conflicts' about mbrl's pins (hydra-core 1.0.3, omegaconf "
          "<2.1, gymnasium 0.26.3) and its jupyter, pytest and sk-video requirements are the "
          "deliberate workarounds above", flush=True)
    ok = check(py)
    print(f"{'done' if ok else 'FAILED'} in {time.perf_counter() - t0:.0f} s: {args.venv}",
          flush=True)
    return 0 if ok else 1


if __name__ == "__main__":
    sys.path.insert(0, str(REPO))
    from agents.cli import main

    sys.exit(main(Args, build))
