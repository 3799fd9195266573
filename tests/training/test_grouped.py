"""The paper-protocol database (``training.evaluate.grouped``): components grouped by label."""

from __future__ import annotations

import copy
from pathlib import Path

import numpy as np
import pytest
from conftest import make_toy_dataset

from training.data.processed import ProcessedDataset
from training.evaluate.grouped import group_by_label


def _with_shared_label() -> tuple[ProcessedDataset, int]:
    """A toy dataset whose first table has its top and its legs labelled alike (both "top")."""
    ds = make_toy_dataset(n_per_category=4, seed=3, cached_points=256)
    ds.shapes = copy.deepcopy(ds.shapes)
    s = next(i for i, m in enumerate(ds.shapes) if m["category"] == "table")
    ds.shapes[s]["labels"][1] = ds.shapes[s]["labels"][0]
    return ds, s


def test_a_labels_components_become_one_part_where_they_were() -> None:
    ds, s = _with_shared_label()
    g = group_by_label(ds, seed=0)
    assert g.grouped_by_label and not ds.grouped_by_label
    assert g.n_components == ds.n_components - 1 and g.n_shapes == ds.n_shapes
    labels = ds.shapes[s]["labels"]
    assert g.shapes[s]["labels"] == [labels[0], *labels[2:]]
    top, legs = ds.components_of(s)[:2]
    merged = int(g.first_comp[s])
    # Its mesh is the two meshes where they sit in the shape, centred at their joint box centre.
    placed = np.concatenate([ds.component_mesh(c)[0] + ds.translation[c] for c in (top, legs)])
    centre = (placed.min(axis=0) + placed.max(axis=0)) / 2
    np.testing.assert_allclose(g.translation[merged], centre, atol=1e-6)
    v, f = g.component_mesh(merged)
    np.testing.assert_allclose(v + g.translation[merged], placed, atol=1e-5)
    assert f.max() == len(v) - 1 and len(f) == sum(len(ds.component_mesh(c)[1]) for c in (top, legs))
    assert g.area[merged] == pytest.approx(ds.area[top] + ds.area[legs])
    # Its samples are the members' own samples (no new points), as many from each as its area says.
    samples = g.points[merged].astype(np.float64) + g.translation[merged]
    member = [ds.points[c].astype(np.float64) + ds.translation[c] for c in (top, legs)]
    nearest = np.stack([np.min(np.linalg.norm(samples[:, None] - m[None], axis=2), axis=1) for m in member])
    assert np.all(nearest.min(axis=0) < 2e-3)
    from_top = int(np.sum(nearest[0] < nearest[1]))
    share = ds.area[top] / (ds.area[top] + ds.area[legs])
    assert abs(from_top - share * len(samples)) <= 2
    # Every other component is as it was.
    last_old, last_new = ds.n_components - 1, g.n_components - 1
    for c_old, c_new in ((int(ds.first_comp[s]) + 2, merged + 1), (0, 0), (last_old, last_new)):
        np.testing.assert_array_equal(g.points[c_new], ds.points[c_old])
        np.testing.assert_array_equal(g.translation[c_new], ds.translation[c_old])
        np.testing.assert_array_equal(g.component_mesh(c_new)[1], ds.component_mesh(c_old)[1])


def test_groups_touch_what_their_members_touched_and_never_themselves() -> None:
    ds, s = _with_shared_label()
    g = group_by_label(ds, seed=0)
    top, legs = ds.components_of(s)[:2]
    assert [int(top), int(legs)] in ds.edges.tolist()  # the toy table's top touches its legs
    first = int(g.first_comp[s])
    ours = {tuple(e) for e in g.edges.tolist() if g.shape_of[e[0]] == s}
    assert all(a != b for a, b in g.edges.tolist())
    # The shelf touched the legs: now it touches the merged part.
    had_shelf = len(ds.components_of(s)) == 3
    assert ours == ({(first, first + 1)} if had_shelf else set())
    assert len(g.edges) == len(ds.edges) - 1


def test_grouping_is_seeded_and_refused_for_training(tmp_path: Path) -> None:
    from training.config import resolve_config
    from training.train import train

    ds, _ = _with_shared_label()
    a, b = group_by_label(ds, seed=0), group_by_label(ds, seed=0)
    assert a.content_hash() == b.content_hash()
    assert group_by_label(ds, seed=1).content_hash() != a.content_hash()
    a.save(tmp_path / "grouped")
    assert ProcessedDataset.load(tmp_path / "grouped").grouped_by_label
    cfg = resolve_config("tiny", overrides={"data": str(tmp_path / "grouped"), "run": str(tmp_path / "run"),
                                            "steps": 2})
    with pytest.raises(ValueError, match="grouped by their labels"):
        train(cfg, show_progress=False)
    assert not (tmp_path / "run").exists()
