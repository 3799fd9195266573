"""Fixtures that run the real app on a real artifact folder.

The folder is ``COMPLEMENTME_TEST_ARTIFACTS`` if set, else the repository's ``exported/``; tests
that need it skip (saying why) only when that folder does not exist. Queries are built from the
catalog (see ``service_testkit.assembly_query``).
"""

from __future__ import annotations

import warnings
from collections.abc import Iterator
from pathlib import Path

import pytest

# Starlette asks for httpx2 for its TestClient; httpx still works and is what we ship.
warnings.filterwarnings("ignore", message=".*httpx.*starlette.testclient.*")

from fastapi.testclient import TestClient  # noqa: E402
from pg_testkit import PostgresCluster, find_postgres  # noqa: E402
from service_testkit import (  # noqa: E402
    ARTIFACTS_ENV,
    AssemblyQuery,
    artifacts_folder,
    assembly_query,
    make_settings,
    multi_part_shapes,
)

from service.api.app import create_app  # noqa: E402
from service.artifacts.catalog import Catalog  # noqa: E402
from service.artifacts.loading import load_artifacts  # noqa: E402
from service.settings import Settings  # noqa: E402
from service.suggest.engine import SuggestionEngine  # noqa: E402


@pytest.fixture(scope="session")
def artifacts() -> Path:
    folder = artifacts_folder()
    if not (folder / "manifest.json").is_file():
        pytest.skip(f"no artifact folder at {folder} (set {ARTIFACTS_ENV} or export to exported/)")
    return folder


@pytest.fixture(scope="session")
def settings(artifacts: Path) -> Settings:
    return make_settings(artifacts)


@pytest.fixture(scope="session")
def shipped_settings() -> Settings:
    """The service's own defaults on the test artifact folder (``settings`` is the tests' copy)."""
    return Settings(artifacts=artifacts_folder())


@pytest.fixture(scope="session")
def shipped_engine(shipped_settings: Settings) -> SuggestionEngine:
    """An engine on the trained model with the service's defaults, for the quality tests: skipped
    when the folder holds no model (COMPLEMENTME_TEST_ARTIFACTS, so a candidate is tested on itself)."""
    folder = shipped_settings.artifacts
    if not (folder / "manifest.json").is_file():
        pytest.skip(f"no trained model in {folder}: the quality tests need the shipped artifacts")
    return SuggestionEngine(load_artifacts(folder), shipped_settings)


@pytest.fixture(scope="session")
def client(settings: Settings) -> Iterator[TestClient]:
    """The real app with its lifespan run: artifacts loaded, checked, warmed up."""
    with TestClient(create_app(settings)) as c:
        yield c


@pytest.fixture(scope="session")
def engine(client: TestClient) -> SuggestionEngine:
    return client.app.state.served.engine  # type: ignore[attr-defined]


@pytest.fixture(scope="session")
def catalog(engine: SuggestionEngine) -> Catalog:
    return engine.catalog


@pytest.fixture(scope="session")
def query(catalog: Catalog, engine: SuggestionEngine) -> AssemblyQuery:
    """One assembly query: the first multi-part shape without its last part."""
    shape = multi_part_shapes(catalog, 1)[0]
    last = [r["part_id"] for r in catalog.records if r["shape_id"] == shape][-1]
    return assembly_query(catalog, shape, last, engine.artifacts.n_points)


def _postgres() -> Iterator[PostgresCluster]:
    """A real PostgreSQL server, removed afterwards (skips, saying why, only when it cannot run here)."""
    bindir, why = find_postgres()
    if bindir is None:
        pytest.skip(why)
    cluster = PostgresCluster(bindir).init().start()
    try:
        yield cluster
    finally:
        cluster.remove()


@pytest.fixture(scope="session")
def postgres() -> Iterator[PostgresCluster]:
    """A PostgreSQL server for the session."""
    yield from _postgres()


@pytest.fixture
def own_postgres() -> Iterator[PostgresCluster]:
    """A PostgreSQL server for one test (outage tests stop and start it)."""
    yield from _postgres()


@pytest.fixture
def database_url(postgres: PostgresCluster) -> str:
    """A new, empty database of the session's server."""
    return postgres.new_database()
