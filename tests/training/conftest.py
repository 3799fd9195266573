"""Tiny processed datasets built directly from trimesh primitives, for the training tests.

Shapes are chairs (seat, back, legs, optional arms), tables (top, legs, optional shelf) and lamps
(base, pole, shade) with random proportions; repeated pieces (four legs) form one component, as
preprocessing would merge them. Each shape is centred at its bounding-box centre and scaled to
unit radius, like the processed data.
"""

from __future__ import annotations

from pathlib import Path
from typing import Any

import numpy as np
import pytest
import trimesh

from training.data.processed import ProcessedDataset


def _box(extents: tuple[float, float, float], centre: tuple[float, float, float]) -> trimesh.Trimesh:
    return trimesh.creation.box(extents=extents, transform=trimesh.transformations.translation_matrix(centre))


def _cylinder(radius: float, height: float, centre: tuple[float, float, float]) -> trimesh.Trimesh:
    # trimesh cylinders run along z; ours stand along y.
    m = trimesh.creation.cylinder(radius=radius, height=height, sections=12)
    m.apply_transform(trimesh.transformations.rotation_matrix(np.pi / 2, [1, 0, 0]))
    m.apply_translation(centre)
    return m


def _legs(w: float, d: float, h: float, r: float, y: float) -> trimesh.Trimesh:
    return trimesh.util.concatenate([
        _cylinder(r, h, (sx * (w / 2 - r), y, sz * (d / 2 - r))) for sx in (-1, 1) for sz in (-1, 1)])


def _chair(rng: np.random.Generator) -> tuple[str, list[tuple[str, trimesh.Trimesh]], list[tuple[int, int]]]:
    w, d = rng.uniform(0.4, 0.6), rng.uniform(0.4, 0.6)
    leg_h, seat_t, back_h = rng.uniform(0.35, 0.5), rng.uniform(0.04, 0.08), rng.uniform(0.3, 0.6)
    parts = [
        ("seat", _box((w, seat_t, d), (0, leg_h + seat_t / 2, 0))),
        ("back", _box((w, back_h, 0.04), (0, leg_h + seat_t + back_h / 2, -d / 2 + 0.02))),
        ("leg", _legs(w, d, leg_h, rng.uniform(0.015, 0.03), leg_h / 2)),
    ]
    edges = [(0, 1), (0, 2)]
    style = "plain"
    if rng.random() < 0.5:
        arm_y = leg_h + seat_t + 0.15
        arms = trimesh.util.concatenate([_box((0.04, 0.04, d), (sx * (w / 2 - 0.02), arm_y, 0))
                                         for sx in (-1, 1)])
        parts.append(("arm", arms))
        edges += [(0, 3), (1, 3)]
        style = "armchair"
    return style, parts, edges


def _table(rng: np.random.Generator) -> tuple[str, list[tuple[str, trimesh.Trimesh]], list[tuple[int, int]]]:
    w, d = rng.uniform(0.8, 1.4), rng.uniform(0.5, 0.9)
    leg_h, top_t = rng.uniform(0.5, 0.75), rng.uniform(0.03, 0.08)
    parts = [
        ("top", _box((w, top_t, d), (0, leg_h + top_t / 2, 0))),
        ("leg", _legs(w, d, leg_h, rng.uniform(0.02, 0.05), leg_h / 2)),
    ]
    edges = [(0, 1)]
    style = "plain"
    if rng.random() < 0.5:
        parts.append(("shelf", _box((w * 0.95, 0.02, d * 0.95), (0, leg_h * 0.3, 0))))
        edges.append((1, 2))
        style = "shelved"
    return style, parts, edges


def _lamp(rng: np.random.Generator) -> tuple[str, list[tuple[str, trimesh.Trimesh]], list[tuple[int, int]]]:
    base_r, base_h = rng.uniform(0.1, 0.2), rng.uniform(0.02, 0.05)
    pole_h = rng.uniform(0.4, 0.9)
    shade_r, shade_h = rng.uniform(0.12, 0.25), rng.uniform(0.1, 0.25)
    shade = trimesh.creation.cone(radius=shade_r, height=shade_h, sections=16)
    shade.apply_transform(trimesh.transformations.rotation_matrix(-np.pi / 2, [1, 0, 0]))
    shade.apply_translation((0, base_h + pole_h, 0))
    parts = [
        ("base", _cylinder(base_r, base_h, (0, base_h / 2, 0))),
        ("pole", _cylinder(0.015, pole_h, (0, base_h + pole_h / 2, 0))),
        ("shade", shade),
    ]
    return "cone", parts, [(0, 1), (1, 2)]


MAKERS = {"chair": _chair, "table": _table, "lamp": _lamp}


def make_toy_dataset(n_per_category: int = 6, seed: int = 0, cached_points: int = 256,
                     categories: tuple[str, ...] = ("chair", "table", "lamp"),
                     copies_of_first: int = 0) -> ProcessedDataset:
    """A ProcessedDataset of ``n_per_category`` random shapes per category.

    ``copies_of_first`` appends that many copies of the first shape (same meshes, new point
    samples, new shape ids): near-duplicate parts across shapes.

    Shapes:
        points (C, cached_points, 3) float16, as the real preprocessing writes them.
    """
    rng = np.random.default_rng(seed)
    specs = [(f"{cat}-{i:04d}", cat, *MAKERS[cat](rng)) for cat in categories for i in range(n_per_category)]
    specs += [(f"{specs[0][0]}-copy{j}", *specs[0][1:]) for j in range(copies_of_first)]
    points, translation, area, shape_of, edges = [], [], [], [], []
    vblocks, fblocks, shapes = [], [], []
    first = [0]
    for shape_id, cat, style, parts, local_edges in specs:
        whole = trimesh.util.concatenate([m for _, m in parts])
        lo, hi = whole.bounds
        centre = (lo + hi) / 2
        scale = 1.0 / np.linalg.norm(whole.vertices - centre, axis=1).max()
        base = first[-1]
        for _, mesh in parts:
            m = mesh.copy()
            m.apply_translation(-centre)
            m.apply_scale(scale)
            c = m.bounds.mean(axis=0)
            m.apply_translation(-c)
            pts, _ = trimesh.sample.sample_surface(m, cached_points, seed=int(rng.integers(2**31)))
            points.append(pts.astype(np.float16))
            translation.append(c.astype(np.float32))
            area.append(np.float32(m.area))
            shape_of.append(len(shapes))
            vblocks.append(m.vertices.astype(np.float32))
            fblocks.append(m.faces.astype(np.int32))
        edges += [(base + a, base + b) for a, b in local_edges]
        first.append(base + len(parts))
        shapes.append({"shape_id": shape_id, "category": cat, "style": style, "source": "toy",
                       "labels": [label for label, _ in parts]})
    vfirst = np.concatenate([[0], np.cumsum([len(v) for v in vblocks])]).astype(np.int64)
    ffirst = np.concatenate([[0], np.cumsum([len(f) for f in fblocks])]).astype(np.int64)
    info: dict[str, Any] = {"seed": seed, "source": "toy"}
    return ProcessedDataset(
        points=np.stack(points), translation=np.stack(translation), area=np.asarray(area, np.float32),
        shape_of=np.asarray(shape_of, np.int32), first_comp=np.asarray(first, np.int64),
        edges=np.asarray(edges, np.int32).reshape(-1, 2), mesh_vertices=np.concatenate(vblocks),
        mesh_faces=np.concatenate(fblocks), vertex_first=vfirst, face_first=ffirst, shapes=shapes, info=info)


@pytest.fixture(scope="session")
def toy_dataset() -> ProcessedDataset:
    return make_toy_dataset()


@pytest.fixture(scope="session")
def toy_dataset_dir(tmp_path_factory: pytest.TempPathFactory, toy_dataset: ProcessedDataset) -> Path:
    folder = tmp_path_factory.mktemp("toy_processed")
    toy_dataset.save(folder)
    return folder


@pytest.fixture(scope="session")
def tiny_run(tmp_path_factory: pytest.TempPathFactory, toy_dataset_dir: Path) -> Path:
    """A run folder trained for a few steps of the tiny preset (for export tests)."""
    from training.config import resolve_config
    from training.train import train

    run = tmp_path_factory.mktemp("tiny_run") / "run"
    cfg = resolve_config("tiny", overrides={"data": str(toy_dataset_dir), "run": str(run), "steps": 20,
                                            "log_every": 5, "val_triplets": 16})
    train(cfg, show_progress=False)
    return run


@pytest.fixture(scope="session")
def toy_dataset_factory():
    """``make_toy_dataset`` itself, for tests that need a dataset of their own."""
    return make_toy_dataset


@pytest.fixture(scope="session")
def generated_dataset_dir(tmp_path_factory: pytest.TempPathFactory) -> Path:
    """The real pipeline on a tiny scale: `data generate` (6 shapes per category) then `data preprocess`."""
    from training.data.generator.generate import generate_dataset
    from training.data.preprocess import PreprocessConfig, preprocess_folder

    root = tmp_path_factory.mktemp("generated")
    generate_dataset(root / "raw", seed=0, shapes_per_category=6, workers=1)
    preprocess_folder(root / "raw", root / "processed", PreprocessConfig(points_per_component=512), workers=1)
    return root / "processed"
