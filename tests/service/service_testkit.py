"""Helpers shared by the service tests: test limits, settings, catalog-built queries, background
threads.

Queries are built from the catalog itself: a catalog shape minus one of its parts
(``assembly_query``), the setting of the paper's retrieval benchmark, so quality assertions
(label of the missing part in the top 5, placement error) can be added on trained artifacts.
"""

from __future__ import annotations

import json
import os
import struct
import threading
from collections.abc import Iterable
from dataclasses import dataclass
from pathlib import Path
from typing import Any

import numpy as np

from service.artifacts.catalog import Catalog
from service.settings import DEFAULT_ARTIFACTS, Settings

ARTIFACTS_ENV = "COMPLEMENTME_TEST_ARTIFACTS"

# Limits of the test app: small enough that the limit tests send small bodies.
TEST_LIMITS = {
    "min_points": 16,
    "max_points": 20_000,
    "max_k": 50,
    "default_k": 10,
    "max_batch_items": 8,
    "max_body_bytes": 1024 * 1024,
    "max_upload_bytes": 2 * 1024 * 1024,
    "max_mesh_vertices": 100_000,
    "max_mesh_faces": 100_000,
    "max_page_size": 100,
    "max_place_parts": 20,
    "max_exclude": 100,
    # The session's one TestClient sends every test's bad requests from one address, faster than a
    # client may get errors: the error budget is off here and tested on its own (test_overload).
    "client_error_burst": 0,
}


def artifacts_folder() -> Path:
    return Path(os.environ.get(ARTIFACTS_ENV) or DEFAULT_ARTIFACTS)


def make_settings(folder: Path, **overrides: object) -> Settings:
    """Settings for a test app: the test limits, explicit so that no environment variable leaks in."""
    values = {"artifacts": folder, "onnx_threads": 1, "faiss_threads": 1, "seed": 0, "warmup": True,
              "verify_checksums": True, **TEST_LIMITS, **overrides}
    return Settings(**values)  # type: ignore[arg-type]


def stop_and_join(stop: threading.Event, threads: Iterable[threading.Thread], timeout: float) -> None:
    """Set ``stop`` (the threads' signal to finish) and join each thread, waiting at most ``timeout``
    seconds for each."""
    stop.set()
    for t in threads:
        t.join(timeout=timeout)


@dataclass
class AssemblyQuery:
    """A catalog shape with one part left out, as points in the canonical frame.

    Shapes:
        points: (n, 3) float32.
        missing_translation: (3,) float32, where the left-out part sits.
    """

    shape_id: str
    points: np.ndarray
    kept: list[str]
    missing: str
    missing_label: str | None
    missing_translation: np.ndarray


def assembly_query(catalog: Catalog, shape_id: str, missing: str, n: int, seed: int = 0) -> AssemblyQuery:
    """Points on every part of ``shape_id`` but ``missing``, area-weighted, from catalog.npz samples.

    Parts are placed with their catalog.json translations; each part gets a share of the ``n``
    points proportional to its area (at least one).
    """
    rows = [i for i, r in enumerate(catalog.records) if r["shape_id"] == shape_id]
    drop = catalog.lookup(missing)
    assert drop in rows, f"{missing} is not a part of {shape_id}"
    kept = [i for i in rows if i != drop]
    assert kept, f"{shape_id} has only one part: nothing is left to query with"
    rng = np.random.default_rng(seed)
    areas = np.array([max(float(catalog.records[i]["area"]), 1e-9) for i in kept])
    counts = np.maximum(1, np.floor(n * areas / areas.sum()).astype(int))
    counts[np.argmax(counts)] += n - counts.sum()
    chunks = []
    for i, c in zip(kept, counts, strict=True):
        pts = catalog.part_points(i)
        pick = rng.choice(len(pts), size=int(c), replace=c > len(pts))
        chunks.append(pts[pick] + catalog.translations[i])
    return AssemblyQuery(shape_id=shape_id, points=np.concatenate(chunks).astype(np.float32),
                         kept=[catalog.part_ids[i] for i in kept], missing=missing,
                         missing_label=catalog.records[drop]["label"],
                         missing_translation=catalog.translations[drop])


def multi_part_shapes(catalog: Catalog, limit: int) -> list[str]:
    """Up to ``limit`` shape ids with at least two parts, spread over the categories."""
    by_cat: dict[str, list[str]] = {}
    counts = np.bincount(catalog.shape_of)
    for i, r in enumerate(catalog.records):
        if counts[catalog.shape_of[i]] >= 2:
            ids = by_cat.setdefault(r["category"], [])
            if r["shape_id"] not in ids:
                ids.append(r["shape_id"])
    out: list[str] = []
    while len(out) < limit and any(by_cat.values()):
        for ids in by_cat.values():
            if ids and len(out) < limit:
                out.append(ids.pop(0))
    return out


# A triangle's three float32 vertices: the binary chunk of the small test glTFs.
TRIANGLE = np.array([[0, 0, 0], [0.2, 0, 0], [0, 0.2, 0]], dtype="<f4").tobytes()


def glb(tree: dict[str, Any], bin_chunk: bytes = b"") -> bytes:
    """A binary glTF from a JSON tree and an optional binary chunk."""
    text = json.dumps(tree, separators=(",", ":")).encode()
    text += b" " * (-len(text) % 4)
    chunks = struct.pack("<II", len(text), 0x4E4F534A) + text
    if bin_chunk:
        bin_chunk += b"\0" * (-len(bin_chunk) % 4)
        chunks += struct.pack("<II", len(bin_chunk), 0x004E4942) + bin_chunk
    return b"glTF" + struct.pack("<II", 2, 12 + len(chunks)) + chunks


def clustered_embeddings(n: int, d: int, seed: int = 0) -> np.ndarray:
    """Embeddings that cluster like real part embeddings do: jittered copies of a few centres.

    Shapes:
        returns (n, d) float32.
    """
    rng = np.random.default_rng(seed)
    centres = rng.standard_normal((max(1, n // 50), d))
    x = centres[rng.integers(len(centres), size=n)] + 0.3 * rng.standard_normal((n, d))
    return x.astype(np.float32)
