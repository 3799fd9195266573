"""`complementme catalog ...`: add a folder of shapes to the catalog; back up, verify and
recover a data folder; migrate the postgres catalog's schema.

Thin wrappers over ``training.catalog_import`` and ``service.catalog_store``'s ``store``, ``recovery``
and ``pg_store``.
"""

from __future__ import annotations

import json
from pathlib import Path
from typing import TYPE_CHECKING

import typer

if TYPE_CHECKING:
    from service.catalog_store.recovery import Report

catalog_app = typer.Typer(help=("The growing catalog: import shapes; back up, verify, recover a data folder; "
                                "migrate the postgres catalog."),
                          no_args_is_help=True)


@catalog_app.command("add")
def add_cmd(
    folder: Path = typer.Argument(..., exists=True, file_okay=False, help=(
        "Folder of shape files (.obj .glb .gltf .ply .off .stl); sub-folders name categories.")),
    url: str | None = typer.Option(None, help="A running service to add to (needs --api-key)."),
    api_key: str | None = typer.Option(None, envvar="COMPLEMENTME_API_KEY", help=(
        "The service's API key (default: COMPLEMENTME_API_KEY).")),
    data_dir: Path | None = typer.Option(None, help=(
        "Write this data folder directly instead of calling a service (loads the artifacts here).")),
    artifacts: Path | None = typer.Option(None, help=(
        "Artifact folder for --data-dir (default: COMPLEMENTME_ARTIFACTS or exported/).")),
    category: str | None = typer.Option(None, help=(
        "Category of every shape (default: its sub-folder's name).")),
    up_axis: str = typer.Option("y", help="The files' up axis: y or z."),
    report: Path | None = typer.Option(None, help="Also write the report as JSON here."),
    timeout: float = typer.Option(120.0, help="Seconds per request (with --url)."),
) -> None:
    """Add every shape of a folder to the catalog: each shape's components become its parts.

    Shapes are read and merged into components as the training data was (paper, Section 4).
    Re-running continues an interrupted import; skipped files are listed with their reason and
    make the command exit with status 1.
    """
    from service.artifacts.layout import ArtifactError
    from service.catalog_store.store import StoreError
    from service.serve.client import ClientError, ComplementMeClient
    from training.catalog_import import HttpSink, LocalSink, import_folder

    if (url is None) == (data_dir is None):
        raise typer.BadParameter("give either --url (a running service) or --data-dir (write it directly)")
    if up_axis not in ("y", "z"):
        raise typer.BadParameter(f"--up-axis must be y or z, found {up_axis!r}")
    try:
        if url is not None:
            if not api_key:
                raise typer.BadParameter("--url needs --api-key (or COMPLEMENTME_API_KEY)")
            with ComplementMeClient(url, timeout=timeout, api_key=api_key) as client:
                result = import_folder(folder, HttpSink(client), category, up_axis)
        else:
            from service.settings import get_settings

            assert data_dir is not None
            sink = LocalSink(artifacts or get_settings().artifacts, data_dir)
            try:
                result = import_folder(folder, sink, category, up_axis)
            finally:
                sink.close()
    except (ClientError, FileNotFoundError, ArtifactError, StoreError) as exc:
        typer.echo(f"error: {exc}", err=True)
        raise typer.Exit(2) from None
    typer.echo(result.table())
    if report is not None:
        report.write_text(json.dumps(result.as_dict(), indent=1) + "\n")
    if result.skipped:
        raise typer.Exit(1)


@catalog_app.command("backup")
def backup_cmd(
    data_dir: Path = typer.Argument(..., exists=True, file_okay=False, help="The data folder to copy."),
    dest: Path = typer.Argument(..., help="An empty or new folder for the copy."),
) -> None:
    """Copy a data folder consistently, also while a server writes to it (SQLite online backup)."""
    from service.catalog_store.store import CatalogStore, StoreError

    try:
        store = CatalogStore(data_dir)
        try:
            files = store.backup(dest)
        finally:
            store.close()
    except StoreError as exc:
        typer.echo(f"error: {exc}", err=True)
        raise typer.Exit(2) from None
    typer.echo(f"{data_dir} -> {dest}: database and {files - 1} geometry file(s) copied")


def _print_report(report: Report) -> None:
    for line in report.restored:
        typer.echo(f"restored: {line}")
    for line in report.notes:
        typer.echo(f"note: {line}")
    for line in report.problems:
        typer.echo(f"problem: {line}", err=True)


@catalog_app.command("verify")
def verify_cmd(
    data_dir: Path = typer.Argument(..., exists=True, file_okay=False, help="The data folder to check."),
) -> None:
    """Check database, geometry files and index against each other (changes nothing).

    Exits with 1 when anything does not match (each problem names its file).
    """
    from service.catalog_store.recovery import verify

    report = verify(data_dir)
    _print_report(report)
    typer.echo(f"{data_dir}: " + ("ok" if report.ok else f"{len(report.problems)} problem(s)"))
    if not report.ok:
        raise typer.Exit(1)


@catalog_app.command("recover")
def recover_cmd(
    data_dir: Path = typer.Argument(..., exists=True, file_okay=False, help="The data folder to repair."),
) -> None:
    """Rebuild rows the database lost (a deleted catalog.sqlite3-wal, an older database put back)
    from the copies the geometry files carry. Stop every server of the folder first.

    Exits with 1 when something could not be restored (listed), 2 when the folder cannot be opened.
    """
    from service.catalog_store.recovery import recover
    from service.catalog_store.store import StoreError

    try:
        report = recover(data_dir)
    except StoreError as exc:
        typer.echo(f"error: {exc}", err=True)
        raise typer.Exit(2) from None
    _print_report(report)
    typer.echo(f"{data_dir}: {len(report.restored)} part(s) restored")
    if not report.ok:
        raise typer.Exit(1)


@catalog_app.command("migrate")
def migrate_cmd(
    database_url: str | None = typer.Option(None, envvar="COMPLEMENTME_DATABASE_URL", show_envvar=True, help=(
        "The postgres catalog's URL, postgresql://USER:PASSWORD@HOST:5432/DBNAME "
        "(default: COMPLEMENTME_DATABASE_URL).")),
    timeout: float = typer.Option(10.0, help="Seconds to wait for the connection."),
) -> None:
    """Create or upgrade the postgres catalog's schema: the versioned migrations it lacks, in one
    transaction. Safe to run again, and while replicas run (they need the new version only after
    an upgrade of the service).

    Exits with 2 when the database cannot be reached or has a newer schema than this version knows.
    """
    import math

    import psycopg

    from service.catalog_store.pg_store import SCHEMA_VERSION, migrate, redacted
    from service.catalog_store.store import StoreError

    if not database_url:
        raise typer.BadParameter("give --database-url (or set COMPLEMENTME_DATABASE_URL)")
    where = redacted(database_url)
    try:
        with psycopg.connect(database_url, connect_timeout=max(1, math.ceil(timeout))) as conn:
            applied = migrate(conn)
    except (psycopg.Error, StoreError) as exc:
        reason = (str(exc).strip().splitlines() or [repr(exc)])[0]
        typer.echo(f"error: {where}: {reason}", err=True)
        raise typer.Exit(2) from None
    done = f"applied migration(s) {', '.join(map(str, applied))}" if applied else "nothing to apply"
    typer.echo(f"{where}: schema version {SCHEMA_VERSION} ({done})")
