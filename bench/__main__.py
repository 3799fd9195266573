"""``python -m bench <command>``: the benchmark commands (see ``bench.cli``)."""

from bench.cli import app

app()
