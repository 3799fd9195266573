"""Generate shapes: one shape from (category, index, seed), or a whole dataset on disk.

Every shape draws from its own random generator seeded by (seed, category, index), so a shape
can be regenerated alone and the dataset does not depend on the number of worker processes.
"""

from __future__ import annotations

import logging
import multiprocessing
import zlib
from pathlib import Path

import numpy as np
from tqdm import tqdm

from training.data.generator.assembly import ShapeBuilder
from training.data.generator.catalog import CATEGORIES, Category
from training.data.shape_io import save_shape
from training.data.shapes import RawShape

log = logging.getLogger(__name__)

# A near-copy of one piece shows up in this fraction of shapes (messy duplicated geometry).
DUPLICATE_PROBABILITY = 0.3
DUPLICATE_OFFSET = 0.004


def shape_id(category: str, index: int) -> str:
    return f"{category}-{index:04d}"


def style_of(category: str, index: int) -> str:
    """Styles cycle with the index so every style gets the same share of a category."""
    styles = list(_category(category).styles)
    return styles[index % len(styles)]


def _category(name: str) -> Category:
    if name not in CATEGORIES:
        raise ValueError(f"unknown category {name!r}; known categories: {', '.join(CATEGORIES)}")
    return CATEGORIES[name]


def shape_rng(category: str, index: int, seed: int) -> np.random.Generator:
    """The generator of one shape: a stable function of (seed, category, index).

    ``zlib.crc32`` rather than ``hash()``: Python salts string hashes per process.
    """
    if index < 0 or seed < 0:
        raise ValueError(f"index and seed must be >= 0, got index={index}, seed={seed}")
    return np.random.default_rng([seed, zlib.crc32(category.encode()), index])


def generate_shape(category: str, index: int, seed: int) -> RawShape:
    """Build shape number ``index`` of ``category``: deterministic in (category, index, seed)."""
    cat = _category(category)
    style = style_of(category, index)
    rng = shape_rng(category, index, seed)
    builder = ShapeBuilder(rng)
    cat.styles[style](rng, builder)
    builder.duplicate_some(DUPLICATE_PROBABILITY, DUPLICATE_OFFSET)
    return builder.build(shape_id(category, index), category, style, source=f"generated:{seed}")


def _generate_and_save(task: tuple[str, int, int, str]) -> str:
    category, index, seed, out = task
    shape = generate_shape(category, index, seed)
    return str(save_shape(shape, Path(out) / category))


def generate_dataset(
    out: Path,
    seed: int = 0,
    shapes_per_category: int = 180,
    categories: list[str] | None = None,
    workers: int = 2,
) -> list[Path]:
    """Write ``<out>/<category>/<shape_id>.glb`` + ``.json`` for every requested shape.

    Args:
        out: output folder (created).
        seed: dataset seed; with the same seed, files are byte-identical.
        shapes_per_category: shapes per category, indices 0 .. n-1.
        categories: subset of category names (default: all, in registry order).
        workers: processes; 1 runs in this process. The output does not depend on it.

    Returns:
        Paths of the written GLB files, in (category, index) order.
    """
    names = list(CATEGORIES) if not categories else list(dict.fromkeys(categories))
    for name in names:
        _category(name)
    if shapes_per_category < 1:
        raise ValueError(f"shapes_per_category must be >= 1, got {shapes_per_category}")
    if workers < 1:
        raise ValueError(f"workers must be >= 1, got {workers}")
    tasks = [(c, i, seed, str(out)) for c in names for i in range(shapes_per_category)]
    Path(out).mkdir(parents=True, exist_ok=True)
    log.info(
        "generating %d shapes (%s) into %s with %d worker(s)", len(tasks), ", ".join(names), out, workers
    )
    bar = tqdm(total=len(tasks), desc="generate", unit="shape")
    paths: list[str] = []
    if workers == 1:
        for t in tasks:
            paths.append(_generate_and_save(t))
            bar.update()
    else:
        ctx = multiprocessing.get_context("spawn")
        with ctx.Pool(workers) as pool:
            for p in pool.imap(_generate_and_save, tasks, chunksize=8):
                paths.append(p)
                bar.update()
    bar.close()
    return [Path(p) for p in paths]
