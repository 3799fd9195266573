"""Offline pictures of automatic assemblies: the runs of `complementme evaluate-assembly`, drawn.

Each run is drawn as its catalog meshes where the assembly placed them (scaled about their
centres, as ``/export`` writes them), one colour per part (the start part first), flat-shaded by
matplotlib (Agg: no display, no GPU). Issue 18 asks for pictures of a few assemblies per
category beside the evaluation's figures; these are that, made by the same command from the
same runs, so a picture never shows an assembly the table did not measure.
"""

from __future__ import annotations

from collections.abc import Sequence
from pathlib import Path
from typing import Any

import numpy as np

from service.artifacts.catalog import Catalog
from service.geometry.frames import Frame
from service.modeling.export_mesh import ExportItem, placed_meshes

# Distinct, print-safe colours; the start part is always the first.
COLOURS = ("#3b6ea5", "#e07b39", "#4c9a4c", "#c94c4c", "#8e6bb8", "#8c6d4f", "#d47fb6", "#7f7f7f",
           "#b5b83a", "#3fb5c4")
# The canonical frame is y up, front +x; matplotlib's 3D axes are z up: draw (x, z, y).
_TO_PLOT = np.array([[1.0, 0.0, 0.0], [0.0, 0.0, 1.0], [0.0, 1.0, 0.0]])
_LIGHT = np.array([0.4, -0.5, 0.75]) / np.linalg.norm([0.4, -0.5, 0.75])


def run_meshes(catalog: Catalog, run: dict[str, Any]) -> list[tuple[np.ndarray, np.ndarray]]:
    """One run's placed meshes (start part first), in the canonical frame, as ``/export`` places
    them (``service.modeling.export_mesh.placed_meshes``).

    Shapes:
        returns [(V, 3) float64 vertices, (F, 3) int64 faces] per part.
    """
    items = [ExportItem(run["start"], tuple(run["start_translation"])),
             *(ExportItem(p, tuple(t), tuple(s))
               for p, t, s in zip(run["parts"], run["translations"], run["scales"], strict=True))]
    return [(np.asarray(m.vertices), np.asarray(m.faces)) for _, m in placed_meshes(catalog, items, Frame())]


def verdict(run: dict[str, Any]) -> str:
    """A run's outcome in words, as the evaluation measured it."""
    if run["empty"]:
        return "nothing added"
    if run["stacked"]:
        return "stacked"
    if run["missing"]:
        return "lacks " + ", ".join(run["missing"])
    return "complete"


def draw_runs(catalog: Catalog, runs: Sequence[dict[str, Any]], path: Path, title: str,
              size: float = 3.2) -> None:
    """Draw ``runs`` side by side into the PNG ``path``, each titled with its start and verdict."""
    import matplotlib

    matplotlib.use("Agg")
    import matplotlib.pyplot as plt
    from mpl_toolkits.mplot3d.art3d import Poly3DCollection

    fig = plt.figure(figsize=(size * max(len(runs), 1), size + 0.5), dpi=110)
    fig.suptitle(title, fontsize=11)
    for k, run in enumerate(runs):
        ax = fig.add_subplot(1, max(len(runs), 1), k + 1, projection="3d")
        lo, hi = np.full(3, np.inf), np.full(3, -np.inf)
        tris: list[np.ndarray] = []
        colours: list[np.ndarray] = []
        for j, (v, f) in enumerate(run_meshes(catalog, run)):
            if len(f) == 0:
                continue
            tri = (v @ _TO_PLOT.T)[f]                                    # (F, 3, 3)
            normal = np.cross(tri[:, 1] - tri[:, 0], tri[:, 2] - tri[:, 0])
            normal /= np.maximum(np.linalg.norm(normal, axis=1, keepdims=True), 1e-12)
            shade = 0.45 + 0.55 * np.abs(normal @ _LIGHT)               # two-sided flat shading
            base = np.array(matplotlib.colors.to_rgb(COLOURS[j % len(COLOURS)]))
            tris.append(tri)
            colours.append(shade[:, None] * base)
        if tris:
            # One collection for every part: matplotlib depth-sorts the triangles of a collection,
            # not collections against each other, so a part drawn per collection could paint over
            # a part in front of it.
            every = np.concatenate(tris)                                  # (T, 3, 3)
            ax.add_collection3d(Poly3DCollection(every, facecolors=np.concatenate(colours), linewidths=0))
            lo, hi = every.reshape(-1, 3).min(0), every.reshape(-1, 3).max(0)
        centre, half = (lo + hi) / 2, max(float(np.max(hi - lo)) / 2, 1e-3)
        for axis, c in zip("xyz", centre, strict=True):
            getattr(ax, f"set_{axis}lim")(c - half, c + half)
        ax.set_box_aspect((1, 1, 1))
        ax.view_init(elev=20, azim=-60)
        ax.set_axis_off()
        ax.set_title(f"{run['start']}\n{verdict(run)}", fontsize=8)
    path.parent.mkdir(parents=True, exist_ok=True)
    fig.savefig(path, bbox_inches="tight")
    plt.close(fig)


def draw_categories(catalog: Catalog, runs: Sequence[dict[str, Any]], out: Path, per_category: int,
                    split: str = "test", strategy: str = "greedy") -> dict[str, Path]:
    """The first ``per_category`` runs of ``strategy`` of each category, one PNG per category
    (``out/<category>.png``); returns the files written."""
    written: dict[str, Path] = {}
    for category in sorted({r["category"] for r in runs}):
        chosen = [r for r in runs if r["category"] == category and r["strategy"] == strategy][:per_category]
        if not chosen:
            continue
        path = Path(out) / f"{category}.png"
        starts = "held-out" if split == "test" else split
        draw_runs(catalog, chosen, path,
                  f"{category}: automatic assembly ({strategy}) from {starts} start parts")
        written[category] = path
    return written
