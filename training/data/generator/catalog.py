"""The registry of generated categories: their styles (builders) and part-label vocabularies."""

from __future__ import annotations

from collections.abc import Callable
from dataclasses import dataclass
from types import ModuleType

import numpy as np

from training.data.generator import chairs
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


CATEGORIES: dict[str, Category] = {c.name: c for c in (_category("chair", chairs),)}
