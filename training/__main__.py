"""``python -m training``: the `complementme` CLI, e.g. under ``torchrun -m training train ...``."""

from training.cli import run

run()
