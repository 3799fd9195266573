"""Training's commands on the `complementme` command line (the service owns the root command,
``service.serve.cli``): data, catalog, train, export and evaluate.

``register`` is the ``complementme.commands`` entry point. Importing this module registers them
on the root app too, so ``training.cli.app`` is the whole command line (``python -m training``,
torchrun, the tests). Torch is imported inside the training commands only, so `complementme
serve` works in an environment that has the service's dependencies alone.
"""

from __future__ import annotations

import typer

from service.serve.cli import TRAIN_EXTRA_MODULES, app, run
from training.catalog_cli import catalog_app
from training.commands import register_training_commands
from training.data.cli import data_app
from training.evaluate.cli import register_evaluate_command

__all__ = ["TRAIN_EXTRA_MODULES", "app", "register", "run"]

_registered: set[int] = set()


def register(root: typer.Typer) -> None:
    """Add training's commands to ``root`` (once: the entry point and the import may both ask)."""
    if id(root) in _registered:
        return
    _registered.add(id(root))
    root.add_typer(data_app, name="data")
    root.add_typer(catalog_app, name="catalog")
    register_training_commands(root)
    register_evaluate_command(root)


register(app)
