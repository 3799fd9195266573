"""Docs name code that exists: every `service/...py`, `training/...py` or `bench/...py` path in
README.md and docs/*.md is a file of the repository, and every dotted `service.x.y` name in
docs/architecture.md imports (a module, or an attribute of one)."""

from __future__ import annotations

import importlib
import re
from pathlib import Path

import pytest

REPO = Path(__file__).resolve().parents[1]
DOCS = [REPO / "README.md", *sorted((REPO / "docs").glob("*.md"))]
PATH = re.compile(r"`((?:service|training|bench|tests)/[\w/]+\.py)")
DOTTED = re.compile(r"`(service(?:\.\w+)+)")


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


def test_architecture_names_resolve() -> None:
    text = (REPO / "docs" / "architecture.md").read_text(encoding="utf-8")
    names = sorted(set(DOTTED.findall(text)))
    assert names, "docs/architecture.md names no service.x.y: the pattern no longer matches it"
    missing = [n for n in names if not _resolves(n)]
    assert not missing, f"docs/architecture.md names code that does not exist: {missing}"


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
