"""Frames for partial uploads (service.suggest.frame_fit): hypotheses, the choice, and the API.

The quality check runs on the artifacts under test: the example chair without legs, uploaded in
millimetres and z up without a frame, must get legs (its label is read only in the check).
"""

from __future__ import annotations

import io
import json
from pathlib import Path

import numpy as np
import pytest
import trimesh
from fastapi.testclient import TestClient

from service.artifacts.catalog import Catalog, split_shapes
from service.geometry.frames import Frame
from service.settings import Settings
from service.suggest.engine import SuggestionEngine, SuggestOptions, SuggestResult, category_probability
from service.suggest.frame_fit import (
    best_frame,
    category_probabilities_of,
    choose_frame,
    fit_frame,
    frame_hypotheses,
    most_familiar,
    scoring_queries,
    up_axes_for,
)

EXAMPLE = Path(__file__).resolve().parents[2] / "examples" / "chair-without-legs.obj"
# The example in a designer's units: millimetres (the complete chair about 450 mm in radius),
# z up, somewhere on the desk.
MM = 450.0
DESK = np.array([1200.0, -300.0, 720.0])


def _in_mm_z_up(vertices: np.ndarray) -> np.ndarray:
    """Canonical (y up, unit radius) vertices as a z-up millimetre file has them."""
    return Frame(center=DESK, radius=MM, up_axis="z").from_canonical(vertices)


def test_hypotheses_hold_the_partial_inside_the_unit_ball() -> None:
    pts = np.random.default_rng(0).uniform([-0.4, 0.0, -0.3], [0.4, 0.5, 0.3], size=(500, 3)) * 300
    frames = frame_hypotheses(pts, ("y", "z"), ratios=[1.0, 1.5, 2.5], shifts=[-1, 0, 1])
    assert {f.up_axis for f in frames} == {"y", "z"}
    assert len(frames) <= 2 * 3 * 3
    for f in frames:
        q = f.to_canonical(pts)
        assert np.linalg.norm(q, axis=1).max() <= 1.0 + 1e-6


def test_hypotheses_contain_the_true_frame_of_a_top_half() -> None:
    """A part that is the top of a complete object: one hypothesis puts it back at the top."""
    whole = np.random.default_rng(1).uniform(-0.5, 0.5, size=(2000, 3))
    whole /= np.linalg.norm(whole - (whole.min(0) + whole.max(0)) / 2, axis=1).max()
    top = whole[whole[:, 1] > 0.1]
    frames = frame_hypotheses(top, ("y",), ratios=np.geomspace(1, 2.5, 9).tolist(),
                              shifts=np.linspace(-1, 1, 9).tolist())
    err = min(np.linalg.norm(f.center) + abs(f.radius - 1.0) for f in frames)
    assert err < 0.15


def _shape_but_its_last_part(catalog: Catalog) -> np.ndarray:
    rows = np.flatnonzero(catalog.shape_of == catalog.shape_of[0])
    return np.concatenate([catalog.part_points(int(i)) + catalog.translations[i] for i in rows[:-1]])


def test_best_frame_without_an_engine_keeps_the_most_likely_hypothesis(engine: SuggestionEngine,
                                                                       catalog: Catalog) -> None:
    frames = [Frame(radius=r) for r in (1.0, 2.0)]
    results = engine.suggest_batch([(_shape_but_its_last_part(catalog), SuggestOptions(k=1, frame=f))
                                    for f in frames])
    fit = best_frame(frames, results)
    scores = [r.suggestions[0].score for r in results]  # type: ignore[union-attr]
    assert fit.frame is frames[int(np.argmax(scores))] and fit.hypotheses == 2


def test_most_familiar_keeps_the_smallest_distance_plus_the_radius_prior(engine: SuggestionEngine,
                                                                          catalog: Catalog) -> None:
    """A catalog shape without its last part, in its own frame or shrunk into a room twice its
    size: its own frame is the more familiar; the prior adds 0.8 log 2 to the larger one."""
    pts = _shape_but_its_last_part(catalog)
    frames = [Frame(radius=r) for r in (1.0, 2.0)]
    answers = engine.suggest_batch(scoring_queries(frames, pts, SuggestOptions(), mixture_only=True))
    assert all(isinstance(r, SuggestResult) and not r.suggestions for r in answers)
    distances = np.array([r.familiarity for r in answers])  # type: ignore[union-attr]
    assert distances[0] < distances[1]
    # g's answer alone is the one of full suggestion queries, in the same batch or not.
    results = engine.suggest_batch([(pts, SuggestOptions(k=1, frame=f)) for f in frames] + [
        (pts, SuggestOptions(frame=frames[1], mixture_only=True))])
    assert [r.familiarity for r in results] == pytest.approx([*distances, distances[1]], abs=1e-4)  # type: ignore[union-attr]
    assert len(results[0].suggestions) == 1  # type: ignore[union-attr]
    assert choose_frame(frames, answers, 0.8).frame is frames[0]
    # Priced as g alone by the batcher's cost model.
    cost = engine.query_cost
    assert cost(len(pts), SuggestOptions(mixture_only=True)) < cost(len(pts), SuggestOptions(k=1))
    fit = most_familiar(frames, distances, radius_prior=0.0)
    assert fit.frame is frames[0] and fit.scores == pytest.approx([-d for d in distances])
    assert most_familiar(frames, distances, radius_prior=0.8).scores[1] == pytest.approx(
        -distances[1] - 0.8 * np.log(2.0))


def test_up_axes_for() -> None:
    assert set(up_axes_for(None)) == {"y", "z"}
    assert up_axes_for(Frame(up_axis="z")) == ("z",)


def _example_mesh() -> trimesh.Trimesh:
    loaded = trimesh.load(EXAMPLE, force="mesh")
    assert isinstance(loaded, trimesh.Trimesh)
    return trimesh.Trimesh(_in_mm_z_up(np.asarray(loaded.vertices)), np.asarray(loaded.faces), process=False)


def _obj_bytes(mesh: trimesh.Trimesh) -> bytes:
    text = mesh.export(file_type="obj")
    assert isinstance(text, str)
    return text.encode()


def test_fit_recovers_the_example_frame(engine: SuggestionEngine, settings: Settings) -> None:
    """The chair without legs in millimetres and z up: up axis, centre and radius recovered."""
    mesh = _example_mesh()
    pts = np.asarray(trimesh.sample.sample_surface(mesh, 2000, seed=0)[0])
    fit = fit_frame(engine, settings, pts, SuggestOptions(categories=("chair",)))
    assert fit.frame.up_axis == "z"
    assert 0.7 * MM <= fit.frame.radius <= 1.4 * MM
    # Measured on the shipped model: radius 392 mm (true 450), centre 165 mm above the true one.
    assert np.linalg.norm(fit.frame.center - DESK) <= 0.5 * MM


def _labels(answer: dict) -> list[str | None]:
    return [s["label"] for s in answer["suggestions"]]


def test_upload_without_a_frame_gets_legs(client: TestClient) -> None:
    """Uploaded in millimetres, z up, no frame: the service fits the frame, reports it, and
    suggests legs (measured by the catalog labels, which only this check reads)."""
    data = _obj_bytes(_example_mesh())
    r = client.post("/suggest/mesh", files={"file": ("chair.obj", io.BytesIO(data), "text/plain")},
                    data={"options": json.dumps({"k": 5, "category": "chair"})})
    assert r.status_code == 200, r.text
    body = r.json()
    assert body["frame_fitted"] is True and body["frame"]["up_axis"] == "z"
    assert 0.7 * MM <= body["frame"]["radius"] <= 1.4 * MM
    assert "leg" in _labels(body), _labels(body)
    # The answer is in the file's frame: the legs go below the seat, along -z, in millimetres.
    leg = next(s for s in body["suggestions"] if s["label"] == "leg")
    assert leg["translation"][2] < DESK[2]
    # Asked not to fit, the same upload is read in the canonical frame and answered as such.
    raw = client.post("/suggest/mesh", files={"file": ("chair.obj", io.BytesIO(data), "text/plain")},
                      data={"options": json.dumps({"k": 5, "category": "chair", "fit_frame": False})})
    assert raw.status_code == 200 and raw.json()["frame_fitted"] is False
    assert raw.json()["frame"]["radius"] == 1.0


def test_points_fit_only_when_asked(client: TestClient) -> None:
    mesh = _example_mesh()
    pts = trimesh.sample.sample_surface(mesh, 1000, seed=0)[0].tolist()
    plain = client.post("/suggest", json={"points": pts, "k": 3, "category": "chair"}).json()
    assert plain["frame_fitted"] is False and plain["frame"]["radius"] == 1.0
    fitted = client.post("/suggest", json={"points": pts, "k": 3, "category": "chair", "fit_frame": True})
    assert fitted.status_code == 200, fitted.text
    assert fitted.json()["frame_fitted"] is True and fitted.json()["frame"]["up_axis"] == "z"
    # With a frame, its up axis is kept and the rest fitted.
    kept = client.post("/suggest", json={"points": pts, "k": 3, "category": "chair", "fit_frame": True,
                                         "frame": {"up_axis": "y"}}).json()
    assert kept["frame"]["up_axis"] == "y"


def test_batch_refuses_fit_frame(client: TestClient) -> None:
    item = {"points": [[0.0, 0.0, 0.0], [0.1, 0.0, 0.0], [0.0, 0.1, 0.0]] * 8, "fit_frame": True}
    r = client.post("/suggest/batch", json={"items": [item]})
    assert r.status_code == 200, r.text
    result = r.json()["results"][0]
    assert result["ok"] is False and result["error"]["code"] == "fit_frame_unsupported"


def test_assemble_mesh_without_a_frame_is_fitted(client: TestClient) -> None:
    data = _obj_bytes(_example_mesh())
    r = client.post("/assemble/mesh", files={"file": ("chair.obj", io.BytesIO(data), "text/plain")},
                    data={"options": json.dumps({"max_parts": 2, "category": "chair"})})
    assert r.status_code == 200, r.text
    body = r.json()
    # Not asked either way: fitted (COMPLEMENTME_FIT_FRAME_UPLOADS is on by default).
    assert body["frame_fitted"] is True and body["frame"]["up_axis"] == "z"
    assert 0.7 * MM <= body["frame"]["radius"] <= 1.4 * MM
    # Asked not to: read in the canonical frame.
    declined = {"max_parts": 2, "category": "chair", "fit_frame": False}
    r = client.post("/assemble/mesh", files={"file": ("chair.obj", io.BytesIO(data), "text/plain")},
                    data={"options": json.dumps(declined)})
    assert r.status_code == 200, r.text
    assert r.json()["frame_fitted"] is False


@pytest.mark.parametrize("points", [[[1.0, 2.0, 3.0]] * 20])
def test_a_cloud_without_extent_cannot_be_fitted(client: TestClient, points: list) -> None:
    r = client.post("/suggest", json={"points": points, "fit_frame": True})
    assert r.status_code == 422 and r.json()["error"]["code"] == "frame_unfit"


def test_the_category_term_prefers_the_frame_in_which_the_query_looks_like_its_kind() -> None:
    frames = [Frame(radius=1.0), Frame(radius=1.0, up_axis="z")]
    distances = np.array([1.0, 1.2])
    assert most_familiar(frames, distances, 0.8).frame is frames[0]
    probs = np.array([0.01, 0.9])
    fit = most_familiar(frames, distances, 0.8, probs, category_weight=16.0)
    assert fit.frame is frames[1]
    assert fit.scores == pytest.approx([-1.0 + 16.0 * np.log(0.01), -1.2 + 16.0 * np.log(0.9)])
    # Weight 0, or no head: the rule without the term; a probability of 0 is floored, not -inf.
    assert most_familiar(frames, distances, 0.8, probs, category_weight=0.0).frame is frames[0]
    assert most_familiar(frames, distances, 0.8, None, category_weight=16.0).frame is frames[0]
    floored = most_familiar(frames, distances, 0.8, np.array([0.0, 0.0]), category_weight=16.0)
    assert np.isfinite(floored.scores).all() and floored.frame is frames[0]


def test_category_probability_reads_the_named_category_or_the_most_probable() -> None:
    names = ["chair", "lamp", "table"]
    probs = np.array([0.2, 0.7, 0.1])
    assert category_probability(probs, names, ("chair",)) == pytest.approx(0.2)
    assert category_probability(probs, names, ("chair", "table")) == pytest.approx(0.2)
    assert category_probability(probs, names, ()) == pytest.approx(0.7)
    assert category_probability(probs, names, ("boat",)) == pytest.approx(0.7)  # none the head knows
    assert category_probability(None, names, ()) is None
    assert category_probability(probs, names[:2], ()) is None  # not the head's classes


def test_answers_carry_the_category_probability_and_the_choice_reads_it(engine: SuggestionEngine,
                                                                        catalog: Catalog) -> None:
    """The shipped head reads a held-out chair as a chair in its own frame and not lying on its
    back: with the category weight, the upright frame wins even where familiarity alone is close."""
    held_out = split_shapes(catalog, "test")
    rows = next(r for _, r in sorted(held_out.items()) if catalog.records[r[0]]["category"] == "chair")
    pts = np.concatenate([catalog.part_points(i) + catalog.translations[i] for i in rows[1:]])
    frames = [Frame(), Frame(up_axis="z")]
    answers = engine.suggest_batch(scoring_queries(frames, pts, SuggestOptions(categories=("chair",)),
                                                   mixture_only=True))
    probs = category_probabilities_of(answers)
    assert probs is not None and probs[0] > 0.5 > probs[1]
    unnamed = engine.suggest_batch([(pts, SuggestOptions(k=1))])[0]
    assert isinstance(unnamed, SuggestResult) and unnamed.inferred_category is not None
    assert unnamed.category_probability == pytest.approx(unnamed.inferred_category.confidence, abs=1e-6)
    assert choose_frame(frames, answers, 0.8, category_weight=16.0).frame is frames[0]
