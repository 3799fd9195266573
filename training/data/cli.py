"""`complementme data ...`: generate, ingest, preprocess and describe shape data.

Each command is a thin wrapper: parse options, call one function of the data package.
"""

from __future__ import annotations

import typer

data_app = typer.Typer(help="Shape data: generate, ingest, preprocess (paper Section 4), statistics.",
                       no_args_is_help=True)

# Commands are added below, one function each: generate (generator), ingest, preprocess, stats.
