"""The registry of generated categories: their styles (builders) and part-label vocabularies."""

from __future__ import annotations

from collections.abc import Callable
from dataclasses import dataclass
from types import ModuleType

import numpy as np

from training.data.generator import (
    airplanes,
    cars,
    chairs,
    guitars,
    lamps,
    rifles,
    sofas,
    tables,
    watercraft,
)
from training.data.generator.assembly import ShapeBuilder

StyleBuilder = Callable[[np.random.Generator, ShapeBuilder], None]


@dataclass(frozen=True)
class Category:
    """One category: label vocabulary (evaluation only) and its styles, in a fixed order."""

    name: str
    labels: tuple[str, ...]
    styles: dict[str, StyleBuilder]


def _category(name: str, module: ModuleType) -> Category:
    return Category(name=name, labels=tuple(module.LABELS), styles=dict(module.STYLES))


# Category name -> module; the order is the dataset's category order.
_MODULES: dict[str, ModuleType] = {
    "chair": chairs,
    "table": tables,
    "sofa": sofas,
    "lamp": lamps,
    "airplane": airplanes,
    "car": cars,
    "guitar": guitars,
    "watercraft": watercraft,
    "rifle": rifles,
}

CATEGORIES: dict[str, Category] = {name: _category(name, module) for name, module in _MODULES.items()}
