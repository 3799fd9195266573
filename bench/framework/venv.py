"""The framework peer's own virtual environment (``bench/.venv-peer``, git-ignored).

The serving frameworks pin their own web stack (starlette, pydantic, uvicorn, ...), which need
not agree with the project's lock (docker/constraints.txt), so they live in a venv of their own
and the project's environment stays as locked. The peer's numeric packages are installed at the
project's locked versions (read from docker/constraints.txt, the one owner of those versions),
so both sides run the same ONNX Runtime, FAISS and numpy; the framework is pinned here.

``python -m bench framework-venv`` creates it (.ci/run does, before the tests); the bench and
its test call ``ensure_venv`` too, which does nothing when the venv matches what it should hold.
"""

from __future__ import annotations

import fcntl
import hashlib
import json
import logging
import subprocess
import sys
from pathlib import Path

log = logging.getLogger(__name__)

BENCH = Path(__file__).resolve().parent.parent
REPO = BENCH.parent
VENV = BENCH / ".venv-peer"
CONSTRAINTS = REPO / "docker" / "constraints.txt"
# The frameworks, pinned. BentoML 1.4.30 is the last release before 1.4.31's client between
# Services started closing its HTTP session every 100 requests with other requests still in
# flight on it (bentoml/BentoML#5540, open): with 1.4.40, 15 of 96 requests at c = 32 failed with
# "Server disconnected" in a smoke run, which would measure that bug, not BentoML's batching.
FRAMEWORKS = {"bentoml": "bentoml==1.4.30", "litserve": "litserve==0.2.19"}
# What bench.framework.pipeline imports, at the project's locked versions (pyarrow and numba:
# through service.geometry.mesh, whose OBJ readers use them; llvmlite is numba's compiler).
NUMERIC = ("numpy", "onnxruntime", "faiss-cpu", "scipy", "trimesh", "pyarrow", "numba", "llvmlite")
STAMP = "complementme-peer.json"  # what the venv was built from; a different one rebuilds it


def requirements(constraints: Path = CONSTRAINTS) -> list[str]:
    """The peer venv's pinned requirements: the frameworks, and the numeric packages as locked."""
    locked: dict[str, str] = {}
    for line in constraints.read_text().splitlines():
        name, sep, version = line.strip().partition("==")
        if sep and not line.lstrip().startswith("#"):
            locked[name.lower()] = version.split(";")[0].strip()
    missing = [n for n in NUMERIC if n not in locked]
    if missing:
        raise RuntimeError(f"{constraints}: no pinned version of {', '.join(missing)}")
    return [*FRAMEWORKS.values(), *(f"{n}=={locked[n]}" for n in NUMERIC)]


def venv_python(folder: Path = VENV) -> Path:
    return folder / "bin" / "python"


def ensure_venv(folder: Path = VENV, timeout: float = 1200.0) -> Path:
    """The peer venv's python, creating or rebuilding the venv when it is missing or out of date.

    One process at a time builds it (a lock file beside the folder): a test and the command run
    together once left a venv whose stamp said "built" while the other's ``--clear`` had emptied
    it, so the stamp is trusted only when the frameworks are also installed.
    """
    wanted = requirements()
    folder.parent.mkdir(parents=True, exist_ok=True)
    with open(folder.parent / f"{folder.name}.lock", "w") as lock:
        fcntl.flock(lock, fcntl.LOCK_EX)
        python = venv_python(folder)
        if _built(folder, wanted):
            return python
        log.info("creating the framework peer's venv %s (%s)", folder, ", ".join(wanted))
        # The project's interpreter makes the venv: same Python version on both sides.
        subprocess.run([sys.executable, "-m", "venv", "--clear", str(folder)], check=True, timeout=timeout)
        proc = subprocess.run([str(python), "-m", "pip", "install", "--quiet", "--disable-pip-version-check",
                               *wanted], capture_output=True, text=True, timeout=timeout, check=False)
        if proc.returncode != 0:
            raise RuntimeError(f"pip could not install the peer's requirements into {folder}:\n"
                               f"{proc.stderr[-3000:] or proc.stdout[-3000:]}")
        digest = hashlib.sha256("\n".join(wanted).encode()).hexdigest()
        (folder / STAMP).write_text(json.dumps({"requirements": wanted, "sha256": digest}, indent=1) + "\n")
        return python


def _built(folder: Path, wanted: list[str]) -> bool:
    """Whether the venv was built from ``wanted`` and still holds both frameworks."""
    python, stamp = venv_python(folder), folder / STAMP
    if not (python.is_file() and stamp.is_file()):
        return False
    try:
        if json.loads(stamp.read_text()).get("requirements") != wanted:
            return False
    except json.JSONDecodeError:
        return False
    try:
        return set(FRAMEWORKS) <= set(installed_versions(python))
    except (subprocess.SubprocessError, OSError, ValueError):
        return False


def installed_versions(python: Path, names: tuple[str, ...] = (*FRAMEWORKS, *NUMERIC)) -> dict[str, str]:
    """Versions of ``names`` in the venv of ``python`` (recorded with the results)."""
    code = ("import json, sys\nfrom importlib.metadata import version, PackageNotFoundError\n"
            "out = {}\nfor n in sys.argv[1:]:\n    try: out[n] = version(n)\n"
            "    except PackageNotFoundError: pass\nprint(json.dumps(out))")
    proc = subprocess.run([str(python), "-c", code, *names], capture_output=True, text=True, timeout=60,
                          check=True)
    return dict(json.loads(proc.stdout))
