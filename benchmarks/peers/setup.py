"""Creates the peers' virtual environments under `.peers/` (idempotent: a finished one is kept).

Two environments, because Safety-Gymnasium 1.0.0 and a CPU-only PyTorch cannot share one
interpreter as published:

- `safety-gymnasium` (Python 3.10): `safety-gymnasium==1.0.0` with its own pins (mujoco 2.3.3,
  gymnasium 0.28.1, numpy 1.23). Package 1.0.0 does not import on Python 3.11 as published.
- `osrl` (Python 3.11): `torch==2.13.0` CPU build, `osrl-lib==0.1.0` and `fast-safe-rl==0.1.0`
  without their dependencies (they pin torch 1.13 and would pull the CUDA build), plus only what
  `osrl.algorithms.cdt` imports (not OApackage: only its data augmentation uses it, and it
  compiles from source for minutes). For the sequential deployment (OSRL's own evaluation loop over
  Safety-Gymnasium in one process) it also gets `safety-gymnasium==1.0.0` with the same mujoco and
  gymnasium pins, minus pygame (rendering only; 2.1.0 has no Python 3.11 wheel). The worker lets
  it import on 3.11 by relaxing, at run time, Python 3.11's ban on ndarray dataclass defaults.
  For the experts' peer (`benchmarks.expert_throughput --omnisafe`) it also gets
  `omnisafe==0.5.0` without its dependencies (they would lift numpy past 2 and pandas to 3,
  which break safety-gymnasium 1.0.0) plus what its PPOLag imports.

    python -m benchmarks.peers.setup [--root .peers] [--force]
"""

import argparse
import glob
import os
import shutil
import subprocess
import sys
import time
from pathlib import Path

ROOT = Path(__file__).resolve().parents[2] / ".peers"

# Each environment: (python version, [pip install argument lists, run in order]).
SPECS = {
    "safety-gymnasium": ("3.10", [["safety-gymnasium==1.0.0"]]),
    "osrl": ("3.11", [
        ["torch==2.13.0"],
        ["--no-deps", "osrl-lib==0.1.0", "fast-safe-rl==0.1.0", "safety-gymnasium==1.0.0",
         "gymnasium-robotics==1.2.2", "pettingzoo==1.24.3", "jax-jumpy==1.0.0"],
        ["numpy<2", "scipy", "pyyaml", "tqdm", "tensorboard", "wandb", "gymnasium==0.28.1",
         "mujoco==2.3.3", "xmltodict", "imageio", "glfw", "PyOpenGL", "Jinja2"],
        ["--no-deps", "omnisafe==0.5.0"],
        ["numpy<2", "pandas<3", "matplotlib<3.11", "seaborn", "moviepy", "typer", "gdown"],
    ]),
}


def find_python(version: str) -> str:
    """A `pythonX.Y` interpreter: $PEER_PYTHON<XY>, then PATH, then pyenv's versions folder."""
    explicit = os.environ.get("PEER_PYTHON" + version.replace(".", ""))
    candidates = [explicit, shutil.which(f"python{version}")]
    candidates += sorted(glob.glob(os.path.expanduser(f"~/.pyenv/versions/{version}.*/bin/python")))
    for c in candidates:
        if c and subprocess.run([c, "--version"], capture_output=True).returncode == 0:
            return c
    raise RuntimeError(f"no Python {version} found; set PEER_PYTHON{version.replace('.', '')}")


def venv_python(name: str, root: Path = ROOT) -> Path:
    """The interpreter of peer environment `name`."""
    return root / name / "bin" / "python"


def _size_mb(path: Path) -> float:
    files = (f for f in path.rglob("*") if f.is_file() and not f.is_symlink())
    return sum(f.stat().st_size for f in files) / 2**20


def ensure(name: str, root: Path = ROOT, force: bool = False) -> dict:
    """Builds environment `name` unless a finished one exists; returns its facts.

    A `.done` marker holding the spec is written last, so an interrupted or changed install is
    rebuilt from scratch on the next call. Raises RuntimeError if pip fails or if a CUDA package
    slipped in (the comparison is CPU against CPU, and those are several GB).
    """
    version, steps = SPECS[name]
    target, marker = root / name, root / name / ".done"
    spec = repr(SPECS[name])
    timing = target / ".install_s"  # kept so that later runs can still report it
    if not force and marker.exists() and marker.read_text() == spec:
        earlier = float(timing.read_text()) if timing.exists() else None
        return {"name": name, "path": str(target), "installed_now": False,
                "install_s": earlier, "size_mb": round(_size_mb(target))}
    shutil.rmtree(target, ignore_errors=True)
    t = time.perf_counter()
    subprocess.run([find_python(version), "-m", "venv", str(target)], check=True)
    pip = [str(venv_python(name, root)), "-m", "pip", "install", "--quiet"]
    for args in steps:
        proc = subprocess.run(pip + args, capture_output=True, text=True)
        if proc.returncode:
            raise RuntimeError(f"pip install {' '.join(args)} failed in {name}:\n"
                               f"{proc.stderr[-3000:]}")
    frozen = subprocess.run([str(venv_python(name, root)), "-m", "pip", "freeze"],
                            capture_output=True, text=True, check=True).stdout
    cuda = [line for line in frozen.splitlines() if line.lower().startswith(("nvidia", "cuda"))]
    if cuda:
        raise RuntimeError(f"CUDA packages were installed into {name}: {cuda}")
    seconds = time.perf_counter() - t
    timing.write_text(f"{seconds:.1f}")
    marker.write_text(spec)
    return {"name": name, "path": str(target), "installed_now": True,
            "install_s": round(seconds, 1), "size_mb": round(_size_mb(target))}


def ensure_all(root: Path = ROOT, force: bool = False) -> list[dict]:
    """Builds every peer environment that is missing; returns their facts."""
    root.mkdir(parents=True, exist_ok=True)
    return [ensure(name, root, force) for name in SPECS]


def main() -> None:
    """Command line: build the environments and print their facts."""
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--root", type=Path, default=ROOT)
    ap.add_argument("--force", action="store_true", help="rebuild even if present")
    args = ap.parse_args()
    for facts in ensure_all(args.root, args.force):
        print(facts, file=sys.stderr)


if __name__ == "__main__":
    main()
