"""Procedural, part-structured 3D shapes: the built-in dataset of ``complementme data generate``.

Nine categories (the ComplementMe paper's: chair, table, sofa, lamp, airplane, car, guitar,
watercraft and rifle) with several fine-grained styles each; every piece carries a semantic part
label (ShapeNet part benchmark names where the category has them). Styles and labels are for
evaluation only: training never reads them. Shapes are seeded and deterministic, y up, front
towards +x, centred at their bounding-box centre and scaled to unit radius.
"""

from training.data.generator.catalog import CATEGORIES, Category
from training.data.generator.generate import generate_dataset, generate_shape, shape_id, style_of

__all__ = ["CATEGORIES", "Category", "generate_dataset", "generate_shape", "shape_id", "style_of"]
