"""The `complementme` command line: data, training, export and evaluation, plus the service's commands.

Torch is imported inside the training commands only, so `complementme serve` works in an
environment that has the service's dependencies alone.
"""

from __future__ import annotations

import logging
import sys

import typer

from service.serve.cli import register_service_commands
from service.serve.logs import LOG_FORMAT, quiet_libraries
from training.catalog_cli import catalog_app
from training.data.cli import data_app

app = typer.Typer(help="ComplementMe: component suggestions for 3D modeling.", no_args_is_help=True,
                  rich_markup_mode=None)
app.add_typer(data_app, name="data")
app.add_typer(catalog_app, name="catalog")
register_service_commands(app)


@app.callback()
def main(verbose: bool = typer.Option(False, "--verbose", "-v", help="Log debug messages.")) -> None:
    logging.basicConfig(level=logging.DEBUG if verbose else logging.INFO,
                        format=LOG_FORMAT)
    quiet_libraries()


# Training commands (train, export, evaluate) are registered below.

from training.commands import register_training_commands  # noqa: E402

register_training_commands(app)

from training.evaluate.cli import register_evaluate_command  # noqa: E402

register_evaluate_command(app)


# Modules of pyproject's `train` extra (tests/training/test_cli_extras.py keeps the two equal):
# a serve-only install (`pip install -e .`, the Docker image) lacks them.
TRAIN_EXTRA_MODULES = frozenset({"torch", "onnx", "onnxscript", "matplotlib"})


def run() -> None:
    """The `complementme` entry point: the CLI, with a one-line answer when the train extra is missing."""
    try:
        app()
    except ModuleNotFoundError as exc:
        missing = (exc.name or "").split(".")[0]
        if missing not in TRAIN_EXTRA_MODULES:
            raise
        command = " ".join(a for a in sys.argv[1:3] if not a.startswith("-")) or "this command"
        typer.echo(f"error: `complementme {command}` needs {missing}, from the train extra: "
                   "pip install -e \".[train]\" (see the README for torch's CPU build)", err=True)
        sys.exit(2)
