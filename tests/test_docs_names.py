"""Docs name code that exists: every `service/...py`, `training/...py` or `bench/...py` path in
README.md and docs/*.md is a file of the repository, and every dotted `service.x.y`,
`training.x.y` or `bench.x.y` name there imports (a module, or an attribute of one)."""

from __future__ import annotations

import importlib
import re
from pathlib import Path

import pytest

REPO = Path(__file__).resolve().parents[1]
DOCS = [REPO / "README.md", *sorted((REPO / "docs").glob("*.md"))]
PATH = re.compile(r"`((?:service|training|bench|tests)/[\w/]+\.py)")
DOTTED = re.compile(r"`((?:service|training|bench)(?:\.\w+)+)")
# A dotted name that ends in one of these is a file (deploy/k8s/service.yaml), not code.
FILE_SUFFIXES = {"yaml", "yml", "json", "md", "py", "toml", "onnx", "npz", "csv", "png", "sh"}


def _paths() -> list[tuple[str, str]]:
    return [(doc.name, m) for doc in DOCS for m in PATH.findall(doc.read_text(encoding="utf-8"))]


@pytest.mark.parametrize(("doc", "path"), _paths())
def test_named_file_exists(doc: str, path: str) -> None:
    assert (REPO / path).is_file(), f"{doc} names {path}, which does not exist"


def _resolves(name: str) -> bool:
    parts = name.split(".")
    for cut in range(len(parts), 0, -1):
        try:
            obj = importlib.import_module(".".join(parts[:cut]))
        except ModuleNotFoundError:
            continue
        for attr in parts[cut:]:
            if not hasattr(obj, attr):
                return False
            obj = getattr(obj, attr)
        return True
    return False


def _dotted() -> list[tuple[str, str]]:
    return [(doc.name, name) for doc in DOCS
            for name in sorted(set(DOTTED.findall(doc.read_text(encoding="utf-8"))))
            if name.rsplit(".", 1)[-1] not in FILE_SUFFIXES]


def test_architecture_names_code() -> None:
    assert any(doc == "architecture.md" for doc, _ in _dotted()), (
        "docs/architecture.md names no service.x.y: the pattern no longer matches it")


@pytest.mark.parametrize(("doc", "name"), _dotted())
def test_named_code_resolves(doc: str, name: str) -> None:
    assert _resolves(name), f"{doc} names {name}, which does not import"


def test_docs_name_the_shipped_model_version() -> None:
    """The model the docs say `exported/` holds, and the one the committed benchmark measured, are
    the model that `exported/manifest.json` names (a re-export changes the version's hash)."""
    import json

    shipped = json.loads((REPO / "exported" / "manifest.json").read_text(encoding="utf-8"))["model_version"]
    claims = {
        "docs/training.md": re.search(r"`exported/` holds \*\*`([\w.-]+)`\*\*",
                                      (REPO / "docs" / "training.md").read_text(encoding="utf-8")),
        "docs/benchmark.md": re.search(r"^- Artifact: `([\w.-]+)`",
                                       (REPO / "docs" / "benchmark.md").read_text(encoding="utf-8"), re.M),
    }
    for doc, match in claims.items():
        assert match, f"{doc} no longer says which model it is about: the pattern needs updating"
        assert match.group(1) == shipped, f"{doc} names {match.group(1)}; exported/ holds {shipped}"
