"""Invariants of the triplet sampler (paper, Sec. 5.3) on a dataset made by the real preprocessing."""

from __future__ import annotations

import dataclasses
from collections.abc import Iterator

import numpy as np
import pytest
import trimesh

from service.geometry.mesh import points_to_mesh_distance
from training.config import resolve_config
from training.data.preprocess import Kept, PreprocessConfig, ShapeRecord, assemble, preprocess_shape
from training.data.processed import ProcessedDataset
from training.data.sampling import (
    Triplet,
    TripletSampler,
    component_descriptors,
    layout_warp,
    lookalike_components,
    sample_assembly,
    sample_part,
    shape_lookalikes,
    warp_boxes,
)
from training.data.shapes import RawPiece, RawShape

# Cached points are float16: coordinates below 1 round by at most 2.4e-4 each.
FLOAT16_TOL = 1e-3


def box(extents: tuple[float, float, float], centre: tuple[float, float, float], name: str,
        key: str | None = None) -> RawPiece:
    m = trimesh.creation.box(extents=extents)
    m.apply_translation(centre)
    return RawPiece(name, np.array(m.vertices), np.array(m.faces), key or name, name)


def chair(rng: np.random.Generator, i: int) -> RawShape:
    w, d, h = rng.uniform(0.8, 1.2), rng.uniform(0.8, 1.2), rng.uniform(0.4, 0.6)
    pieces = [box((w, 0.1, d), (0, h + 0.05, 0), "seat"),
              box((w, 0.8, 0.1), (0, h + 0.5, -d / 2 + 0.05), "back")]
    pieces += [box((0.1, h, 0.1), (sx * (w / 2 - 0.05), h / 2, sz * (d / 2 - 0.05)), f"leg{k}", key="leg")
               for k, (sx, sz) in enumerate([(-1, -1), (1, -1), (-1, 1), (1, 1)])]
    if i % 2:  # arms resting on the seat, touching the back
        pieces += [box((0.1, 0.3, d - 0.1), (sx * (w / 2 - 0.05), h + 0.25, 0.05), f"arm{k}", key="arm")
                   for k, sx in enumerate((-1, 1))]
    return RawShape(f"chair-{i}", "chair", pieces)


def lamp(rng: np.random.Generator, i: int) -> RawShape:
    pole = rng.uniform(0.8, 1.4)
    pieces = [box((0.6, 0.08, 0.6), (0, 0.04, 0), "base"),
              box((0.08, pole, 0.08), (0, 0.08 + pole / 2, 0), "pole"),
              box((0.7, 0.3, 0.7), (0, 0.08 + pole + 0.15, 0), "shade")]
    return RawShape(f"lamp-{i}", "lamp", pieces)


@pytest.fixture(scope="module")
def dataset() -> ProcessedDataset:
    rng = np.random.default_rng(0)
    config = PreprocessConfig(points_per_component=256)
    results = []
    for shape in [chair(rng, i) for i in range(4)] + [lamp(rng, i) for i in range(3)]:
        r = preprocess_shape(shape, config)
        assert isinstance(r, Kept), r
        results.append(ShapeRecord(shape.shape_id, shape.category, None, "test", r))
    return assemble(results, config)


def test_dataset_has_the_expected_graphs(dataset: ProcessedDataset) -> None:
    sizes = np.diff(dataset.first_comp).tolist()
    assert sizes == [3, 4, 3, 4, 3, 3, 3]  # seat, back, legs (+ arms); base, pole, shade


def _connected_within(nodes: list[int], adj: list[set[int]]) -> bool:
    seen, todo = {nodes[0]}, [nodes[0]]
    while todo:
        for nb in adj[todo.pop()] & set(nodes):
            if nb not in seen:
                seen.add(nb)
                todo.append(nb)
    return seen == set(nodes)


def _triplets(sampler: TripletSampler, n: int, seed: int) -> Iterator[Triplet]:
    """``n`` triplets of ``sampler``, drawn with ``np.random.default_rng(seed)``."""
    rng = np.random.default_rng(seed)
    return (sampler.sample_triplet(rng) for _ in range(n))


def test_triplets_respect_the_contact_graph(dataset: ProcessedDataset) -> None:
    sampler = TripletSampler(dataset, n_points=64)
    adj = dataset.adjacency()
    for t in _triplets(sampler, 300, seed=1):
        comps = set(dataset.components_of(t.shape).tolist())
        assert set(t.query) <= comps and 1 <= len(t.query) <= len(comps) - 1
        assert len(set(t.query)) == len(t.query)
        assert _connected_within(t.query, adj)
        assert t.positive in comps and t.positive not in t.query
        assert any(t.positive in adj[q] for q in t.query)
        assert t.negative not in t.query
        assert not any(t.negative in adj[q] for q in t.query)


def test_query_negatives_come_from_the_query_at_the_asked_share(dataset: ProcessedDataset) -> None:
    sampler = TripletSampler(dataset, n_points=64, query_negative_fraction=0.4)
    adj = dataset.adjacency()
    from_query = 0
    for t in _triplets(sampler, 1000, seed=5):
        assert t.negative != t.positive
        if t.negative in t.query:
            from_query += 1
        else:  # the paper's negative: neither in X nor adjacent to it
            assert not any(t.negative in adj[q] for q in t.query)
    assert from_query / 1000 == pytest.approx(0.4, abs=0.05)


def test_query_negative_fraction_outside_0_1_is_refused(dataset: ProcessedDataset) -> None:
    with pytest.raises(ValueError, match="query_negative_fraction"):
        TripletSampler(dataset, query_negative_fraction=1.5)


def test_hard_negative_shares_over_one_are_refused_by_sampler_and_config(dataset: ProcessedDataset) -> None:
    # One rule (training.config.check_negative_shares), read by both: the config fails before any
    # data is loaded, the sampler when built directly.
    with pytest.raises(ValueError, match=r"TripletSampler: .*sum to at most 1, got \(0.6, 0.5, 0.0\)"):
        TripletSampler(dataset, query_negative_fraction=0.6, lookalike_negative_fraction=0.5)
    with pytest.raises(ValueError, match=r"train config: .*sum to at most 1, got \(0.0, 0.5, 0.6\)"):
        overrides = {"lookalike_negative_fraction": 0.5, "shape_negative_fraction": 0.6}
        resolve_config(overrides=overrides).validate()
    TripletSampler(dataset, query_negative_fraction=0.5, lookalike_negative_fraction=0.5)   # at 1: allowed


def test_lookalikes_are_the_nearest_components_of_other_shapes_of_the_category(
        dataset: ProcessedDataset) -> None:
    desc = component_descriptors(dataset)
    near = lookalike_components(dataset, 2)
    category = [dataset.shapes[int(s)]["category"] for s in dataset.shape_of]
    for comp in range(dataset.n_components):
        others = [c for c in range(dataset.n_components)
                  if category[c] == category[comp] and dataset.shape_of[c] != dataset.shape_of[comp]]
        dist = {c: float(np.linalg.norm(desc[c] - desc[comp])) for c in others}
        best = sorted(dist.values())[:2]
        assert [dist[int(c)] for c in near[comp]] == pytest.approx(best)


def test_lookalike_negatives_come_from_other_shapes_of_the_category(dataset: ProcessedDataset) -> None:
    sampler = TripletSampler(dataset, n_points=32, lookalike_negative_fraction=1.0, lookalike_neighbours=2)
    for t in _triplets(sampler, 200, seed=6):
        neg_shape = int(dataset.shape_of[t.negative])
        assert neg_shape != t.shape
        assert dataset.shapes[neg_shape]["category"] == dataset.shapes[t.shape]["category"]
        assert any(t.negative in sampler.lookalikes[q] for q in t.query)


def test_shape_negatives_skip_copies_of_the_part_in_other_shapes() -> None:
    """Two chairs of one geometry (sampled apart) and a third: each twin's parts are the other's
    nearest look-alikes, yet never its shape negatives, which ask for another shape."""
    config = PreprocessConfig(points_per_component=2048)
    shapes = [chair(np.random.default_rng(5), 0), chair(np.random.default_rng(5), 2),
              chair(np.random.default_rng(6), 4)]
    results = []
    for shape in shapes:
        r = preprocess_shape(shape, config)
        assert isinstance(r, Kept), r
        results.append(ShapeRecord(shape.shape_id, shape.category, None, "test", r))
    twins = assemble(results, config)
    near = lookalike_components(twins, 2)
    strict = shape_lookalikes(twins, k=2)
    np.testing.assert_array_equal(shape_lookalikes(twins, k=2, min_distance=0.0), near)
    first, second = (twins.components_of(s) for s in (0, 1))
    for a, b in zip(first.tolist(), second.tolist(), strict=True):
        assert b in near[a].tolist() and a in near[b].tolist()   # each twin's part is the other's look-alike
        assert b not in strict[a].tolist() and a not in strict[b].tolist()
    assert (strict == -1).any() and (strict >= 0).all(axis=1).sum() < len(strict)


def test_shape_negatives_do_the_positive_s_job_in_another_shape(dataset: ProcessedDataset) -> None:
    sampler = TripletSampler(dataset, n_points=32, shape_negative_fraction=1.0)
    assert sampler.shape_negatives is not None
    drawn = 0
    for t in _triplets(sampler, 200, seed=9):
        assert t.negative not in t.query and t.negative != t.positive
        assert t.shape_negative == bool((sampler.shape_negatives[t.positive] >= 0).any())
        if t.shape_negative:
            assert t.negative in sampler.shape_negatives[t.positive].tolist()
            assert int(dataset.shape_of[t.negative]) != t.shape
            drawn += 1
    assert drawn > 50
    batch = sampler.batch(16, np.random.default_rng(10))
    assert batch["Z_shape"].dtype == bool and batch["Z_shape"].any()


def test_h_sees_the_positive_undone_by_its_log_scale(dataset: ProcessedDataset) -> None:
    sampler = TripletSampler(dataset, n_points=64, scale_augment=0.3)
    batch = sampler.batch(16, np.random.default_rng(7))
    back = batch["Y_h"] * np.exp(batch["Y_log_scale"])[:, None, :]
    np.testing.assert_allclose(back, batch["Y"], atol=1e-5)


def test_substitutes_are_look_alikes_fitted_to_the_positive_s_size(dataset: ProcessedDataset) -> None:
    """With substitutes h sees another shape's look-alike part, and its target log scale takes that
    part's box to the positive's (the chairs' legs differ in height from shape to shape)."""
    sampler = TripletSampler(dataset, n_points=256, substitute_fraction=1.0, lookalike_neighbours=2)
    batch = sampler.batch(32, np.random.default_rng(8))
    fitted = batch["Y_h"] * np.exp(batch["Y_log_scale"])[:, None, :]
    want, got = np.ptp(batch["Y"], axis=1), np.ptp(fitted, axis=1)
    fat = want > 0.05   # thin axes are left unscaled (MIN_FIT_EXTENT)
    assert np.abs(np.log(got[fat] / want[fat])).max() < 0.05
    moved = np.abs(batch["Y_log_scale"]).max(axis=1) > 0.01
    assert moved.mean() > 0.5, "the look-alikes were the positives themselves"
    plain = TripletSampler(dataset, n_points=64).batch(8, np.random.default_rng(8))
    np.testing.assert_array_equal(plain["Y_h"], plain["Y"])
    assert not plain["Y_log_scale"].any()


def test_mixed_queries_swap_components_for_look_alikes_at_their_place(dataset: ProcessedDataset) -> None:
    """A mixed query keeps every component's place and box (look-alikes are centred and fitted to
    it), but its surface comes in part from other shapes; off, X is the shape's own samples."""
    sampler = TripletSampler(dataset, n_points=256, mixed_query_fraction=1.0, lookalike_neighbours=2)
    plain = TripletSampler(dataset, n_points=256)
    rng = np.random.default_rng(3)
    swapped = 0
    for _ in range(20):
        query = next(_triplets(plain, 1, seed=int(rng.integers(1 << 30)))).query
        cloud = sampler.query_points(query, 256, rng)
        lo = np.min([dataset.points[c].min(axis=0) + dataset.translation[c] for c in query], axis=0)
        hi = np.max([dataset.points[c].max(axis=0) + dataset.translation[c] for c in query], axis=0)
        inside = (cloud >= lo - 0.03) & (cloud <= hi + 0.03)
        assert inside.all()
        own = np.concatenate([dataset.points[c].astype(np.float32) + dataset.translation[c] for c in query])
        nearest = np.min(np.linalg.norm(cloud[:, None] - own[None], axis=2), axis=1)
        swapped += bool(np.mean(nearest > 1e-4) > 0.1)
        ref = plain.query_points(query, 256, np.random.default_rng(0))
        assert np.min(np.linalg.norm(ref[:, None] - own[None], axis=2), axis=1).max() < 1e-4
    assert swapped >= 5, "no query was mixed"


def test_a_layout_warp_is_monotone_and_keeps_the_frame() -> None:
    knots, warped = layout_warp(np.random.default_rng(4))
    np.testing.assert_allclose(warped[:, [0, -1]], [[-1, 1]] * 3)
    assert (np.diff(warped, axis=1) > 0).all()
    assert np.abs(warped - knots).max() > 0.02, "the warp moved nothing"


def test_warped_boxes_that_meet_at_a_face_still_meet() -> None:
    """A leg under a seat: the leg's top face and the seat's bottom face are one coordinate, which
    the warp maps to one place; each box is rescaled to the warped span of its corners."""
    knots, warped = layout_warp(np.random.default_rng(5))
    centre = np.array([[0.0, -0.5, 0.0], [0.0, 0.05, 0.0]])     # leg (y -1..0), seat (y 0..0.1)
    half = np.array([[0.05, 0.5, 0.05], [0.5, 0.05, 0.5]])
    new_centre, scale = warp_boxes(knots, warped, centre, half)
    leg_top = new_centre[0, 1] + half[0, 1] * scale[0, 1]
    seat_bottom = new_centre[1, 1] - half[1, 1] * scale[1, 1]
    assert leg_top == pytest.approx(seat_bottom, abs=1e-6)
    assert new_centre[0, 1] - half[0, 1] * scale[0, 1] == pytest.approx(-1.0, abs=1e-6)
    thin = warp_boxes(knots, warped, np.zeros((1, 3)), np.zeros((1, 3)))[1]
    assert (thin > 0).all(), "a flat box takes its segment's stretch"


def test_warped_layouts_move_parts_with_their_boxes(dataset: ProcessedDataset) -> None:
    """With the layout warped, the positive's target place and size are its warped box's, the
    query's points lie on warped components, and h's part stays the catalog geometry (its fitting
    scale undoes the warp); off, batches are drawn exactly as before."""
    sampler = TripletSampler(dataset, n_points=256, layout_warp=1.0)
    batch = sampler.batch(32, np.random.default_rng(9))
    moved = np.abs(batch["Y_log_scale"]).max(axis=1) > 0.01
    assert moved.mean() > 0.5, "no positive was rescaled by the warp"
    fitted = batch["Y_h"] * np.exp(batch["Y_log_scale"])[:, None, :]
    want, got = np.ptp(batch["Y"], axis=1), np.ptp(fitted, axis=1)
    fat = want > 0.05
    assert np.abs(np.log(got[fat] / want[fat])).max() < 0.05
    inside = np.abs(batch["X"]) <= 1.0 + 1e-3      # the warp keeps the unit frame
    assert inside.all()
    plain = TripletSampler(dataset, n_points=64).batch(8, np.random.default_rng(8))
    off = TripletSampler(dataset, n_points=64, layout_warp=0.0).batch(8, np.random.default_rng(8))
    for key in plain:
        np.testing.assert_array_equal(plain[key], off[key])


def test_negative_shares_summing_past_one_are_refused(dataset: ProcessedDataset) -> None:
    with pytest.raises(ValueError, match="at most 1"):
        TripletSampler(dataset, query_negative_fraction=0.6, lookalike_negative_fraction=0.6)
    with pytest.raises(ValueError, match="at most 1"):
        TripletSampler(dataset, query_negative_fraction=0.5, lookalike_negative_fraction=0.25,
                       shape_negative_fraction=0.5)


def test_removal_queries_are_a_shape_minus_a_connected_group(dataset: ProcessedDataset) -> None:
    sampler = TripletSampler(dataset, n_points=32, removal_query_fraction=1.0)
    adj = dataset.adjacency()
    disconnected = 0
    for t in _triplets(sampler, 300, seed=8):
        comps = set(dataset.components_of(t.shape).tolist())
        removed = sorted(comps - set(t.query))
        assert removed and t.query and _connected_within(removed, adj)
        assert t.positive in removed and any(t.positive in adj[q] for q in t.query)
        assert t.negative not in t.query and not any(t.negative in adj[q] for q in t.query)
        disconnected += not _connected_within(t.query, adj)
    assert disconnected > 0  # a chair without its seat: legs and back do not touch


def test_positives_drawn_by_size_favour_the_larger_neighbours(dataset: ProcessedDataset) -> None:
    """``positive_size_power``: Y is still one of X's neighbours, but the larger ones win more
    often than a uniform draw gives them; power 0 is the paper's draw, batch for batch."""
    adj = dataset.adjacency()

    def share_of_larger(sampler: TripletSampler) -> float:
        """Mean share of Y's other neighbours that are larger than Y (0: Y is always the largest)."""
        diag = np.linalg.norm(component_descriptors(dataset)[:, 3:], axis=1)
        shares = []
        for t in _triplets(sampler, 1000, seed=11):
            neighbours = sorted(set().union(*(adj[q] for q in t.query)) - set(t.query))
            assert t.positive in neighbours
            if len(neighbours) > 1:
                shares.append(sum(diag[n] > diag[t.positive] for n in neighbours) / (len(neighbours) - 1))
        assert len(shares) > 200
        return float(np.mean(shares))

    uniform = share_of_larger(TripletSampler(dataset, n_points=32))
    sized = share_of_larger(TripletSampler(dataset, n_points=32, positive_size_power=4.0))
    assert sized < uniform - 0.1, (sized, uniform)
    plain = TripletSampler(dataset, n_points=32).batch(8, np.random.default_rng(3))
    zero = TripletSampler(dataset, n_points=32, positive_size_power=0.0).batch(8, np.random.default_rng(3))
    for key in plain:
        np.testing.assert_array_equal(plain[key], zero[key])
    with pytest.raises(ValueError, match="positive_size_power"):
        TripletSampler(dataset, positive_size_power=-1.0)


def test_sampled_points_lie_on_the_components(dataset: ProcessedDataset) -> None:
    sampler = TripletSampler(dataset, n_points=128)
    rng = np.random.default_rng(2)
    for _ in range(20):
        t = sampler.sample_triplet(rng)
        x = sample_assembly(dataset, t.query, 128, rng)
        placed = [(v + dataset.translation[c], f) for c in t.query for v, f in [dataset.component_mesh(c)]]
        dist = np.min([points_to_mesh_distance(x, v, f) for v, f in placed], axis=0)
        assert x.shape == (128, 3) and x.dtype == np.float32 and dist.max() < FLOAT16_TOL
        for comp in (t.positive, t.negative):
            y = sample_part(dataset, comp, 128, rng)
            v, f = dataset.component_mesh(comp)
            assert points_to_mesh_distance(y, v, f).max() < FLOAT16_TOL


def test_assembly_samples_are_area_weighted(dataset: ProcessedDataset) -> None:
    comps = dataset.components_of(0)[:2]
    x = sample_assembly(dataset, comps, 20_000, np.random.default_rng(3))
    v, f = dataset.component_mesh(int(comps[0]))
    on_first = points_to_mesh_distance(x[:2000] - dataset.translation[comps[0]], v, f) < FLOAT16_TOL
    share = dataset.area[comps[0]] / dataset.area[comps].sum()
    assert on_first.mean() == pytest.approx(share, abs=0.04)


def test_batch_arrays(dataset: ProcessedDataset) -> None:
    batch = TripletSampler(dataset, n_points=32).batch(5, np.random.default_rng(4))
    for key in ("X", "Y", "Z"):
        assert batch[key].shape == (5, 32, 3) and batch[key].dtype == np.float32
    assert batch["Y_translation"].shape == (5, 3)


def test_a_dataset_without_any_possible_negative_is_refused(dataset: ProcessedDataset) -> None:
    # One shape of two touching components (a lamp's base and pole): every component is in X or
    # adjacent to it, so no negative exists.
    tiny = _first_components(dataset.subset([4]), 2)
    assert tiny.edges.tolist() == [[0, 1]]
    with pytest.raises(ValueError, match="negative"):
        TripletSampler(tiny, n_points=8).sample_triplet(np.random.default_rng(0))


def _first_components(ds: ProcessedDataset, n: int) -> ProcessedDataset:
    """A one-shape dataset holding only the first ``n`` (connected) components of shape 0."""
    comps = np.arange(n)
    edges = ds.edges[(ds.edges < n).all(axis=1)]
    return ProcessedDataset(
        points=ds.points[comps], translation=ds.translation[comps], area=ds.area[comps],
        shape_of=np.zeros(n, np.int32), first_comp=np.array([0, n]), edges=edges,
        mesh_vertices=ds.mesh_vertices[:ds.vertex_first[n]], mesh_faces=ds.mesh_faces[:ds.face_first[n]],
        vertex_first=ds.vertex_first[:n + 1], face_first=ds.face_first[:n + 1],
        shapes=[{**ds.shapes[0], "labels": ds.shapes[0]["labels"][:n]}], info={})


def test_augment_strength_widens_the_augmentation_s_rescale(dataset: ProcessedDataset) -> None:
    """The same draws at strength 2 rescale each augmented positive by the square of strength 1's
    factors (twice the log scales); strength 1 is the default's batches exactly."""
    def positives(strength: float | None) -> np.ndarray:
        sampler = (TripletSampler(dataset, n_points=64, augment=1.0) if strength is None else
                   TripletSampler(dataset, n_points=64, augment=1.0, augment_strength=strength))
        # No holes: how many points a hole replaces depends on the points, and so would the draws
        # of the triplets after it.
        sampler.ranges = dataclasses.replace(sampler.ranges, hole_probability=0.0)
        return sampler.batch(16, np.random.default_rng(5))["Y"].astype(np.float64)

    np.testing.assert_array_equal(positives(1.0), positives(None))
    before, one, two = positives(1e-9), positives(1.0), positives(2.0)
    for b in range(len(before)):
        logs = []
        for after in (one, two):
            A = np.linalg.lstsq(before[b], after[b], rcond=None)[0]
            logs.append(np.log(np.linalg.svd(A, compute_uv=False)))
        np.testing.assert_allclose(logs[1], 2 * logs[0], atol=2e-3)
        assert np.abs(logs[0]).max() <= 0.2 + 0.1 + 1e-3  # per axis and whole shape, strength 1


def test_without_augmented_parts_the_query_alone_is_augmented(dataset: ProcessedDataset) -> None:
    """``augment_parts`` off: the query as augmented as before, the positive and negatives as the
    catalog holds them (the same draws with the augmentation's transform near identity), h's
    translation target augmented with the query."""
    def batch(**options: object) -> dict[str, np.ndarray]:
        sampler = TripletSampler(dataset, n_points=64, augment=1.0, **options)  # type: ignore[arg-type]
        sampler.ranges = dataclasses.replace(sampler.ranges, hole_probability=0.0)
        return sampler.batch(16, np.random.default_rng(6))

    both, query_only, near_identity = batch(), batch(augment_parts=False), batch(augment_strength=1e-9)
    np.testing.assert_array_equal(query_only["X"], both["X"])
    np.testing.assert_array_equal(query_only["Y_translation"], both["Y_translation"])
    for key in ("Y", "Z", "P"):
        np.testing.assert_allclose(query_only[key], near_identity[key], atol=1e-6)
        assert np.abs(both[key] - query_only[key]).max() > 0.01, key
