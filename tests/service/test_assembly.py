"""Automatic assembly (service.modeling.assembly, POST /assemble): rules, trees, the API, and shape quality.

The quality test runs on the shipped, trained model in exported/ (whatever
COMPLEMENTME_TEST_ARTIFACTS says) and is skipped only when exported/ has no model: from random
start parts of every category, seeded greedy and sampled runs must give shapes that hold the
category's essential parts, and never two parts of one label within 0.05 of each other.
"""

from __future__ import annotations

import io
from collections import Counter
from pathlib import Path

import numpy as np
import pytest
import trimesh
from fastapi.testclient import TestClient
from service_testkit import make_settings

from service.artifacts.catalog import Catalog, split_shapes
from service.errors import InputError, ServiceError
from service.geometry.boxes import box_iou
from service.geometry.frames import Frame
from service.modeling.assembly import (
    ADD_REASONS,
    STOP_REASONS,
    AssembleOptions,
    Assembler,
    Node,
    Start,
    Strategy,
    _Candidate,
    _Placed,
    _State,
    estimate_area,
    open_modes,
    own_cover_shares,
)
from service.settings import Settings
from service.suggest.contact import Assembly as ContactAssembly
from service.suggest.contact import Surface, measure_contact
from service.suggest.engine import Suggestion, SuggestionEngine, SuggestResult

# What a complete shape of each category must hold (labels of training/data/generator).
ESSENTIAL = {
    "chair": {"seat", "back", "leg"}, "table": {"top", "leg"}, "airplane": {"body", "wing", "tail"},
    "car": {"body", "wheel"}, "sofa": {"seat", "back"}, "lamp": {"base", "shade"},
    "guitar": {"body", "neck"}, "watercraft": {"hull"}, "rifle": {"barrel", "stock", "body"},
}
SAME_LABEL_MIN_DISTANCE = 0.05
QUALITY_RUNS = 10          # per category: half greedy, half sampled
QUALITY_SHARE = 0.8


def _chain_ok(result: object, max_parts: int) -> None:
    steps = result.steps  # type: ignore[attr-defined]
    assert len(steps) <= max_parts
    for d, n in enumerate(steps, start=1):
        assert n.depth == d
        assert n.parent == (steps[d - 2].node if d > 1 else None)
    assert result.stop_reason in STOP_REASONS  # type: ignore[attr-defined]


def test_generator_labels_hold_the_essentials() -> None:
    from training.data.generator.catalog import CATEGORIES

    for cat, labels in ESSENTIAL.items():
        assert labels <= set(CATEGORIES[cat].labels), cat


# ------------------------------------------------------------------ rules on synthetic boxes


def _box(lo: list[float], hi: list[float], n: int = 200, seed: int = 0) -> _Placed:
    lo_, hi_ = np.array(lo, float), np.array(hi, float)
    pts = np.random.default_rng(seed).uniform(lo_, hi_, size=(n, 3))
    return _Placed(pts, Surface(pts), 1.0, lo_, hi_)


@pytest.mark.parametrize(("cand", "placed", "dup"), [
    # the same box again; nested inside (a hub in a tyre); a bit larger around (a tyre on a hub)
    (([-.2, -.2, -.2], [.2, .2, .2]), ([-.21, -.2, -.19], [.2, .21, .2]), True),
    (([-.1, -.1, -.02], [.1, .1, .02]), ([-.2, -.2, -.05], [.2, .2, .05]), True),
    (([-.22, -.22, -.05], [.22, .22, .05]), ([-.15, -.15, -.05], [.15, .15, .05]), True),
    # a longer rod on a shorter one (the same profile)
    (([-.03, -.8, -.03], [.03, .8, .03]), ([-.025, -.3, -.025], [.025, .3, .025]), True),
    # crossing boxes at one spot (one part per spot)
    (([-.6, -.05, -.4], [.6, .05, .4]), ([-.05, -.3, -.05], [.05, .3, .05]), True),
    # a hull around its deck (much larger, another profile); crossing boxes centred apart; apart
    (([-.8, -.3, -.5], [.8, .3, .5]), ([-.3, -.03, -.3], [.3, .03, .3]), False),
    (([-.6, -.05, -.4], [.6, .05, .4]), ([.0, -.3, .2], [.1, .3, .3]), False),
    (([.5, .5, .5], [.7, .7, .7]), ([-.2, -.2, -.2], [.2, .2, .2]), False),
])
def test_duplicate_rule(engine: SuggestionEngine, cand: tuple, placed: tuple, dup: bool,
                        settings: Settings) -> None:
    asm = Assembler(engine, settings)
    assert asm._duplicate(_box(cand[0], cand[1]), [_box(placed[0], placed[1], seed=1)]) is dup


def test_duplicate_rule_chamfer(engine: SuggestionEngine, settings: Settings) -> None:
    """Same samples moved by less than the Chamfer threshold: a duplicate even when centres differ."""
    s = settings
    a = _box([-.4, -.02, -.4], [.4, .02, .4], n=2000)
    shift = np.array([0.6 * s.assemble_duplicate_distance, 0.0, 0.0])
    moved = _Placed(a.points + shift, a.surface, 1.0, a.lo + shift, a.hi + shift)
    assert Assembler(engine, settings)._duplicate(moved, [a])


def test_redundant_part_on_placed_surface(engine: SuggestionEngine, settings: Settings) -> None:
    """A plate just above a placed plate (within the cover distance) adds no new surface."""
    s = settings
    seat = _box([-.4, -.02, -.4], [.4, .02, .4], n=2000)
    lift = s.assemble_cover_distance / 2
    above = _box([-.4, .02 + lift, -.3], [.4, .04 + lift, .5], n=2000, seed=2)
    asm = Assembler(engine, settings)
    assert not asm._duplicate(above, [seat])  # not the same spot...
    assert asm._redundant(above, _State([seat], frozenset()))      # ...but lying on placed surface
    far = _box([-.4, .5, -.4], [.4, .54, .4], n=2000, seed=3)
    assert not asm._redundant(far, _State([seat], frozenset()))


def test_same_job_rule(engine: SuggestionEngine, catalog: Catalog, settings: Settings) -> None:
    """The same catalog part a little beside itself does the job of the placed one (g cannot
    tell them apart); the same part far away, or a part g tells apart, does not."""
    asm = Assembler(engine, settings)
    # A mode's spread: a quarter of the embedding's (g's sigmas are 0.05-0.07 against 0.21).
    sigma = np.full(catalog.embeddings.shape[1], float(np.std(catalog.embeddings)) / 4)
    i = 0
    t = catalog.translations[i].astype(np.float64)
    size = float(np.linalg.norm(catalog.bbox_max[i] - catalog.bbox_min[i]))
    placed = _State([asm._catalog_part(i, t)], frozenset())
    emb = catalog.embeddings.astype(np.float64)   # each candidate at its mode's mean
    assert asm._same_job(asm._catalog_part(i, t + np.array([0.2 * size, 0, 0])), placed, emb[i], sigma)
    assert not asm._same_job(asm._catalog_part(i, t + np.array([3.0 * size, 0, 0])), placed, emb[i], sigma)
    z = np.sqrt(np.mean(((catalog.embeddings - catalog.embeddings[i]) / sigma) ** 2, axis=1))
    other = int(np.argmax(z))   # the part g finds least like part 0, at part 0's place
    assert z[other] > settings.assemble_same_job_sigmas
    assert not asm._same_job(asm._catalog_part(other, t), placed, emb[other], sigma)


def test_a_part_filling_a_placed_part_s_box_does_its_job_further_apart(engine: SuggestionEngine,
                                                                       catalog: Catalog,
                                                                       settings: Settings) -> None:
    """Another style of a part (embeddings between ``assemble_same_job_sigmas`` and
    ``assemble_strong_overlap_sigmas`` apart), fitted into a placed part's box, does its job (a
    second roof over the roof); moved so the boxes overlap less than
    ``assemble_strong_overlap_iou``, it does not."""
    s = settings
    asm = Assembler(engine, s)
    sigma = np.full(catalog.embeddings.shape[1], float(np.std(catalog.embeddings)) / 4)
    i = 0
    t = catalog.translations[i].astype(np.float64)
    z = np.sqrt(np.mean(((catalog.embeddings - catalog.embeddings[i]) / sigma) ** 2, axis=1))
    between = np.flatnonzero((z > s.assemble_same_job_sigmas + 0.2)
                             & (z < s.assemble_strong_overlap_sigmas - 0.2))
    assert len(between), "no part at that embedding distance"
    j = int(between[0])

    def extent(k: int) -> np.ndarray:
        return np.maximum(catalog.bbox_max[k] - catalog.bbox_min[k], 1e-3).astype(np.float64)

    fitted = extent(i) / extent(j)   # j scaled into i's box
    placed = _State([asm._catalog_part(i, t)], frozenset())
    emb = catalog.embeddings.astype(np.float64)
    assert asm._same_job(asm._catalog_part(j, t, fitted), placed, emb[j], sigma)
    axis = int(np.argmax(extent(i)))
    shift = np.zeros(3)
    shift[axis] = 0.4 * extent(i)[axis]    # IoU (1 - 0.4) / (1 + 0.4) = 0.43
    beside = asm._catalog_part(j, t + shift, fitted)
    iou = float(box_iou(beside.lo, beside.hi, placed.lo, placed.hi)[0])
    assert s.assemble_overlap_iou < iou < s.assemble_strong_overlap_iou
    assert not asm._same_job(beside, placed, emb[j], sigma)


def test_a_part_overlapping_a_part_its_mode_explains_does_its_job(engine: SuggestionEngine,
                                                                  catalog: Catalog,
                                                                  settings: Settings) -> None:
    """Another style of a part, its box shifted so it overlaps the placed part's by less than
    ``assemble_strong_overlap_iou``: it does the placed part's job when the placed part lies
    within ``assemble_overlap_mode_distance`` of the candidate's mode (the kind the mode
    proposes is there: a second roof shifted along the first), and not when the mode lies as
    far from the placed part as the candidate does."""
    s = settings
    asm = Assembler(engine, s)
    emb = catalog.embeddings.astype(np.float64)
    sigma = np.full(emb.shape[1], float(np.std(emb)) / 4)
    i = 0
    t = catalog.translations[i].astype(np.float64)
    z = np.sqrt(np.mean(((emb - emb[i]) / sigma) ** 2, axis=1))
    between = np.flatnonzero((z > s.assemble_same_job_sigmas + 0.2)
                             & (z < s.assemble_strong_overlap_sigmas - 0.2))
    assert len(between), "no part at that embedding distance"
    j = int(between[0])
    extent_i = np.maximum(catalog.bbox_max[i] - catalog.bbox_min[i], 1e-3).astype(np.float64)
    extent_j = np.maximum(catalog.bbox_max[j] - catalog.bbox_min[j], 1e-3).astype(np.float64)
    shift = np.zeros(3)
    shift[int(np.argmax(extent_i))] = 0.4 * float(np.max(extent_i))
    placed = _State([asm._catalog_part(i, t)], frozenset())
    beside = asm._catalog_part(j, t + shift, extent_i / extent_j)
    iou = float(box_iou(beside.lo, beside.hi, placed.lo, placed.hi)[0])
    assert s.assemble_overlap_iou < iou < s.assemble_strong_overlap_iou
    mode = emb[i] + 0.5 * s.assemble_overlap_mode_distance * sigma     # the placed part nearby
    assert asm._same_job(beside, placed, mode, sigma)
    assert not asm._same_job(beside, placed, emb[j], sigma)
    far = _State([asm._catalog_part(i, t + 3 * shift)], frozenset())   # boxes apart
    assert not asm._same_job(beside, far, mode, sigma)


def test_far_floating_part_is_pulled_into_contact(engine: SuggestionEngine, catalog: Catalog,
                                                  settings: Settings) -> None:
    """A part lifted past contact_max_offset (but within contact_reach) off the part it touches
    is brought back into contact by the second, longer search."""
    s = settings
    rows = np.flatnonzero(catalog.shape_of == catalog.shape_of[0])
    surfaces = {int(r): engine.contacts.part_surface(catalog, int(r)).moved(catalog.translations[r])
                for r in rows}
    far = (s.contact_max_offset + s.contact_reach) / 2

    def moved_away(a: int, b: int) -> np.ndarray:
        """Part b's translation moved straight away from part a by ``far``."""
        d = catalog.translations[b].astype(np.float64) - catalog.translations[a]
        return catalog.translations[b] + far * d / np.linalg.norm(d)

    def floats(a: int, b: int) -> bool:
        """b touches a at its place, and moved away it is out of the bounded search's reach."""
        assembly = ContactAssembly(surfaces[a])
        away = engine.contacts.part_surface(catalog, b).moved(moved_away(a, b))
        return (measure_contact(surfaces[b], assembly).touching(s.contact_tolerance)
                and measure_contact(away, assembly).gap > s.contact_max_offset + 2 * s.contact_tolerance)

    a, b = next((int(a), int(b)) for a in rows for b in rows if a != b and floats(int(a), int(b)))
    assembly = ContactAssembly(surfaces[a])
    t = moved_away(a, b)
    offset = engine.refine_against(assembly, np.array([b]), t[None])[0]
    assert np.linalg.norm(offset) > s.contact_max_offset
    after = measure_contact(engine.contacts.part_surface(catalog, b).moved(t + offset), assembly)
    assert after.gap <= s.contact_tolerance


def test_estimate_area() -> None:
    pts = np.random.default_rng(0).uniform([0, 0, 0], [1, 0, 2], size=(4000, 3))
    assert estimate_area(pts) == pytest.approx(2.0, rel=0.3)


# ------------------------------------------------------------------ the engine side


@pytest.fixture(scope="module")
def permissive(artifacts: Path) -> Settings:
    """The test settings with the likelihood rule off, so chains grow whatever the model's calibration."""
    return make_settings(artifacts, assemble_max_distance=1e9, assemble_min_mode_weight=0.0)


def test_unlikely_candidates_stop_the_chain(engine: SuggestionEngine, artifacts: Path) -> None:
    strict = make_settings(artifacts, assemble_max_distance=1e-9)
    result = Assembler(engine, strict).assemble(Start(kind="part", part_index=0),
                                                AssembleOptions(max_parts=3))
    assert result.steps == [] and result.stop_reason == "unlikely"


def test_chain_from_a_part(engine: SuggestionEngine, permissive: Settings, catalog: Catalog) -> None:
    start = Start(kind="part", part_index=0)
    result = Assembler(engine, permissive).assemble(start, AssembleOptions(max_parts=4))
    _chain_ok(result, 4)
    assert result.category == catalog.records[0]["category"]
    assert result.nodes == result.steps
    # A part the bounded search leaves floating gets a second search reaching contact_reach.
    bound = max(engine.config.contact_max_offset, engine.config.contact_reach)
    for n in result.steps:
        assert n.suggestion.category == result.category
        assert np.linalg.norm(n.contact_offset) <= bound + 1e-9
        np.testing.assert_allclose(n.translation, np.asarray(n.suggestion.translation) + n.contact_offset)
    np.testing.assert_allclose(result.start_translation, catalog.translations[0])
    # The same request gives the same assembly.
    again = Assembler(engine, permissive).assemble(start, AssembleOptions(max_parts=4))
    assert [n.suggestion.part_id for n in again.steps] == [n.suggestion.part_id for n in result.steps]
    # Without refinement, parts sit where h put them.
    raw = Assembler(engine, permissive).assemble(start, AssembleOptions(max_parts=4, refine_contact=False))
    assert all(not np.any(n.contact_offset) for n in raw.steps)


def test_sampling_is_seeded(engine: SuggestionEngine, permissive: Settings) -> None:
    start = Start(kind="part", part_index=0)
    runs = [[n.suggestion.part_id for n in Assembler(engine, permissive).assemble(
        start, AssembleOptions(max_parts=4, strategy="sample", seed=s)).steps] for s in (1, 1, 2)]
    assert runs[0] == runs[1]


def test_tree(engine: SuggestionEngine, permissive: Settings) -> None:
    settings = permissive
    result = Assembler(engine, permissive).assemble(Start(kind="part", part_index=0),
                                        AssembleOptions(max_parts=3, branching=2))
    assert 1 <= len(result.nodes) <= settings.assemble_max_nodes
    children = Counter(n.parent for n in result.nodes)
    assert max(children.values()) <= 2
    by_id = {n.node: n for n in result.nodes}
    for n in result.nodes:
        assert n.depth <= 3
        if n.parent is not None:
            assert by_id[n.parent].depth == n.depth - 1
    # Siblings are different parts that do not look alike at one place; no two branches reach
    # the same set of parts; the main chain takes the first child at every depth.
    for parent in children:
        kids = [n for n in result.nodes if n.parent == parent]
        assert len({n.suggestion.part_id for n in kids}) == len(kids)
    sets: list[frozenset[int]] = []
    for n in result.nodes:
        chain: list[int] = []
        at: Node | None = n
        while at is not None:
            chain.append(int(engine.catalog.group[at.suggestion.part_index]))
            at = by_id[at.parent] if at.parent is not None else None
        sets.append(frozenset(chain))
    assert len(set(sets)) == len(sets)
    _chain_ok(result, 3)
    assert result.steps[0] is next(n for n in result.nodes if n.parent is None)
    # Leaves say why they ended.
    leaves = [n for n in result.nodes if n.node not in children]
    assert leaves and all(n.stop_reason in STOP_REASONS for n in leaves)


def test_tree_node_budget(engine: SuggestionEngine, artifacts: Path) -> None:
    small = make_settings(artifacts, assemble_max_nodes=5)
    result = Assembler(engine, small).assemble(Start(kind="part", part_index=0),
                                        AssembleOptions(max_parts=6, branching=3))
    assert len(result.nodes) <= 5


def test_points_start_locks_the_first_category(engine: SuggestionEngine, permissive: Settings,
                                               catalog: Catalog) -> None:
    rows = np.flatnonzero(catalog.shape_of == catalog.shape_of[0])
    pts = np.concatenate([catalog.part_points(int(i)) + catalog.translations[i] for i in rows])
    result = Assembler(engine, permissive).assemble(Start(kind="points", points=pts),
                                                    AssembleOptions(max_parts=3))
    _chain_ok(result, 3)
    if result.steps:
        assert result.category == result.steps[0].suggestion.category
        assert {n.suggestion.category for n in result.steps} == {result.category}


@pytest.mark.parametrize(("options", "code"), [
    (AssembleOptions(max_parts=0), "max_parts_out_of_range"),
    (AssembleOptions(max_parts=10_000), "max_parts_out_of_range"),
    (AssembleOptions(branching=0), "branching_out_of_range"),
    (AssembleOptions(branching=1000), "branching_out_of_range"),
    (AssembleOptions(temperature=0.0), "bad_temperature"),
    (AssembleOptions(categories=("no-such-category",)), "unknown_category"),
])
def test_refusals(engine: SuggestionEngine, options: AssembleOptions, code: str, settings: Settings) -> None:
    with pytest.raises(ServiceError) as err:
        Assembler(engine, settings).assemble(Start(kind="part", part_index=0), options)
    assert err.value.code == code


def test_too_few_start_points(engine: SuggestionEngine, settings: Settings) -> None:
    with pytest.raises(InputError) as err:
        Assembler(engine, settings).assemble(Start(kind="points", points=np.zeros((3, 3), np.float32)))
    assert err.value.code == "too_few_points"


# ------------------------------------------------------------------ the API


def test_api_assemble(client: TestClient, catalog: Catalog) -> None:
    pid = catalog.part_ids[0]
    r = client.post("/assemble", json={"part_id": pid, "max_parts": 3})
    assert r.status_code == 200, r.text
    body = r.json()
    assert body["start"]["kind"] == "part" and body["start"]["part_id"] == pid
    np.testing.assert_allclose(body["start"]["translation"], catalog.translations[0], atol=1e-6)
    assert body["stop_reason"] in STOP_REASONS and body["category"] == catalog.records[0]["category"]
    assert body["stop_message"] == STOP_REASONS[body["stop_reason"]] and body["frame_fitted"] is False
    assert len(body["steps"]) <= 3 and body["nodes"] == body["steps"]
    for s in body["steps"]:
        i = catalog.lookup(s["part_id"])
        box_min = np.subtract(s["bbox_min"], s["translation"])
        np.testing.assert_allclose(box_min, catalog.bbox_min[i] * np.array(s["scale"]), atol=1e-5)
        assert s["links"]["mesh"].endswith("/mesh")
        assert s["added_message"] == ADD_REASONS[s["added_by"]]
    # A z-up, scaled frame answers the same parts at mapped translations.
    framed = client.post("/assemble", json={"part_id": pid, "max_parts": 3, "frame": {
        "center": [1, 2, 3], "radius": 2.0, "up_axis": "z"}}).json()
    turn = np.array([[1.0, 0, 0], [0, 0, 1.0], [0, -1.0, 0]])
    for a, b in zip(body["steps"], framed["steps"], strict=True):
        assert a["part_id"] == b["part_id"]
        back = (np.array(b["translation"]) - [1, 2, 3]) / 2.0 @ turn.T
        np.testing.assert_allclose(back, a["translation"], atol=1e-5)


def test_the_answer_names_every_rule_that_adds_a_part() -> None:
    """The API's `added_by` values are the assembly's `ADD_REASONS`, no more, no fewer."""
    from typing import get_args

    from service.api.schemas_modeling import StepOut

    assert set(get_args(StepOut.model_fields["added_by"].annotation)) == set(ADD_REASONS)


def test_api_assemble_from_parts_continues(client: TestClient, catalog: Catalog) -> None:
    first = client.post("/assemble", json={"part_id": catalog.part_ids[0], "max_parts": 2}).json()
    parts = [{"part_id": catalog.part_ids[0], "translation": first["start"]["translation"]}]
    parts += [{"part_id": s["part_id"], "translation": s["translation"]} for s in first["steps"]]
    r = client.post("/assemble", json={"parts": parts, "max_parts": 2})
    assert r.status_code == 200, r.text
    body = r.json()
    assert body["start"]["kind"] == "parts" and body["start"]["parts"] == len(parts)
    assert body["category"] == catalog.records[0]["category"]


def test_api_assemble_tree(client: TestClient, catalog: Catalog) -> None:
    r = client.post("/assemble", json={"part_id": catalog.part_ids[0], "max_parts": 2, "branching": 2,
                                       "strategy": "sample", "seed": 5})
    assert r.status_code == 200, r.text
    body = r.json()
    ids = {n["node"] for n in body["nodes"]}
    assert all(n["parent"] is None or n["parent"] in ids for n in body["nodes"])
    assert {s["node"] for s in body["steps"]} <= ids


def test_api_assemble_mesh(client: TestClient) -> None:
    box = trimesh.creation.box((0.8, 0.06, 0.8))
    data = box.export(file_type="obj").encode()
    r = client.post("/assemble/mesh", files={"file": ("seat.obj", io.BytesIO(data), "text/plain")},
                    data={"options": '{"max_parts": 2}'})
    assert r.status_code == 200, r.text
    assert r.json()["start"]["kind"] == "mesh"
    bad = client.post("/assemble/mesh", files={"file": ("seat.obj", io.BytesIO(data), "text/plain")},
                      data={"options": '{"max_parts": "many"}'})
    assert bad.status_code == 422 and bad.json()["error"]["code"] == "validation_error"
    assert bad.json()["error"]["details"][0]["loc"][:3] == ["body", "options", "max_parts"]


@pytest.mark.parametrize(("body", "status", "code"), [
    ({}, 422, "validation_error"),
    ({"part_id": "P", "points": [[0, 0, 0]] * 20}, 422, "validation_error"),
    ({"part_id": "no-such/0"}, 404, "unknown_part"),
    ({"parts": [{"part_id": "no-such/0", "translation": [0, 0, 0]}]}, 404, "unknown_part"),
    ({"part_id": "P", "max_parts": 0}, 422, "max_parts_out_of_range"),
    ({"part_id": "P", "branching": 99}, 422, "branching_out_of_range"),
    ({"part_id": "P", "branching": 0}, 422, "validation_error"),
    ({"part_id": "P", "category": "no-such-category"}, 422, "unknown_category"),
    ({"part_id": "P", "style": "no-such-style"}, 422, "unknown_style"),
    ({"part_id": "P", "temperature": 0}, 422, "validation_error"),
    ({"part_id": "P", "strategy": "best"}, 422, "validation_error"),
    ({"part_id": "P", "exclude_modes": [999]}, 422, "unknown_mode"),
    ({"points": [[0, 0, 0]] * 3}, 422, "too_few_points"),
])
def test_api_assemble_errors(client: TestClient, catalog: Catalog, body: dict, status: int,
                             code: str) -> None:
    if body.get("part_id") == "P":
        body["part_id"] = catalog.part_ids[0]
    r = client.post("/assemble", json=body)
    assert r.status_code == status, r.text
    assert r.json()["error"]["code"] == code


# ------------------------------------------------------------------ quality on the trained model


QualityRuns = tuple[dict[str, float], list[tuple[str, str, Strategy, str]]]


@pytest.fixture(scope="module")
def quality_runs(shipped_engine: SuggestionEngine, shipped_settings: Settings) -> QualityRuns:
    """Random start parts of each category, greedy and sampled, seeded: the share of runs per
    category with every essential part, and the pairs of same-label parts placed within 0.05."""
    engine, cat = shipped_engine, shipped_engine.catalog
    rng = np.random.default_rng(0)
    asm = Assembler(engine, shipped_settings)
    complete: dict[str, list[bool]] = {}
    close_pairs = []
    for c in sorted(ESSENTIAL):
        if c not in cat.categories:
            continue
        rows = np.flatnonzero(cat.category_of == cat.categories.index(c))
        for run in range(QUALITY_RUNS):
            i = int(rng.choice(rows))
            strategy: Strategy = "greedy" if run % 2 == 0 else "sample"
            options = AssembleOptions(strategy=strategy, seed=run)
            result = asm.assemble(Start(kind="part", part_index=i), options)
            labels = [cat.records[i]["label"], *(n.suggestion.label for n in result.steps)]
            places = [cat.translations[i].astype(np.float64), *(n.translation for n in result.steps)]
            complete.setdefault(c, []).append(ESSENTIAL[c] <= set(labels))
            for a in range(len(labels)):
                for b in range(a):
                    near = np.linalg.norm(places[a] - places[b]) < SAME_LABEL_MIN_DISTANCE
                    if labels[a] == labels[b] and near:
                        close_pairs.append((c, cat.part_ids[i], strategy, labels[a]))
    assert complete, "no category of the generated dataset in the catalog"
    return {c: float(np.mean(v)) for c, v in complete.items()}, close_pairs


@pytest.mark.parametrize("category", sorted(ESSENTIAL))
def test_automatic_assembly_completes_shapes(quality_runs: QualityRuns, category: str) -> None:
    """Essential parts present in at least 80% of the runs of every category."""
    shares = quality_runs[0]
    assert shares[category] >= QUALITY_SHARE, str(sorted(shares.items()))


def test_automatic_assembly_never_stacks_one_kind_of_part(quality_runs: QualityRuns) -> None:
    """Never two parts of one label within 0.05 of each other."""
    assert not quality_runs[1], quality_runs[1]


def test_the_cover_rule_follows_each_categorys_own_parts(shipped_engine: SuggestionEngine,
                                                         shipped_settings: Settings) -> None:
    """Rifle magazines and bodies lie half on other parts of their own shapes, chair parts do not:
    the share that makes a candidate redundant is what 90% of the category's training parts stay
    below, never less than ``assemble_cover_share``."""
    s, cat = shipped_settings, shipped_engine.catalog
    asm = Assembler(shipped_engine, s)
    rifle = own_cover_shares(cat, "rifle", s.assemble_cover_distance, s.assemble_cover_shapes)
    chair = own_cover_shares(cat, "chair", s.assemble_cover_distance, s.assemble_cover_shapes)
    few = own_cover_shares(cat, "rifle", s.assemble_cover_distance, 10)
    assert 10 <= len(few) <= 10 * 8 < len(rifle)  # a draw of 10 shapes (2-8 parts each)
    assert len(rifle) > 100 and len(chair) > 100
    assert asm.cover_share("rifle") == pytest.approx(max(s.assemble_cover_share, np.quantile(rifle, 0.9)))
    assert asm.cover_share("rifle") > s.assemble_cover_share + 0.2 > asm.cover_share("chair") > 0
    assert np.mean(rifle < asm.cover_share("rifle")) >= 0.89  # real rifle parts pass the rule
    off = Assembler(shipped_engine, s.model_copy(update={"assemble_cover_quantile": 0.0}))
    assert off.cover_share("rifle") == s.assemble_cover_share


def test_a_complete_object_ends_without_asking_for_more_candidates(shipped_engine: SuggestionEngine,
                                                                   shipped_settings: Settings,
                                                                   monkeypatch: pytest.MonkeyPatch) -> None:
    """Once g's most likely candidate is no more likely than a placed part, the chain ends
    "complete" on that step's one engine call, rather than asking round after round for less
    likely candidates that do placed parts' jobs (a guitar's body, neck and head)."""
    engine, cat = shipped_engine, shipped_engine.catalog
    asm = Assembler(engine, shipped_settings)
    calls: list[int] = []
    suggest = engine.suggest

    def counted(*args: object, **kwargs: object) -> object:
        calls.append(1)
        return suggest(*args, **kwargs)  # type: ignore[arg-type]

    monkeypatch.setattr(engine, "suggest", counted)
    guitars = np.flatnonzero(cat.category_of == cat.categories.index("guitar"))
    ended = 0
    for i in guitars[:: max(1, len(guitars) // 6)][:6]:
        calls.clear()
        result = asm.assemble(Start(kind="part", part_index=int(i)), AssembleOptions())
        if result.stop_reason == "complete":
            ended += 1
            # One call per added part, one for the step that found the object complete, and at
            # most one extra round for steps whose first candidates all did placed parts' jobs.
            assert len(calls) <= 2 * len(result.steps) + 1, (len(calls), len(result.steps))
    assert ended >= 4, f"{ended} of 6 guitar runs ended complete"


def test_open_modes_are_the_heavy_modes_no_placed_part_explains() -> None:
    means = np.array([[0.0, 0.0], [1.0, 0.0], [0.0, 1.0], [5.0, 5.0]])
    sigmas = np.full((4, 2), 0.1)
    weights = np.array([0.15, 0.5, 0.3, 0.05])
    near_first = np.array([[0.05, 0.0]])           # 0.35 RMS sigmas from mode 0's mean
    assert open_modes(near_first, weights, means, sigmas, 0.1, 1.0) == [1, 2]    # heaviest first
    assert open_modes(near_first, weights, means, sigmas, 0.4, 1.0) == [1]       # light modes never
    assert open_modes(np.zeros((0, 2)), weights, means, sigmas, 0.1, 1.0) == [1, 2, 0]
    off_second = np.array([[1.3, 0.3]])            # 3 RMS sigmas from mode 1's mean
    assert 1 in open_modes(off_second, weights, means, sigmas, 0.1, 2.9)
    assert 1 not in open_modes(off_second, weights, means, sigmas, 0.1, 3.1)
    assert open_modes(near_first, weights, means, sigmas, 0.6, 1.0) == []


def _own_place_candidate(catalog: Catalog, row: int, mode: int) -> _Candidate:
    """A candidate placed where the part sits in its own shape, attributed to ``mode``."""
    t = catalog.translations[row].astype(np.float64)
    sug = Suggestion(rank=1, part_index=row, part_id=catalog.part_ids[row], shape_id="s", category="c",
                     label=None, score=0.0, rank_score=0.0, mode=mode, mode_weight=0.5, duplicates=1,
                     translation=t, bbox_min=t + catalog.bbox_min[row], bbox_max=t + catalog.bbox_max[row])
    return _Candidate(sug, 0.0, None, mode)


def test_open_modes_give_a_tree_one_child_each(engine: SuggestionEngine, catalog: Catalog,
                                               settings: Settings) -> None:
    """A state that would end complete while two heavy modes are unmet: a chain takes the
    heaviest mode's part, a tree (n = 2) one part of each mode, candidates tested once."""
    shape = max(split_shapes(catalog, "train").values(), key=len)
    placed, *others = [int(r) for r in shape]
    # Two parts of the same shape that neither lie on the placed one nor do its job.
    asm = Assembler(engine, settings)
    state = _State([asm._catalog_part(placed, catalog.translations[placed].astype(np.float64))], frozenset())
    free = [r for r in others if not asm._redundant(
        asm._catalog_part(r, catalog.translations[r].astype(np.float64)), state)][:2]
    assert len(free) == 2
    emb = catalog.embeddings
    result = SuggestResult(suggestions=[], mode_weights=np.array([0.6, 0.4], np.float32), frame=Frame(),
                           n_input_points=0, candidates=2, mode_means=emb[free].astype(np.float32),
                           mode_sigmas=np.full((2, emb.shape[1]), 0.01, np.float32))
    weights = result.mode_weights.astype(np.float64)

    def candidates() -> list[_Candidate]:
        return [_own_place_candidate(catalog, r, m) for m, r in enumerate(free)]

    one, why = asm._open_mode_picks(result, weights, state, candidates(), 0.0)
    assert why == "" and [c.suggestion.part_index for c in one] == [free[0]]     # the heavier mode
    likely = candidates()
    two, why = asm._open_mode_picks(result, weights, state, likely, 0.0, n=2)
    assert why == "" and [c.suggestion.part_index for c in two] == free
    assert all(c.redundant is False for c in likely)                             # tested, kept
    # Below the margin of the most likely placed part: none, complete.
    none, why = asm._open_mode_picks(result, weights, state, candidates(),
                                     settings.assemble_open_mode_margin + 1.0, n=2)
    assert none == [] and why == "complete"


def test_an_unmet_mode_keeps_a_rifle_going(shipped_engine: SuggestionEngine,
                                           shipped_settings: Settings) -> None:
    """A rifle's heaviest mode offers bipods and scopes after the first ones are placed and the
    chain used to end "complete" without the magazine or the body (docs/modeling.md); with the
    open-mode rule on, held-out rifle starts end with every essential part more often than off
    (labels read here only, to measure)."""
    cat = shipped_engine.catalog
    rifles = [rows for rows in split_shapes(cat, "test").values()
              if cat.records[rows[0]]["category"] == "rifle"]
    # "Complete" as the assembly evaluation has it: every label more than half the rifles have.
    counts = Counter(label for rows in rifles for label in {cat.records[i]["label"] for i in rows})
    essential = {label for label, n in counts.items() if n > len(rifles) / 2}
    shapes = rifles[:12]
    assert len(shapes) >= 8 and {"body", "magazine"} <= essential

    def complete_runs(settings: Settings) -> tuple[int, int]:
        """Runs with every essential label, and parts an unmet mode added."""
        asm, done, unmet = Assembler(shipped_engine, settings), 0, 0
        for rows in shapes:
            shape = str(cat.records[rows[0]]["shape_id"])
            result = asm.assemble(Start(kind="part", part_index=rows[0]),
                                  AssembleOptions(exclude_shapes=(shape,), refine_contact=False))
            labels = {cat.records[rows[0]]["label"], *(n.suggestion.label for n in result.steps)}
            done += essential <= labels
            unmet += sum(n.added_by == "unmet_mode" for n in result.steps)
        return done, unmet

    (on, unmet), (off, none) = complete_runs(shipped_settings), complete_runs(
        shipped_settings.model_copy(update={"assemble_open_mode_weight": 0.0}))
    assert on > off, (on, off)
    assert unmet >= 1 and none == 0             # the answer says which parts the rule added


def test_an_unmet_mode_adds_no_part_far_less_likely_than_the_placed_ones(
        shipped_engine: SuggestionEngine, shipped_settings: Settings) -> None:
    """The page's auto-complete from a lone seat (docs/modeling.md): without the likelihood floor
    an unmet seat mode added a thick seat block under the finished chair's seat; with it the
    chain holds one seat and ends complete (labels read here only, to measure)."""
    cat = shipped_engine.catalog
    start = Start(kind="part", part_index=cat.lookup("chair-0000/1"))

    def seats(settings: Settings) -> int:
        result = Assembler(shipped_engine, settings).assemble(start, AssembleOptions(max_parts=6))
        return sum(n.suggestion.label == "seat" for n in result.steps)

    assert seats(shipped_settings) == 0
    assert seats(shipped_settings.model_copy(update={"assemble_open_mode_margin": 1e9})) >= 1


def test_a_catalog_write_keeps_what_the_assembly_read_of_the_data(shipped_engine: SuggestionEngine,
                                                                   shipped_settings: Settings) -> None:
    """Writes add parts of split "added" only, so a later snapshot's cover share and templates are
    the shipped snapshot's: kept once, not made again by the first ``/assemble`` after each write.
    An added chair shape of two parts is not among the templates a fresh build of them reads."""
    from service.catalog_store.snapshot import AddedPart, CatalogBuilder, combined_index
    from service.catalog_store.store import PartGeometry
    from service.modeling.templates import shape_templates

    s, cat = shipped_settings, shipped_engine.catalog
    rows = next(r for r in split_shapes(cat, "train").values()
                if cat.records[r[0]]["category"] == "chair")[:2]
    added = []
    for j, i in enumerate(rows):
        vertices, faces = cat.mesh(i)
        rec = dict(cat.records[i], part_id=f"added-{j}", shape_id="added-chair", split="added",
                   origin="added", duplicate_of=None)
        added.append(AddedPart(j, rec, cat.embeddings[i], cat.part_features[i],
                               PartGeometry(vertices, faces, cat.points[i])))
    builder = CatalogBuilder(cat)
    builder.append(added)
    grown = builder.catalog()
    snapshot = shipped_engine.snapshot(grown, combined_index(shipped_engine.index, grown, len(cat)))
    before, after = Assembler(shipped_engine, s), Assembler(shipped_engine, s, snapshot)
    assert after.templates("chair") is before.templates("chair")
    assert after.cover_share("chair") == before.cover_share("chair")
    fresh = shape_templates(grown, "chair", s.assemble_cover_shapes, s.seed)
    assert [t.shape_id for t in fresh] == [t.shape_id for t in before.templates("chair")]
    assert own_cover_shares(grown, "chair", s.assemble_cover_distance, s.assemble_cover_shapes,
                            s.seed).tolist() == own_cover_shares(cat, "chair", s.assemble_cover_distance,
                                                                 s.assemble_cover_shapes, s.seed).tolist()


def test_the_warm_up_walks_the_catalog_records_once_for_every_category(
        shipped_settings: Settings, monkeypatch: pytest.MonkeyPatch) -> None:
    """Every category's cover share and templates read the training shapes of one walk over the
    records (the same walk says whether the catalog has a training split), not a walk each: at
    ten million parts a walk takes seconds. What they read is what a walk of their own gives."""
    import service.artifacts.catalog as catalog_module
    import service.modeling.assembly as assembly_module
    from service.artifacts.loading import load_artifacts
    from service.modeling.templates import shape_templates

    s = shipped_settings
    engine = SuggestionEngine(load_artifacts(s.artifacts), s)  # its own snapshot: nothing cached yet
    cat = engine.catalog
    alone = {c: [t.shape_id for t in shape_templates(cat, c, s.assemble_cover_shapes, s.seed)]
             for c in cat.categories}
    shares = own_cover_shares(cat, "rifle", s.assemble_cover_distance, s.assemble_cover_shapes, s.seed)
    walks: list[str] = []

    def counted(catalog: Catalog, split: str, fallback: bool = True) -> dict[str, list[int]]:
        walks.append(split)
        return split_shapes(catalog, split, fallback)

    monkeypatch.setattr(catalog_module, "split_shapes", counted)
    monkeypatch.setattr(assembly_module, "split_shapes", counted)
    assembler = Assembler(engine, s)
    assembler.warm()
    assert walks == ["train"]
    assert {c: [t.shape_id for t in assembler.templates(c)] for c in cat.categories} == alone
    assert own_cover_shares(cat, "rifle", s.assemble_cover_distance, s.assemble_cover_shapes, s.seed,
                            assembler.training_shapes()).tolist() == shares.tolist()
    assert assembler.cover_share("rifle") == max(s.assemble_cover_share,
                                                 float(np.quantile(shares, s.assemble_cover_quantile)))
    assert walks == ["train"]


def test_a_catalog_without_a_training_split_reads_every_multi_part_shape(shipped_settings: Settings) -> None:
    """A catalog with no training split (here every record marked "test") has no training shapes
    to keep under the shipped snapshot: the assembly reads every multi-part shape of its own
    snapshot, as a walk with the fallback gives them."""
    import dataclasses

    from service.artifacts.loading import load_artifacts
    from service.modeling.templates import shape_templates

    s = shipped_settings
    artifacts = load_artifacts(s.artifacts)
    records = [{**rec, "split": "test"} for rec in artifacts.catalog.records]
    artifacts.catalog = dataclasses.replace(artifacts.catalog, records=records)
    engine = SuggestionEngine(artifacts, s)
    cat = engine.catalog
    assert split_shapes(cat, "train", fallback=False) == {}
    assembler = Assembler(engine, s)
    assert assembler.training_shapes() == split_shapes(cat, "train")
    assert len(assembler.training_shapes()) > len(split_shapes(load_artifacts(s.artifacts).catalog, "train"))
    assert ([t.shape_id for t in assembler.templates("chair")]
            == [t.shape_id for t in shape_templates(cat, "chair", s.assemble_cover_shapes, s.seed)])


def test_the_warm_up_makes_what_assembly_reads_of_every_category(artifacts: Path,
                                                                 monkeypatch: pytest.MonkeyPatch) -> None:
    """After start, no ``/assemble`` reads the training shapes again: the warm-up made every
    category's cover share and templates (a first auto-complete costs what the next one does)."""
    import service.modeling.assembly as assembly_module
    from service.api.app import create_app

    with TestClient(create_app(make_settings(artifacts, verify_checksums=False))) as c:
        def refuse(*args: object, **kwargs: object) -> None:
            raise AssertionError("read the training shapes after start")
        monkeypatch.setattr(assembly_module, "own_cover_shares", refuse)
        monkeypatch.setattr(assembly_module, "shape_templates", refuse)
        catalog = c.app.state.served.engine.catalog  # type: ignore[attr-defined]
        for category in catalog.categories:
            start = next(r["part_id"] for r in catalog.records if r["category"] == category)
            r = c.post("/assemble", json={"part_id": start, "max_parts": 2})
            assert r.status_code == 200, r.text
