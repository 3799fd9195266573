"""Rebuild the README's example queries: a held-out chair of the built-in dataset minus its legs.

Run from the repository root: ``python examples/make_examples.py``, again after every export.
The chair is the first chair of the shipped model's test split (``exported/catalog.json``; the
model never trained on it, though its parts are in the catalog) that has legs, regenerated from
its seed, so the files are the same on every machine. The OBJ's first line names it.

Writes:
    examples/chair-without-legs.obj   the partial assembly as a mesh (for /suggest/mesh)
    examples/chair-without-legs.json  a /suggest request: 1000 surface points, k = 5
"""

from __future__ import annotations

import json
import re
from pathlib import Path

import numpy as np
import trimesh

from service.artifacts.layout import CATALOG_JSON
from service.geometry.mesh import sample_surface
from service.settings import DEFAULT_ARTIFACTS
from training.data.generator.generate import generate_shape
from training.data.shapes import RawShape

HERE = Path(__file__).resolve().parent
DATASET_SEED = 0  # training/recipes/shipped.sh: `complementme data generate --seed 0`


def held_out_chair(catalog_json: Path = DEFAULT_ARTIFACTS / CATALOG_JSON) -> RawShape:
    """The first generated chair of the catalog's test split that has legs."""
    records = json.loads(catalog_json.read_text())
    held_out = sorted({r["shape_id"] for r in records
                       if r["category"] == "chair" and r.get("split") == "test"})
    for shape_id in held_out:
        match = re.fullmatch(r"chair-(\d+)", shape_id)
        shape = generate_shape("chair", int(match.group(1)), seed=DATASET_SEED) if match else None
        if shape is not None and any(p.label == "leg" for p in shape.pieces):
            return shape
    raise SystemExit(f"no generated chair with legs in the test split of {catalog_json}")


def main() -> None:
    shape = held_out_chair()
    kept = [p for p in shape.pieces if p.label != "leg"]
    mesh = trimesh.util.concatenate([trimesh.Trimesh(p.vertices, p.faces, process=False) for p in kept])
    header = f"# {shape.shape_id} without its legs: a chair of the shipped model's test split\n"
    (HERE / "chair-without-legs.obj").write_text(header + trimesh.exchange.obj.export_obj(
        mesh, include_normals=False, include_texture=False, include_color=False))
    points = sample_surface(np.asarray(mesh.vertices), np.asarray(mesh.faces), 1000, seed=0)
    request = {"points": np.round(points.astype(np.float64), 4).tolist(), "k": 5, "category": "chair"}
    (HERE / "chair-without-legs.json").write_text(json.dumps(request) + "\n")


if __name__ == "__main__":
    main()
