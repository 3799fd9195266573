"""The missing-spot rule's numeric core (service.modeling.templates) on synthetic shapes and on
the shipped catalog's own shapes, and what it does to automatic assembly (labels read in these
tests only, to measure)."""

from __future__ import annotations

from collections import Counter

import numpy as np
import pytest
from scipy.spatial import cKDTree

from service.artifacts.catalog import split_shapes
from service.modeling.assembly import AssembleOptions, Assembler, Start
from service.modeling.templates import ShapeTemplate, missing_spots, shape_templates
from service.settings import Settings
from service.suggest.engine import SuggestionEngine


def _cloud(lo: list[float], hi: list[float], seed: int, n: int = 64) -> np.ndarray:
    return np.random.default_rng(seed).uniform(np.array(lo), np.array(hi), size=(n, 3))


SEAT = ([-.4, -.02, -.4], [.4, .02, .4])
BACK = ([-.4, .05, .36], [.4, .8, .4])
LEGS = ([-.05, -.6, -.05], [.05, -.05, .05])   # one central post


def _template(name: str, boxes: list[tuple[list[float], list[float]]], seed: int) -> ShapeTemplate:
    clouds = [_cloud(lo, hi, seed + k) for k, (lo, hi) in enumerate(boxes)]
    points = np.concatenate(clouds)
    component = np.repeat(np.arange(len(clouds)), [len(c) for c in clouds])
    return ShapeTemplate(name, points, component, len(clouds), cKDTree(points))


def _spots(placed: np.ndarray, templates: list[ShapeTemplate], share: float = 0.5,
           neighbours: int = 6, n_parts: int = 2) -> list[tuple[np.ndarray, int]]:
    return missing_spots(placed, templates, neighbours=neighbours, cover_distance=0.05, uncovered_share=0.5,
                         share=share, radius=0.15, n_parts=n_parts)


def test_a_spot_most_nearest_shapes_fill_is_missing() -> None:
    """Four chairs of six have a back: a seat on legs lacks it; with the back placed, or when
    fewer shapes than the share have one, nothing is missing."""
    chairs = [_template(f"chair{k}", [SEAT, LEGS, BACK], 10 * k) for k in range(4)]
    stools = [_template(f"stool{k}", [SEAT, LEGS], 100 + 10 * k) for k in range(2)]
    templates = chairs + stools
    seat_on_legs = np.concatenate([_cloud(*SEAT, seed=7, n=2000), _cloud(*LEGS, seed=8, n=400)])
    spots = _spots(seat_on_legs, templates)
    assert len(spots) == 1
    centre, votes = spots[0]
    assert votes == 4
    assert np.linalg.norm(centre - (np.array(BACK[0]) + np.array(BACK[1])) / 2) < 0.05
    assert _spots(seat_on_legs, templates, share=0.8) == []                       # 4 of 6 < 0.8
    whole = np.concatenate([seat_on_legs, _cloud(*BACK, seed=9, n=2000)])
    assert _spots(whole, templates) == []


def test_shapes_with_no_more_parts_than_the_assembly_do_not_vote() -> None:
    """A seat on three legs of other styles: three parts, as many as a chair with a back has. The
    chairs' backs are then not missing parts but placed parts elsewhere (each chair's uncovered
    component is its back, yet the assembly is not short of a part), so no chair votes."""
    chairs = [_template(f"chair{k}", [SEAT, LEGS, BACK], 10 * k) for k in range(4)]
    seat_on_legs = np.concatenate([_cloud(*SEAT, seed=7, n=2000), _cloud(*LEGS, seed=8, n=400)])
    assert len(_spots(seat_on_legs, chairs, n_parts=2)) == 1
    assert _spots(seat_on_legs, chairs, n_parts=3) == []


def test_only_the_nearest_shapes_vote() -> None:
    """Shapes that do not hold the placed parts (a seat elsewhere) are not asked: their parts are
    not the assembly's missing ones."""
    chairs = [_template(f"chair{k}", [SEAT, LEGS, BACK], 10 * k) for k in range(3)]
    up = 1.5
    far = [_template(f"far{k}", [([-.4, -.02 + up, -.4], [.4, .02 + up, .4]), LEGS,
                                 ([-.4, .05 + up, .36], [.4, .8 + up, .4])], 50 + 10 * k)
           for k in range(6)]
    seat_on_legs = np.concatenate([_cloud(*SEAT, seed=7, n=2000), _cloud(*LEGS, seed=8, n=400)])
    spots = _spots(seat_on_legs, chairs + far, neighbours=3)
    assert len(spots) == 1 and spots[0][1] == 3
    # Asked, the far shapes' seats would be the missing spot instead.
    assert any(c[1] > 1.0 for c, _ in _spots(seat_on_legs, chairs + far, neighbours=9, share=0.6))


def test_no_templates_no_spots() -> None:
    placed = _cloud(*SEAT, seed=1)
    assert missing_spots(placed, [], 10, 0.05, 0.5, 0.5, 0.15) == []
    assert missing_spots(np.zeros((0, 3)), [_template("a", [SEAT, BACK], 0)], 10, 0.05, 0.5, 0.5, 0.15) == []
    assert missing_spots(placed, [_template("a", [SEAT, BACK], 0)], 0, 0.05, 0.5, 0.5, 0.15) == []


# ------------------------------------------------------------------ on the shipped catalog


def test_templates_are_the_categorys_training_shapes(shipped_engine: SuggestionEngine) -> None:
    cat = shipped_engine.catalog
    train = {sid for sid, rows in split_shapes(cat, "train").items()
             if cat.records[rows[0]]["category"] == "sofa"}
    templates = shape_templates(cat, "sofa", max_shapes=1000)
    assert {t.shape_id for t in templates} == train and len(train) > 50
    assert len(shape_templates(cat, "sofa", max_shapes=10)) == 10
    t = templates[0]
    assert t.points.shape == (len(t.component), 3) and set(t.component.tolist()) == set(range(t.n_components))


@pytest.mark.parametrize(("category", "label"), [("sofa", "seat"), ("lamp", "bulb"), ("car", "hood")])
def test_a_held_out_shape_without_a_part_is_missing_it(shipped_engine: SuggestionEngine,
                                                       shipped_settings: Settings, category: str,
                                                       label: str) -> None:
    """Held-out shapes with one part taken away: the data's nearest shapes say a part is missing
    where it was (within the spot radius) for most of them (all of 36 sofas, 36 lamps and 36
    cars when measured; a rifle's body, which its stock, barrel and magazine surround, only for
    a quarter: docs/modeling.md)."""
    s, cat = shipped_settings, shipped_engine.catalog
    templates = shape_templates(cat, category, s.assemble_cover_shapes)
    found = tried = 0
    for rows in split_shapes(cat, "test").values():
        if cat.records[rows[0]]["category"] != category or tried == 20:
            continue
        part = [i for i in rows if cat.records[i]["label"] == label]
        if len(part) != 1:
            continue
        tried += 1
        rest = np.concatenate([cat.part_points(i) + cat.translations[i] for i in rows if i != part[0]])
        where = (cat.bbox_min[part[0]] + cat.bbox_max[part[0]]) / 2 + cat.translations[part[0]]
        spots = missing_spots(rest, templates, s.assemble_gap_neighbours, s.assemble_cover_distance,
                              s.assemble_gap_uncovered, s.assemble_gap_share, s.assemble_gap_radius,
                              n_parts=len(rows) - 1)
        found += any(np.linalg.norm(c - where) < s.assemble_gap_radius for c, _ in spots)
    assert tried == 20
    assert found >= 16, f"{found} of {tried}"


def test_a_missing_spot_keeps_an_assembly_going(shipped_engine: SuggestionEngine,
                                                shipped_settings: Settings) -> None:
    """Held-out sofas, from each of their parts (docs/modeling.md: runs ended on cushions with no
    seat under them): with the rule on, more runs end with every label most sofas have than with
    it off (measured over all 36 held-out sofas: 168 of 187 runs against 146)."""
    cat = shipped_engine.catalog
    shapes = [rows for rows in split_shapes(cat, "test").values()
              if cat.records[rows[0]]["category"] == "sofa"]
    counts = Counter(label for rows in shapes for label in {cat.records[i]["label"] for i in rows})
    essential = {label for label, n in counts.items() if n > len(shapes) / 2}
    starts = [(row, str(cat.records[row]["shape_id"])) for rows in shapes[:12] for row in rows]

    def complete_runs(settings: Settings) -> tuple[int, int]:
        """Runs with every essential label, and parts the missing-spot rule added."""
        asm, done, spotted = Assembler(shipped_engine, settings), 0, 0
        for row, shape in starts:
            result = asm.assemble(Start(kind="part", part_index=row),
                                  AssembleOptions(exclude_shapes=(shape,), refine_contact=False))
            done += essential <= {cat.records[row]["label"], *(n.suggestion.label for n in result.steps)}
            spotted += sum(n.added_by == "missing_spot" for n in result.steps)
        return done, spotted

    (on, spotted), (off, none) = complete_runs(shipped_settings), complete_runs(
        shipped_settings.model_copy(update={"assemble_gap_neighbours": 0}))
    assert on > off, (on, off)
    assert spotted >= on - off and none == 0     # the answer says which parts the rule added
