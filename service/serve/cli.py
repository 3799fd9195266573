"""The `complementme` command line, owned by the service: serve, suggest, batch.

Each command is a thin wrapper: parse options, call the app factory or the client. Nothing here
imports torch, so `complementme serve` runs with the service's dependencies alone. Other parts
of the distribution add their commands through the ``complementme.commands`` entry-point group
(``training.cli:register``: data, catalog, train, export, evaluate); a training command run
without the train extra answers in one line which extra it needs.
"""

from __future__ import annotations

import logging
import os
import sys
from importlib.metadata import entry_points
from pathlib import Path
from typing import Any

import typer

from service.serve.logs import LOG_FORMAT, quiet_libraries

log = logging.getLogger(__name__)

APP_FACTORY = "service.api.app:create_app"  # what uvicorn serves (the benchmarks' set-ups serve it too)
# uvicorn's httptools protocol answering parser errors with the JSON error body (its ``http``).
HTTP_PROTOCOL = "service.api.http_protocol:JsonErrorProtocol"
GRACEFUL_SECONDS = 10  # uvicorn's grace for requests in flight at a stop


def _frame_options(up_axis: str | None, center: str | None, radius: float | None) -> dict[str, Any] | None:
    """The request's ``frame`` from the command's options (None: none given)."""
    if up_axis is None and center is None and radius is None:
        return None
    frame: dict[str, Any] = {"up_axis": up_axis or "y"}
    if center is not None:
        try:
            frame["center"] = [float(x) for x in center.split(",")]
        except ValueError:
            raise typer.BadParameter(f"--center must be x,y,z numbers, found {center!r}") from None
        if len(frame["center"]) != 3:
            raise typer.BadParameter(f"--center must be three numbers x,y,z, found {center!r}")
    if radius is not None:
        frame["radius"] = radius
    return frame


def _check_catalog(s: Any) -> None:
    """Open the catalog store as the server will (``StoreError`` if it cannot be served)."""
    if s.catalog_backend == "postgres":
        from service.catalog_store.pg_store import PgCatalogStore

        PgCatalogStore(s.database_url.get_secret_value(), timeout=s.database_timeout,
                       migrate_schema=s.database_migrate).close()
        return
    from service.catalog_store.store import CatalogStore

    store = CatalogStore(s.data_dir)
    try:
        store.check_folder()
    finally:
        store.close()


def _options(k: int | None, category: list[str] | None, exclude_shape: list[str] | None,
             frame: dict[str, Any] | None, fit: bool | None = None) -> dict[str, Any]:
    opts: dict[str, Any] = {"k": k, "frame": frame}
    if fit is not None:
        opts["fit_frame"] = fit
    if category:
        opts["category"] = category
    if exclude_shape:
        opts["exclude_shapes"] = exclude_shape
    return opts


def _table(answer: dict[str, Any]) -> str:
    rows = [("rank", "part_id", "category", "label", "score", "mode (weight)", "translation")]
    for s in answer["suggestions"]:
        t = ", ".join(f"{x:.3f}" for x in s["translation"])
        rows.append((str(s["rank"]), s["part_id"], s["category"], s["label"] or "-", f"{s['score']:.2f}",
                     f"{s['mode']} ({s['mode_weight']:.2f})", f"[{t}]"))
    widths = [max(len(r[i]) for r in rows) for i in range(len(rows[0]))]
    lines = ["  ".join(cell.ljust(w) for cell, w in zip(r, widths, strict=True)).rstrip() for r in rows]
    f = answer["frame"]
    frame = (f"frame{' (fitted)' if answer.get('frame_fitted') else ''}: centre "
             f"[{', '.join(f'{x:.4g}' for x in f['center'])}], radius {f['radius']:.4g}, up {f['up_axis']}")
    return "\n".join([f"model {answer['model_version']}", frame, *lines])


# The options `suggest` and `batch` share.
UrlOpt = typer.Option("http://127.0.0.1:8000", help="The service's base URL.")
CategoryOpt = typer.Option(None, help="Only this category (repeatable).")


def register_service_commands(app: typer.Typer) -> None:
    """Add the service's commands to the root CLI (kept here so they need no torch)."""

    @app.command()
    def serve(
        artifacts: Path | None = typer.Option(None, help="Artifact folder (default: COMPLEMENTME_ARTIFACTS "
                                              "or exported/ at the repository root)."),
        host: str | None = typer.Option(None, help="Bind address (default: COMPLEMENTME_HOST)."),
        port: int | None = typer.Option(None, help="Port (default: COMPLEMENTME_PORT)."),
    ) -> None:
        """Serve the suggestion API with uvicorn on the exported artifacts: one server process.

        For more cores, run one process per core on ports of their own behind a proxy
        (docker/haproxy/haproxy.cfg, docs/deploy.md).
        """
        import uvicorn
        from pydantic import ValidationError

        quiet_libraries()
        from service.settings import ENV_PREFIX, get_settings

        # Options become environment settings: the app factory reads its settings from there.
        if artifacts is not None:
            os.environ[ENV_PREFIX + "ARTIFACTS"] = str(artifacts.resolve())
        for name, value in (("HOST", host), ("PORT", port)):
            if value is not None:
                os.environ[ENV_PREFIX + name] = str(value)
        get_settings.cache_clear()
        try:
            s = get_settings()
        except ValidationError as exc:
            typer.echo(f"error: invalid {ENV_PREFIX}* setting:\n{exc}", err=True)
            raise typer.Exit(2) from None
        if s.catalog_enabled:
            # The lifespan checks the data folder (or the database) too, but a refusal there ends
            # in uvicorn's start-up traceback; checked here first, it is one line that names the
            # files (or the database, its password left out).
            from service.catalog_store.store import StoreError

            try:
                _check_catalog(s)
            except StoreError as exc:
                typer.echo(f"error: {exc}", err=True)
                raise typer.Exit(1) from None
        log.info("serving %s on http://%s:%d", s.artifacts, s.host, s.port)
        uvicorn.run(APP_FACTORY, factory=True, http=HTTP_PROTOCOL, host=s.host, port=s.port,
                    log_level=s.log_level, timeout_graceful_shutdown=GRACEFUL_SECONDS)

    @app.command()
    def suggest(
        file: Path = typer.Argument(..., exists=True, dir_okay=False, help=(
            "A mesh (.obj .ply .stl .off .glb .gltf), points (.npy; .xyz .pts .txt: x y z per line) "
            "or a saved /suggest request (.json, e.g. examples/chair-without-legs.json).")),
        url: str = UrlOpt,
        k: int | None = typer.Option(None, "--k", "-k", help=(
            "Suggestions to show [default: the request file's k, else the service's "
            "COMPLEMENTME_DEFAULT_K, 10].")),
        category: list[str] | None = CategoryOpt,
        exclude_shape: list[str] | None = typer.Option(None, help="Never parts of this shape (repeatable)."),
        up_axis: str | None = typer.Option(None, help="The file's up axis: y or z."),
        center: str | None = typer.Option(None, help="Centre of the complete object in file units: x,y,z."),
        radius: float | None = typer.Option(None, help="Radius of the complete object in file units."),
        fit: bool | None = typer.Option(None, "--fit/--no-fit", help=(
            "Let the service estimate the complete object's frame from the file (centre, radius and, "
            "without --up-axis, the up axis); --center and --radius are then ignored. --no-fit reads "
            "the file in the given (or canonical) frame. [default: the service's: a mesh sent without "
            "a frame is fitted (COMPLEMENTME_FIT_FRAME_UPLOADS), points are not]")),
        as_json: bool = typer.Option(False, "--json", help="Print the service's JSON answer."),
        timeout: float = typer.Option(30.0, help="Seconds per request."),
    ) -> None:
        """Ask a running service for suggestions for one file and print a ranked table."""
        import orjson

        quiet_libraries()
        from service.serve.client import ClientError, ComplementMeClient, suggest_file

        with ComplementMeClient(url, timeout=timeout) as client:
            try:
                frame = (({"up_axis": up_axis} if up_axis else None) if fit
                         else _frame_options(up_axis, center, radius))
                options = _options(k, category, exclude_shape, frame, fit)
                answer = suggest_file(client, file, **options)
            except (ClientError, ValueError, OSError) as exc:  # the service's refusal, or a bad file
                typer.echo(f"error: {exc}", err=True)
                raise typer.Exit(1) from None
        typer.echo(orjson.dumps(answer, option=orjson.OPT_INDENT_2).decode() if as_json else _table(answer))

    @app.command()
    def batch(
        folder: Path = typer.Argument(..., exists=True, file_okay=False, help=(
            "Folder of meshes, point files and .json requests (the files `suggest` takes); "
            "other files and sub-folders are listed as skipped.")),
        url: str = UrlOpt,
        out: Path = typer.Option(Path("results.jsonl"), help="JSON Lines output, one line per file."),
        concurrency: int = typer.Option(4, min=1, max=256, help="Requests in flight at once."),
        k: int | None = typer.Option(None, "--k", "-k", help=(
            "Suggestions per file [default: a request file's k, else the service's COMPLEMENTME_DEFAULT_K, "
            "10].")),
        category: list[str] | None = CategoryOpt,
        up_axis: str | None = typer.Option(None, help="The files' up axis: y or z."),
        timeout: float = typer.Option(60.0, help="Seconds per request."),
    ) -> None:
        """Send every file of a folder to the service and write the answers as JSON Lines.

        Exits with status 1 when any file failed (its line then holds the error).
        """
        from tqdm import tqdm

        quiet_libraries()
        from service.serve.client import ComplementMeClient, query_files, run_batch, skipped_files

        files = query_files(folder)
        skipped = skipped_files(folder)
        for path, reason in skipped:
            typer.echo(f"skipped {path}: {reason}", err=True)
        if not files:
            typer.echo(f"error: no mesh or point files in {folder}", err=True)
            raise typer.Exit(1)
        frame = {"up_axis": up_axis} if up_axis else None
        with ComplementMeClient(url, timeout=timeout) as client, tqdm(total=len(files), unit="file") as bar:
            ok, failed = run_batch(client, files, out, concurrency=concurrency, progress=bar,
                                   **_options(k, category, None, frame))
        typer.echo(f"{ok} answered, {failed} failed, {len(skipped)} skipped; wrote {out}")
        if failed:
            raise typer.Exit(1)


# ------------------------------------------------------------------ the root command

app = typer.Typer(help="ComplementMe: component suggestions for 3D modeling.", no_args_is_help=True,
                  rich_markup_mode=None)


@app.callback()
def main(verbose: bool = typer.Option(False, "--verbose", "-v", help="Log debug messages.")) -> None:
    logging.basicConfig(level=logging.DEBUG if verbose else logging.INFO, format=LOG_FORMAT)
    quiet_libraries()


register_service_commands(app)

# Where other packages of the distribution register their commands: each entry point is a
# function taking the root Typer app.
COMMANDS_GROUP = "complementme.commands"

# Modules of pyproject's `train` extra (tests/training/test_cli_extras.py keeps the two equal):
# a serve-only install (`pip install -e .`, the Docker image) lacks them.
TRAIN_EXTRA_MODULES = frozenset({"torch", "onnx", "onnxscript", "matplotlib"})


def load_commands(root: typer.Typer) -> None:
    """Add the commands registered under ``COMMANDS_GROUP`` (training's, when it is installed)."""
    for entry in entry_points(group=COMMANDS_GROUP):
        entry.load()(root)


def run() -> None:
    """The `complementme` entry point: the CLI, with a one-line answer when the train extra is missing."""
    try:
        load_commands(app)
        app()
    except ModuleNotFoundError as exc:
        missing = (exc.name or "").split(".")[0]
        if missing not in TRAIN_EXTRA_MODULES:
            raise
        command = " ".join(a for a in sys.argv[1:3] if not a.startswith("-")) or "this command"
        typer.echo(f"error: `complementme {command}` needs {missing}, from the train extra: "
                   "pip install -e \".[train]\" (see the README for torch's CPU build)", err=True)
        sys.exit(2)
