"""Settings: environment variables with one prefix, and the generated docs table kept current."""

from __future__ import annotations

from pathlib import Path

import pytest

from service.settings import DEFAULT_ARTIFACTS, Settings, get_settings, render_settings_markdown

DOC = Path(__file__).resolve().parents[2] / "docs" / "settings.md"


def test_docs_table_is_up_to_date() -> None:
    assert DOC.read_text() == render_settings_markdown(), (
        "docs/settings.md is stale: regenerate it with `python -m service.settings > docs/settings.md`")


def test_every_setting_is_documented() -> None:
    for name, field in Settings.model_fields.items():
        assert field.description and len(field.description) > 10, f"setting {name} has no description"
        assert f"COMPLEMENTME_{name.upper()}" in DOC.read_text()


def test_environment_overrides_and_cache(monkeypatch: pytest.MonkeyPatch) -> None:
    monkeypatch.setenv("COMPLEMENTME_MAX_K", "7")
    monkeypatch.setenv("COMPLEMENTME_ARTIFACTS", "/somewhere/else")
    get_settings.cache_clear()
    try:
        s = get_settings()
        assert s.max_k == 7 and s.artifacts == Path("/somewhere/else")
        assert get_settings() is s
    finally:
        get_settings.cache_clear()


def test_default_artifacts_are_the_repository_export() -> None:
    assert Path(__file__).resolve().parents[2] / "exported" == DEFAULT_ARTIFACTS
