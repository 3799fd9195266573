"""The `complementme` command line: data, training, export and evaluation, plus the service's commands.

Torch is imported inside the training commands only, so `complementme serve` works in an
environment that has the service's dependencies alone.
"""

from __future__ import annotations

import logging

import typer

from service.cli import LOG_FORMAT, register_service_commands
from training.catalog_cli import catalog_app
from training.data.cli import data_app

app = typer.Typer(help="ComplementMe: component suggestions for 3D modeling.", no_args_is_help=True)
app.add_typer(data_app, name="data")
app.add_typer(catalog_app, name="catalog")
register_service_commands(app)


@app.callback()
def main(verbose: bool = typer.Option(False, "--verbose", "-v", help="Log debug messages.")) -> None:
    logging.basicConfig(level=logging.DEBUG if verbose else logging.INFO,
                        format=LOG_FORMAT)


# Training commands (train, export, evaluate) are registered below.

from training.commands import register_training_commands  # noqa: E402

register_training_commands(app)

from training.evaluate.cli import register_evaluate_command  # noqa: E402

register_evaluate_command(app)
