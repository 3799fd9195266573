"""Service commands of the `complementme` CLI: serve, suggest, batch."""

from __future__ import annotations

import typer


def register_service_commands(app: typer.Typer) -> None:
    """Add the service's commands to the root CLI (kept here so they need no torch)."""
