"""Rebuild the README's example queries: a held-out chair of the built-in dataset minus its legs.

Run from the repository root: ``python examples/make_examples.py``. The chair is regenerated
from its seed (shape ``chair-0000``, in the shipped model's test split), so the files are the
same on every machine.

Writes:
    examples/chair-without-legs.obj   the partial assembly as a mesh (for /suggest/mesh)
    examples/chair-without-legs.json  a /suggest request: 1000 surface points, k = 5
"""

from __future__ import annotations

import json
from pathlib import Path

import numpy as np
import trimesh

from service.geometry import sample_surface
from training.data.generator.generate import generate_shape

HERE = Path(__file__).resolve().parent


def main() -> None:
    shape = generate_shape("chair", 0, seed=0)
    kept = [p for p in shape.pieces if p.label != "leg"]
    assert len(kept) < len(shape.pieces), "chair-0000 should have legs to remove"
    mesh = trimesh.util.concatenate([trimesh.Trimesh(p.vertices, p.faces, process=False) for p in kept])
    (HERE / "chair-without-legs.obj").write_text(trimesh.exchange.obj.export_obj(
        mesh, include_normals=False, include_texture=False, include_color=False))
    points = sample_surface(np.asarray(mesh.vertices), np.asarray(mesh.faces), 1000, seed=0)
    request = {"points": np.round(points.astype(np.float64), 4).tolist(), "k": 5, "category": "chair"}
    (HERE / "chair-without-legs.json").write_text(json.dumps(request) + "\n")


if __name__ == "__main__":
    main()
