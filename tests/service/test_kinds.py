"""Kinds of parts (service.modeling.kinds) and the assembly's kind rule (``assemble_kind_share``).

The pure functions run on small made-up tables; the rule runs on the shipped model and catalog,
where labels are read only to check what the assembly built.
"""

from __future__ import annotations

import numpy as np
import pytest

from service.artifacts.catalog import Catalog, split_shapes
from service.modeling.assembly import AssembleOptions, Assembler, Start
from service.modeling.kinds import KindTable, kind_table, part_kinds, wanted_kinds
from service.settings import Settings
from service.suggest.engine import SuggestionEngine, SuggestOptions


def test_part_kinds_links_chains_not_gaps() -> None:
    """Parts within the distance of the next one are one kind, however long the chain; a gap
    wider than the distance separates kinds. 700 parts: more than one chunk of the distance matrix."""
    rng = np.random.default_rng(0)
    chain = np.zeros((600, 4))
    chain[:, 0] = np.arange(600) * 0.05            # links of 0.05: one kind 30 long
    other = rng.normal(size=(100, 4)) * 0.01 + 100.0
    kinds = part_kinds(np.concatenate([chain, other]), distance=0.06)
    assert len(set(kinds[:600].tolist())) == 1
    assert len(set(kinds[600:].tolist())) == 1
    assert kinds[0] != kinds[650]
    assert len(set(part_kinds(chain, distance=0.04).tolist())) == 600
    assert len(part_kinds(np.zeros((0, 4)), 0.1)) == 0


def _table(shapes: list[list[int]], kinds: int) -> KindTable:
    held = np.zeros((len(shapes), kinds), bool)
    for s, ks in enumerate(shapes):
        held[s, ks] = True
    return KindTable(np.zeros(0, np.int64), held)


# Kinds: 0 seat, 1 chair legs, 2 back, 3 stool legs. Three chairs, two stools.
CHAIRS_AND_STOOLS = _table([[0, 1, 2], [0, 1, 2], [0, 1, 2], [0, 3], [0, 3]], 4)


@pytest.mark.parametrize(("placed", "share", "wanted"), [
    ([0, 1], 0.5, [(2, 1.0)]),               # a chair's seat and legs: its nearest shapes have backs
    ([0, 3], 0.5, []),                       # a stool's: its nearest shapes are stools, complete
    ([0], 0.5, [(1, 0.6), (2, 0.6)]),        # a seat alone: every shape is as near
    ([0], 0.7, []),                          # ... and no kind is held by 70% of them
    ([0, 1, 1, 2], 0.5, []),                 # a kind placed is never wanted
    ([-1], 0.5, []),                         # a part of no kind says nothing
    ([0, 1, -1], 0.5, [(2, 1.0)]),           # ... and does not stop the others from speaking
])
def test_wanted_kinds(placed: list[int], share: float, wanted: list[tuple[int, float]]) -> None:
    got = wanted_kinds(CHAIRS_AND_STOOLS, np.array(placed), share)
    assert [k for k, _ in got] == [k for k, _ in wanted]
    assert np.allclose([s for _, s in got], [s for _, s in wanted])


def test_kind_table_on_the_catalog(catalog: Catalog, settings: Settings) -> None:
    """Every part of the category has a kind (the shipped catalog's test parts lie near training
    parts), no part of another category has one, and each training shape holds a kind per part
    at most."""
    table = kind_table(catalog, "chair", settings.assemble_kind_distance, settings.assemble_cover_shapes)
    code = catalog.category_codes(["chair"])[0]
    inside = catalog.category_of == code
    assert np.all(table.kind_of[~inside] == -1)
    assert np.mean(table.kind_of[inside] >= 0) > 0.99
    train = [rows for rows in split_shapes(catalog, "train").values() if catalog.category_of[rows[0]] == code]
    assert table.shape_kinds.shape == (len(train), int(table.kind_of.max()) + 1)
    held = table.shape_kinds.sum(axis=1)
    assert np.all(held >= 1) and np.all(held <= np.array([len(r) for r in sorted(train, key=min)]).max())


def test_among_parts_restricts_the_candidates(engine: SuggestionEngine, catalog: Catalog) -> None:
    """``among_parts`` keeps the answer to those parts, together with the other filters."""
    chair = [i for i in range(len(catalog)) if catalog.records[i]["category"] == "chair"]
    among = tuple(catalog.part_ids[i] for i in chair[:30])
    query = catalog.part_points(chair[0]) + catalog.translations[chair[0]]
    got = engine.suggest(query, SuggestOptions(k=50, among_parts=among))
    assert got.suggestions and {s.part_id for s in got.suggestions} <= set(among)
    shape = str(catalog.records[chair[0]]["shape_id"])
    got = engine.suggest(query, SuggestOptions(k=50, among_parts=among, exclude_shapes=(shape,)))
    assert got.suggestions and all(s.shape_id != shape for s in got.suggestions)


# Starts whose greedy chain, without the kind rule, ends as a backless seat with legs although
# the chairs nearest it in the data have backs (docs/modeling.md).
BACKLESS = ["chair-0083/0", "chair-0048/0"]


@pytest.mark.parametrize("start", BACKLESS)
def test_kind_rule_adds_what_the_nearest_shapes_hold(engine: SuggestionEngine, catalog: Catalog,
                                                      settings: Settings, start: str) -> None:
    row = catalog.lookup(start)
    options = AssembleOptions(exclude_shapes=(str(catalog.records[row]["shape_id"]),))
    off = Assembler(engine, settings.model_copy(update={"assemble_kind_candidates": 0})).assemble(
        Start(kind="part", part_index=row), options)
    asm = Assembler(engine, settings)
    on = asm.assemble(Start(kind="part", part_index=row), options)
    labels_off = [catalog.records[n.suggestion.part_index]["label"] for n in off.steps]
    labels_on = [catalog.records[n.suggestion.part_index]["label"] for n in on.steps]
    assert off.stop_reason == on.stop_reason == "complete"
    assert "back" not in labels_off and "back" in labels_on
    # The chain is the same up to the step the rule spoke at; that step's part is of a kind the
    # placed parts lacked and their nearest shapes mostly hold.
    j = len(off.steps)
    assert [n.suggestion.part_id for n in on.steps[:j]] == [n.suggestion.part_id for n in off.steps]
    table = asm.kind_table("chair")
    assert table is not None
    placed = [row, *(n.suggestion.part_index for n in off.steps)]
    wanted = {k for k, _ in wanted_kinds(table, table.kind_of[placed], settings.assemble_kind_share)}
    assert table.kind_of[on.steps[j].suggestion.part_index] in wanted
