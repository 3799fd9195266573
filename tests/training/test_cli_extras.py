"""The CLI in a serve-only install: training commands say which extra they need, in one line."""

from __future__ import annotations

import logging
import re
import subprocess
import sys
from pathlib import Path

import pytest
import tomllib

from service.serve.logs import quiet_libraries
from training.cli import TRAIN_EXTRA_MODULES

REPO = Path(__file__).resolve().parents[2]

# Runs the CLI with the train extra's modules made unimportable, as in `pip install -e .`.
WITHOUT_TRAIN_EXTRA = """
import sys
class Missing:
    def find_spec(self, name, path=None, target=None):
        if name.split(".")[0] in {modules!r}:
            raise ModuleNotFoundError(f"No module named {{name!r}}", name=name)
sys.meta_path.insert(0, Missing())
from training.cli import run
sys.argv = ["complementme", *sys.argv[1:]]
run()
"""


def test_train_extra_modules_are_pyprojects_train_extra() -> None:
    with open(REPO / "pyproject.toml", "rb") as fh:
        train = tomllib.load(fh)["project"]["optional-dependencies"]["train"]
    assert {re.split(r"[<>=!~\[; ]", req, maxsplit=1)[0] for req in train} == TRAIN_EXTRA_MODULES


@pytest.mark.parametrize(("args", "command"), [
    (["train", "--preset", "shipped", "--data", "{tmp}/data", "--run", "{tmp}/run"], "train"),
    (["export", "--run", "{tmp}/run", "--out", "{tmp}/out"], "export"),
    (["category-head", "--run", "{tmp}/run", "--outside", "{tmp}/data"], "category-head"),
])
def test_training_command_without_the_train_extra_says_so(tmp_path: Path, args: list[str],
                                                          command: str) -> None:
    code = WITHOUT_TRAIN_EXTRA.format(modules=set(TRAIN_EXTRA_MODULES))
    done = subprocess.run([sys.executable, "-c", code, *(a.format(tmp=tmp_path) for a in args)],
                          cwd=REPO, capture_output=True, text=True, timeout=300)
    assert done.returncode == 2, done.stderr
    lines = done.stderr.strip().splitlines()
    assert len(lines) == 1, done.stderr  # no traceback
    assert lines[0].startswith(f"error: `complementme {command}` needs ") and '.[train]' in lines[0], lines


def test_library_chatter_is_quiet_unless_verbose() -> None:
    root = logging.getLogger()
    before = root.level, {n: logging.getLogger(n).level for n in ("httpx", "faiss.loader")}
    try:
        for n in before[1]:
            logging.getLogger(n).setLevel(logging.NOTSET)
        root.setLevel(logging.DEBUG)  # -v
        quiet_libraries()
        assert logging.getLogger("faiss.loader").getEffectiveLevel() == logging.DEBUG
        root.setLevel(logging.INFO)
        quiet_libraries()
        assert not logging.getLogger("faiss.loader").isEnabledFor(logging.INFO)
        assert not logging.getLogger("httpx").isEnabledFor(logging.INFO)
    finally:
        root.setLevel(before[0])
        for n, level in before[1].items():
            logging.getLogger(n).setLevel(level)


def test_evaluate_writes_its_report_beside_its_own_out_folder() -> None:
    """Only the committed benchmark (no --out, no --quick) writes docs/benchmark.md: an exploratory
    run with --out keeps its report beside its results."""
    from training.evaluate.cli import QUICK_OUT, default_report

    assert default_report(None, quick=False) == Path("docs/benchmark.md")
    assert default_report(Path("/tmp/try"), quick=False) == Path("/tmp/try/benchmark.md")
    assert default_report(None, quick=True) == QUICK_OUT / "benchmark.md"
    assert default_report(Path("/tmp/try"), quick=True) == Path("/tmp/try/benchmark.md")
