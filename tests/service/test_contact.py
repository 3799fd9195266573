"""Contact refinement: synthetic contacts with known answers, then the engine and the API on artifacts."""

from __future__ import annotations

import json
from pathlib import Path

import contact_reference
import numpy as np
import pytest
import trimesh
from fastapi.testclient import TestClient
from scipy.spatial import cKDTree
from service_testkit import AssemblyQuery, assembly_query, multi_part_shapes

from service.artifacts.catalog import Catalog
from service.geometry.frames import Frame
from service.settings import Settings
from service.suggest import contact_kernel
from service.suggest.contact import (
    Assembly,
    ContactParams,
    Refinement,
    Surface,
    SurfaceCache,
    measure_contact,
    refine_offset,
    refine_offsets,
    sample_oriented,
)
from service.suggest.engine import SuggestionEngine, SuggestOptions
from training.evaluate.contact import Mesh, contact

REPO = Path(__file__).resolve().parents[2]
SEAT_TOP = 0.03  # the seat box spans y in [-0.03, 0.03]
LEG_HALF = 0.4   # the leg cylinder spans y in [-0.4, 0.4] around its centre


def _seat() -> trimesh.Trimesh:
    return trimesh.creation.box((0.8, 2 * SEAT_TOP, 0.8))


def _leg() -> trimesh.Trimesh:
    leg = trimesh.creation.cylinder(0.03, 2 * LEG_HALF, sections=24)
    leg.apply_transform(trimesh.transformations.rotation_matrix(np.pi / 2, (1, 0, 0)))
    return leg


@pytest.fixture(scope="module")
def seat() -> Assembly:
    m = _seat()
    return Assembly(sample_oriented(m.vertices, m.faces, 4096, 0))


@pytest.fixture(scope="module")
def leg() -> Surface:
    m = _leg()
    return sample_oriented(m.vertices, m.faces, 1024, 1)


def _exact(part_mesh: trimesh.Trimesh, t: np.ndarray, asm_mesh: trimesh.Trimesh) -> tuple[float, float]:
    """The benchmark's exact gap and depth (winding numbers and point-triangle distances)."""
    def mesh(m: trimesh.Trimesh, offset: np.ndarray) -> Mesh:
        pts = sample_oriented(m.vertices, m.faces, 512, 3).points
        return Mesh(m.vertices + offset, m.faces.astype(np.int64), pts + offset)
    c = contact(mesh(part_mesh, t), [mesh(asm_mesh, np.zeros(3))])
    return c.gap, c.depth


def test_sample_oriented_normals_point_outwards() -> None:
    box = trimesh.creation.box((1.0, 2.0, 3.0))
    s = sample_oriented(box.vertices, box.faces, 500, 0)
    assert s.points.shape == (500, 3) and s.normals is not None and s.normals.shape == (500, 3)
    np.testing.assert_allclose(np.linalg.norm(s.normals, axis=1), 1.0, atol=1e-9)
    # On a centred box, the outward normal points away from the centre on every face.
    assert np.all(np.einsum("ij,ij->i", s.points, s.normals) > 0)
    again = sample_oriented(box.vertices, box.faces, 500, 0)
    np.testing.assert_array_equal(s.points, again.points)
    with pytest.raises(ValueError, match="positive area"):
        sample_oriented(box.vertices, np.zeros((0, 3), np.int64), 10, 0)


@pytest.mark.parametrize("height", [0.05, 0.02, -0.03, -0.06])
def test_leg_under_seat_is_brought_into_contact(seat: Assembly, leg: Surface, height: float) -> None:
    """A leg below the seat (gap) or pushed into it (penetration) ends touching its underside."""
    touching = np.array([0.3, -SEAT_TOP - LEG_HALF, 0.3])
    t = touching + np.array([0.0, -height, 0.0])  # height > 0: below the seat; < 0: pushed into it
    params = ContactParams(max_offset=0.1, tolerance=0.01)
    r = refine_offset(leg.moved(t), seat, params)
    assert r.resolved
    assert not r.before.touching(params.tolerance)
    assert r.after.touching(params.tolerance)
    assert np.linalg.norm(r.offset) <= params.max_offset + 1e-9
    # The benchmark's exact measure agrees: neither floating nor interpenetrating past 0.02.
    gap, depth = _exact(_leg(), t + r.offset, _seat())
    assert gap <= 0.02 and depth <= 0.02, (gap, depth)
    before_gap, before_depth = _exact(_leg(), t, _seat())
    assert before_gap > 0.02 or before_depth > 0.02


def test_touching_part_is_left_alone(seat: Assembly, leg: Surface) -> None:
    t = np.array([0.3, -SEAT_TOP - LEG_HALF - 0.003, 0.3])
    r = refine_offset(leg.moved(t), seat, ContactParams())
    assert r.resolved and np.all(r.offset == 0)


def test_too_far_keeps_the_translation(seat: Assembly, leg: Surface) -> None:
    """A gap larger than the bound cannot be closed: no half-way move, the translation is kept."""
    t = np.array([0.3, -SEAT_TOP - LEG_HALF - 0.25, 0.3])
    r = refine_offset(leg.moved(t), seat, ContactParams(max_offset=0.1))
    assert not r.resolved and np.all(r.offset == 0)
    # Within a larger bound the same gap closes.
    r2 = refine_offset(leg.moved(t), seat, ContactParams(max_offset=0.3))
    assert r2.resolved and 0.2 < np.linalg.norm(r2.offset) <= 0.3


def test_zero_bound_never_moves(seat: Assembly, leg: Surface) -> None:
    t = np.array([0.3, -SEAT_TOP - LEG_HALF - 0.05, 0.3])
    r = refine_offset(leg.moved(t), seat, ContactParams(max_offset=0.0))
    assert np.all(r.offset == 0) and not r.resolved


def test_points_only_assembly_sees_its_samples_inside_the_part(leg: Surface) -> None:
    """Without assembly normals, penetration is still seen from the assembly samples inside the part."""
    m = _seat()
    plain = Assembly(Surface(sample_oriented(m.vertices, m.faces, 4096, 0).points))
    sunk = np.array([0.3, -SEAT_TOP - LEG_HALF + 0.05, 0.3])
    state = measure_contact(leg.moved(sunk), plain)
    assert state.depth > 0.02
    r = refine_offset(leg.moved(sunk), plain, ContactParams())
    assert r.resolved and r.offset[1] < -0.03


def test_measure_contact_gap(seat: Assembly, leg: Surface) -> None:
    t = np.array([0.3, -SEAT_TOP - LEG_HALF - 0.07, 0.3])
    state = measure_contact(leg.moved(t), seat)
    assert state.depth == 0
    assert 0.07 <= state.gap <= 0.07 + 0.03  # sampled: at least the true gap, about a spacing more


def test_refinement_is_deterministic(seat: Assembly, leg: Surface) -> None:
    t = np.array([0.31, -SEAT_TOP - LEG_HALF + 0.04, 0.28])
    a = refine_offset(leg.moved(t), seat, ContactParams())
    b = refine_offset(leg.moved(t), seat, ContactParams())
    np.testing.assert_array_equal(a.offset, b.offset)


def _same(fast: list[Refinement], slow: list[Refinement]) -> None:
    """The batched search chose what the one-part reference chose.

    Both measure the same samples at the same offsets in the same order; the batched one shifts
    each part's block of samples by a multiple of its spacing (tens of units), which changes
    distances by float rounding (about 1e-14), so offsets, gaps and depths agree to 1e-9 (a
    decision could only differ for a gap or depth within 1e-14 of the tolerance).
    """
    assert len(fast) == len(slow)
    for a, b in zip(fast, slow, strict=True):
        assert a.resolved == b.resolved
        np.testing.assert_allclose(a.offset, b.offset, atol=1e-9)
        np.testing.assert_allclose([a.before.gap, a.before.depth, a.after.gap, a.after.depth],
                                   [b.before.gap, b.before.depth, b.after.gap, b.after.depth], atol=1e-9)


def test_batched_search_matches_the_reference_on_synthetic_contacts(seat: Assembly, leg: Surface) -> None:
    """Gaps, penetrations, a touching leg, one too far and one out of reach, in one batch."""
    base = np.array([0.3, -SEAT_TOP - LEG_HALF, 0.3])
    heights = [0.05, 0.02, -0.003, -0.03, -0.06, 0.25, 2.0]
    parts = [leg.moved(base + np.array([0.0, -h, 0.0])) for h in heights]
    params = ContactParams()
    plain = Assembly(Surface(seat.points))  # no assembly normals: only its samples inside the part count
    for assembly in (seat, plain):
        _same(refine_offsets(parts, assembly, params),
              [contact_reference.refine_offset(p, assembly, params) for p in parts])
    assert refine_offsets([], seat, params) == []


def test_few_assembly_samples_within_reach_match_the_reference(leg: Surface) -> None:
    """When fewer assembly samples than are measured lie within reach of the part, the search
    takes the rest nearest first (``contact_kernel._nearest_rest``, pruned by a lower bound):
    the same samples, hence the same refinements, as the reference, which measures every one."""
    m = _seat()
    sparse = sample_oriented(m.vertices, m.faces, 600, 2)
    params = ContactParams()
    base = np.array([0.3, -SEAT_TOP - LEG_HALF, 0.3])
    parts = [leg.moved(base + np.array([0.0, -h, 0.0])) for h in (0.02, 0.06, 0.09, 0.11)]
    reach = params.max_offset + 2 * params.tolerance
    within = [int(np.sum(cKDTree(p.points).query(sparse.points, distance_upper_bound=reach)[0] < reach))
              for p in parts]
    assert all(0 < w < params.search_points for w in within), within  # the case this test is about
    for assembly in (Assembly(sparse), Assembly(Surface(sparse.points))):
        _same(refine_offsets(parts, assembly, params),
              [contact_reference.refine_offset(p, assembly, params) for p in parts])


@pytest.mark.parametrize("seed", [0, 1, 2])
def test_nearest_rest_chooses_the_nearest_samples(leg: Surface, seed: int) -> None:
    """The assembly samples the search measures when few lie within reach: exactly the m nearest
    the part, ties to the lower row, with their exact distances (brute force by cKDTree)."""
    rng = np.random.default_rng(seed)
    a_pts = np.ascontiguousarray(rng.uniform(-0.6, 0.6, size=(700, 3)))
    a_pts[::50] = a_pts[1::50]  # exact ties between rows
    part = np.ascontiguousarray(leg.points)
    m, reach, ub = 128, 0.12, 0.22
    true_d, true_i = cKDTree(part).query(a_pts)
    d2 = np.where(true_d < reach, true_d, np.inf)
    i2 = np.where(true_d < reach, true_i, -1).astype(np.int64)
    known = np.flatnonzero(i2 >= 0)
    assert 0 < len(known) < m
    grid = contact_kernel.build_grid(part, 1.0)
    bd, bi = np.empty(4), np.empty(4, np.int64)
    balls = contact_kernel._clusters(part)[2]
    rows = contact_kernel._nearest_rest(a_pts, balls, grid, d2, i2, known, m, ub, bd, bi)
    chosen = contact_kernel._closest(rows, d2[rows], m)
    expected = np.sort(np.argsort(true_d, kind="mergesort")[:m])
    np.testing.assert_array_equal(chosen, expected)
    np.testing.assert_allclose(d2[chosen], true_d[chosen], rtol=0, atol=1e-12)


def test_threads_give_the_same_answers(seat: Assembly, leg: Surface) -> None:
    """The parts dealt to 1, 2 or 3 threads (more than parts too): the same refinements, in order."""
    base = np.array([0.3, -SEAT_TOP - LEG_HALF, 0.3])
    parts = [leg.moved(base + np.array([0.01 * j, -h, 0.0])) for j, h in enumerate([0.05, -0.03, 0.02, 2.0])]
    one = refine_offsets(parts, seat, ContactParams(threads=1))
    for threads in (2, 3, 8):
        _same(refine_offsets(parts, seat, ContactParams(threads=threads)), one)


@pytest.mark.parametrize("k", [1, 4])
@pytest.mark.parametrize("ub", [0.05, 0.3, np.inf])
def test_grid_nearest_matches_a_kd_tree(k: int, ub: float) -> None:
    """The compiled search's nearest samples: the distances scipy's cKDTree gives for the same
    bound (strict, as its ``distance_upper_bound``), for queries inside, beside and far off the
    points, including a grid capped at its most cells and one of coincident points."""
    rng = np.random.default_rng(k)
    clouds = [rng.normal(size=(500, 3)) * [0.3, 0.1, 0.02], rng.random((30_000, 3)), np.zeros((7, 3))]
    for pts in clouds:
        grid = contact_kernel.build_grid(pts, 1.0)
        queries = np.concatenate([rng.normal(size=(300, 3)) * 0.5, rng.normal(size=(20, 3)) * 10.0])
        want_d, _ = cKDTree(pts).query(queries, k=k, distance_upper_bound=ub)
        want_d = want_d.reshape(len(queries), k)
        d, i = np.empty(k), np.empty(k, dtype=np.int64)
        for q, wd in zip(queries, want_d, strict=True):
            contact_kernel.nearest(q[0], q[1], q[2], grid, k, ub, d, i)
            np.testing.assert_allclose(d, wd, rtol=0, atol=1e-12)
            found = np.isfinite(d)
            assert np.all(i[~found] == -1)
            np.testing.assert_allclose(np.linalg.norm(pts[i[found]] - q, axis=1), d[found], atol=1e-12)


def test_batched_search_matches_the_reference_on_catalog_parts(engine: SuggestionEngine,
                                                               catalog: Catalog) -> None:
    """Real catalog shapes with one part left out, their top-10 suggestions placed by h: against the
    query's points (what /suggest refines) and against the present parts' oriented samples (what
    /assemble and the evaluation refine)."""
    contacts = engine.contacts
    outcomes = set()
    # The benchmark's query (a held-out chair without legs), then catalog shapes without their last
    # part. Its suggestions are also tried lifted by 1.0: too far for any move within the bound
    # (whether h's own placements include such parts depends on the model).
    example = json.loads((REPO / "examples" / "chair-without-legs.json").read_text())
    queries: list[tuple[np.ndarray, list[int]]] = [(np.asarray(example["points"], dtype=np.float32), [])]
    for shape in multi_part_shapes(catalog, 3):
        rows = [i for i, r in enumerate(catalog.records) if r["shape_id"] == shape]
        q = assembly_query(catalog, shape, catalog.part_ids[rows[-1]], engine.artifacts.n_points)
        queries.append((q.points, rows[:-1]))
    for n, (points, present) in enumerate(queries):
        found = engine.suggest(points, SuggestOptions(k=10, refine_contact=False)).suggestions
        idx = np.array([s.part_index for s in found])
        placed = np.array([s.translation for s in found], dtype=np.float64)
        placements = [placed, placed + np.array([0.0, 1.0, 0.0])] if n == 0 else [placed]
        assemblies = [contacts.assembly_from_points(points)]
        if present:
            assemblies.append(Assembly(Surface.union([
                contacts.part_surface(catalog, i).moved(catalog.translations[i]) for i in present])))
        for assembly in assemblies:
            for tr in placements:
                fast = refine_offsets(contacts.placed(catalog, idx, tr), assembly, contacts.params)
                slow = [contact_reference.refine_offset(contacts.part_surface(catalog, int(i)).moved(t),
                                                        assembly, contacts.params)
                        for i, t in zip(idx, tr, strict=True)]
                _same(fast, slow)
                outcomes |= {(r.resolved, bool(np.any(r.offset))) for r in slow}
    # The sample exercises every outcome: moved into contact, touching already, not resolvable.
    assert outcomes == {(True, True), (True, False), (False, False)}, outcomes


def test_surface_cache_resamples_a_changed_mesh() -> None:
    cache = SurfaceCache(64, 0, max_entries=2)
    box = trimesh.creation.box((1.0, 1.0, 1.0))
    a = cache.get("p/0", box.vertices, box.faces)
    assert cache.get("p/0", box.vertices, box.faces) is a
    bigger = trimesh.creation.box((2.0, 1.0, 1.0))
    b = cache.get("p/0", bigger.vertices, bigger.faces)
    assert b is not a and np.abs(b.points[:, 0]).max() > 0.6
    cache.get("q/0", box.vertices, box.faces)
    cache.get("r/0", box.vertices, box.faces)
    assert len(cache._items) == 2


# ------------------------------------------------------------------ engine and API on artifacts


def test_engine_offsets_are_bounded_and_added(engine: SuggestionEngine, query: AssemblyQuery) -> None:
    on = engine.suggest(query.points, SuggestOptions(k=8, refine_contact=True))
    off = engine.suggest(query.points, SuggestOptions(k=8, refine_contact=False))
    assert [s.part_id for s in on.suggestions] == [s.part_id for s in off.suggestions]
    bound = engine.config.contact_max_offset
    for a, b in zip(on.suggestions, off.suggestions, strict=True):
        assert np.all(b.contact_offset == 0)
        assert np.linalg.norm(a.contact_offset) <= bound + 1e-6
        np.testing.assert_allclose(a.translation, b.translation + a.contact_offset, atol=1e-5)
        np.testing.assert_allclose(a.bbox_min - b.bbox_min, a.contact_offset, atol=1e-5)


@pytest.mark.parametrize("fit_scale", [True, False])
def test_engine_refined_parts_touch_the_query(engine: SuggestionEngine, query: AssemblyQuery,
                                              fit_scale: bool) -> None:
    """Every refined placement touches the query by the service's own sampled measure, at the size
    it is answered with (fitted or not), in /suggest and in /place alike."""
    result = engine.suggest(query.points, SuggestOptions(k=8, refine_contact=True, fit_scale=fit_scale))
    assert any(np.any(s.contact_offset != 0) for s in result.suggestions)
    if fit_scale:  # the case that tells a part refined at its catalog size from one refined as served
        assert any(np.max(np.abs(np.log(s.scale))) > 0.05 for s in result.suggestions)
    asm = engine.contacts.assembly_from_points(query.points)
    tol = engine.config.contact_tolerance
    placed = engine.place(query.points, [s.part_id for s in result.suggestions], fit_scale=fit_scale)
    for s, p in zip(result.suggestions, placed.placements, strict=True):
        part = engine.contacts.part_surface(engine.catalog, s.part_index)
        for scale, translation, offset in ((s.scale, s.translation, s.contact_offset),
                                           (p.scale, p.translation, p.contact_offset)):
            if np.any(offset != 0):
                state = measure_contact(part.scaled(scale).moved(translation), asm)
                assert state.touching(tol + 1e-9), (s.part_id, scale, state)


def test_engine_offsets_follow_the_frame(engine: SuggestionEngine, query: AssemblyQuery) -> None:
    """A scaled, shifted, z-up query gets the same offsets, mapped like translations."""
    frame = Frame(center=np.array([1.0, 2.0, 3.0]), radius=4.0, up_axis="z")
    caller = frame.from_canonical(query.points)
    plain = engine.place(query.points, [query.missing])
    framed = engine.place(caller, [query.missing], frame)
    a, b = plain.placements[0], framed.placements[0]
    back = b.contact_offset / frame.radius @ frame.rotation.T
    np.testing.assert_allclose(back, a.contact_offset, atol=1e-4)


def test_api_reports_contact_offset(client: TestClient, query: AssemblyQuery) -> None:
    pts = query.points.tolist()
    on = client.post("/suggest", json={"points": pts, "k": 5, "refine_contact": True}).json()
    off = client.post("/suggest", json={"points": pts, "k": 5, "refine_contact": False}).json()
    for a, b in zip(on["suggestions"], off["suggestions"], strict=True):
        assert a["part_id"] == b["part_id"]
        assert b["contact_offset"] == [0.0, 0.0, 0.0]
        np.testing.assert_allclose(np.add(b["translation"], a["contact_offset"]), a["translation"], atol=1e-5)
    placed = client.post("/place", json={"points": pts, "part_ids": [query.missing]}).json()
    raw = client.post("/place", json={"points": pts, "part_ids": [query.missing],
                                      "refine_contact": False}).json()
    p, r = placed["placements"][0], raw["placements"][0]
    np.testing.assert_allclose(np.add(r["translation"], p["contact_offset"]), p["translation"], atol=1e-5)
    bad = client.post("/place", json={"points": pts, "part_ids": [query.missing], "refine_contact": "maybe"})
    assert bad.status_code == 422 and bad.json()["error"]["code"] == "validation_error"


def test_suggest_refines_only_when_asked_or_configured(engine: SuggestionEngine, settings: Settings,
                                                       client: TestClient, query: AssemblyQuery) -> None:
    """Refinement of suggestions is opt-in (it costs ten times the rest); the setting flips it."""
    pts = query.points.tolist()
    k = 20  # enough suggestions that some are not in contact as h places them
    plain = client.post("/suggest", json={"points": pts, "k": k}).json()
    asked = client.post("/suggest", json={"points": pts, "k": k, "refine_contact": True}).json()
    assert all(s["contact_offset"] == [0.0, 0.0, 0.0] for s in plain["suggestions"])
    assert any(s["contact_offset"] != [0.0, 0.0, 0.0] for s in asked["suggestions"])
    default = engine.suggest(query.points, SuggestOptions(k=k))
    assert all(np.all(s.contact_offset == 0) for s in default.suggestions)
    on_by_default = SuggestionEngine(engine.artifacts, settings.model_copy(
        update={"suggest_refine_contact": True}))
    refined = on_by_default.suggest(query.points, SuggestOptions(k=k))
    np.testing.assert_allclose([s.contact_offset for s in refined.suggestions],
                               [s["contact_offset"] for s in asked["suggestions"]], atol=1e-5)
    # /place keeps refining unless told not to (the modeling page and /assemble rely on it).
    offsets = [client.post("/place", json={"points": pts, "part_ids": [query.missing], **flag}).json()[
        "placements"][0]["contact_offset"] for flag in ({}, {"refine_contact": True})]
    assert offsets[0] == offsets[1]
