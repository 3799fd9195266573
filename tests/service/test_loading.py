"""A bad artifact folder is refused at start with an error naming the bad file.

Each test builds a faulty copy of the real folder: every file a symlink to the original except
the one being broken, and (where the fault is not a checksum mismatch) a manifest rewritten
with fresh checksums so that the deeper check is the one that fires.
"""

from __future__ import annotations

import json
import os
import shutil
import subprocess
import sys
from collections.abc import Callable
from pathlib import Path

import faiss
import numpy as np
import pytest
from fastapi.testclient import TestClient
from service_testkit import make_settings

from service.api.app import create_app
from service.artifacts.layout import ArtifactError, read_manifest, write_manifest
from service.artifacts.loading import load_artifacts

REPO = Path(__file__).resolve().parents[2]


def faulty_copy(src: Path, dst: Path, break_it: Callable[[Path], None],
                rewrite_manifest: bool = True) -> Path:
    dst.mkdir()
    for f in src.iterdir():
        (dst / f.name).symlink_to(f.resolve())
    break_it(dst)
    if rewrite_manifest:
        manifest = read_manifest(src, verify_checksums=False)
        write_manifest(dst, {k: v for k, v in manifest.items() if k not in ("files", "format_version")})
    return dst


def replace(folder: Path, name: str, data: bytes) -> None:
    (folder / name).unlink()
    (folder / name).write_bytes(data)


def load_npz(path: Path) -> dict[str, np.ndarray]:
    with np.load(path, allow_pickle=False) as d:
        return {k: d[k] for k in d.files}


def save_npz(folder: Path, arrays: dict[str, np.ndarray]) -> None:
    (folder / "catalog.npz").unlink()
    np.savez(folder / "catalog.npz", **arrays)


def edit_catalog_json(folder: Path, edit: Callable[[list], object]) -> None:
    records = json.loads((folder / "catalog.json").read_text())
    parts = records["parts"] if isinstance(records, dict) else records
    edit(parts)
    (folder / "catalog.json").unlink()
    (folder / "catalog.json").write_text(json.dumps(records))


def refused(folder: Path, *names: str) -> str:
    with pytest.raises(ArtifactError) as info:
        load_artifacts(folder)
    message = str(info.value)
    for name in names:
        assert name in message, message
    return message


def test_the_real_folder_loads(artifacts: Path) -> None:
    a = load_artifacts(artifacts)
    assert len(a.catalog) == a.manifest["part_count"] == a.index.ntotal


def test_missing_folder_and_manifest(tmp_path: Path, artifacts: Path) -> None:
    refused(tmp_path / "nowhere", str(tmp_path / "nowhere"))
    folder = faulty_copy(artifacts, tmp_path / "a", lambda d: (d / "manifest.json").unlink(), False)
    refused(folder, str(folder / "manifest.json"))


def test_manifest_not_json_or_unknown_version(tmp_path: Path, artifacts: Path) -> None:
    folder = faulty_copy(artifacts, tmp_path / "a", lambda d: replace(d, "manifest.json", b"{nope"), False)
    refused(folder, "manifest.json", "not valid JSON")
    manifest = json.loads((artifacts / "manifest.json").read_text())
    bumped = json.dumps({**manifest, "format_version": 999}).encode()
    folder = faulty_copy(artifacts, tmp_path / "b", lambda d: replace(d, "manifest.json", bumped), False)
    refused(folder, "manifest.json", "999")


def test_missing_file(tmp_path: Path, artifacts: Path) -> None:
    folder = faulty_copy(artifacts, tmp_path / "a", lambda d: (d / "h_head.onnx").unlink(), False)
    refused(folder, str(folder / "h_head.onnx"), "missing")


def test_checksum_mismatch(tmp_path: Path, artifacts: Path) -> None:
    data = bytearray((artifacts / "g.onnx").read_bytes())
    data[-1] ^= 0xFF
    folder = faulty_copy(artifacts, tmp_path / "a", lambda d: replace(d, "g.onnx", bytes(data)), False)
    refused(folder, str(folder / "g.onnx"), "checksum")


def test_graph_with_other_names(tmp_path: Path, artifacts: Path) -> None:
    # f's graph where g should be: outputs "embedding" instead of weights, means, sigmas.
    folder = faulty_copy(artifacts, tmp_path / "a",
                         lambda d: replace(d, "g.onnx", (artifacts / "f.onnx").read_bytes()))
    refused(folder, str(folder / "g.onnx"), "outputs", "embedding")


def test_graph_that_is_not_onnx(tmp_path: Path, artifacts: Path) -> None:
    folder = faulty_copy(artifacts, tmp_path / "a", lambda d: replace(d, "h_query.onnx", b"not a graph"))
    refused(folder, str(folder / "h_query.onnx"))


def test_mode_count_disagrees_with_the_graph(tmp_path: Path, artifacts: Path) -> None:
    manifest = json.loads((artifacts / "manifest.json").read_text())

    def bump(d: Path) -> None:
        replace(d, "manifest.json", json.dumps({**manifest, "n_modes": manifest["n_modes"] + 1}).encode())

    folder = faulty_copy(artifacts, tmp_path / "a", bump, False)
    refused(folder, str(folder / "g.onnx"))


def test_index_with_the_wrong_count_or_truncated(tmp_path: Path, artifacts: Path) -> None:
    emb = load_npz(artifacts / "catalog.npz")["embeddings"]

    def short_index(d: Path) -> None:
        index = faiss.IndexFlatL2(emb.shape[1])
        index.add(emb[:-1])
        (d / "index.faiss").unlink()
        faiss.write_index(index, str(d / "index.faiss"))

    folder = faulty_copy(artifacts, tmp_path / "a", short_index)
    refused(folder, str(folder / "index.faiss"), "part_count")
    data = (artifacts / "index.faiss").read_bytes()
    half = data[: len(data) // 2]
    folder = faulty_copy(artifacts, tmp_path / "b", lambda d: replace(d, "index.faiss", half))
    refused(folder, str(folder / "index.faiss"))


def test_catalog_json_faults(tmp_path: Path, artifacts: Path) -> None:
    folder = faulty_copy(artifacts, tmp_path / "a",
                         lambda d: edit_catalog_json(d, lambda parts: parts[3].pop("translation")))
    refused(folder, str(folder / "catalog.json"), "record 3", "translation")
    folder = faulty_copy(artifacts, tmp_path / "b", lambda d: edit_catalog_json(d, lambda parts: parts.pop()))
    refused(folder, str(folder / "catalog.json"), "part_count")

    def cycle(parts: list) -> None:
        parts[0]["duplicate_of"], parts[1]["duplicate_of"] = 1, 0

    folder = faulty_copy(artifacts, tmp_path / "c", lambda d: edit_catalog_json(d, cycle))
    refused(folder, str(folder / "catalog.json"), "cycle")
    folder = faulty_copy(artifacts, tmp_path / "d", lambda d: replace(d, "catalog.json", b"[{]"))
    refused(folder, str(folder / "catalog.json"))


def test_catalog_npz_faults(tmp_path: Path, artifacts: Path) -> None:
    arrays = load_npz(artifacts / "catalog.npz")

    def wrong_dim(d: Path) -> None:
        save_npz(d, {**arrays, "embeddings": arrays["embeddings"][:, :-1]})

    folder = faulty_copy(artifacts, tmp_path / "a", wrong_dim)
    refused(folder, str(folder / "catalog.npz"), "embeddings")

    def bad_faces(d: Path) -> None:
        faces = arrays["mesh_faces"].copy()
        faces[0, 0] = np.iinfo(faces.dtype).max  # past the part's vertices (faces may be uint16)
        save_npz(d, {**arrays, "mesh_faces": faces})

    folder = faulty_copy(artifacts, tmp_path / "b", bad_faces)
    refused(folder, str(folder / "catalog.npz"), "mesh_faces")

    def missing_array(d: Path) -> None:
        save_npz(d, {k: v for k, v in arrays.items() if k != "part_features"})

    folder = faulty_copy(artifacts, tmp_path / "c", missing_array)
    refused(folder, str(folder / "catalog.npz"), "part_features")

    def nan_embedding(d: Path) -> None:
        emb = arrays["embeddings"].copy()
        emb[2, 1] = np.nan
        save_npz(d, {**arrays, "embeddings": emb})

    folder = faulty_copy(artifacts, tmp_path / "d", nan_embedding)
    refused(folder, str(folder / "catalog.npz"), "NaN")


def test_the_app_refuses_to_start(tmp_path: Path, artifacts: Path) -> None:
    folder = faulty_copy(artifacts, tmp_path / "a", lambda d: replace(d, "g.onnx", b"broken"))
    app = create_app(make_settings(folder))
    with pytest.raises(ArtifactError, match=str(folder / "g.onnx")), TestClient(app):
        pass


def test_serve_exits_naming_the_bad_file(tmp_path: Path, artifacts: Path) -> None:
    folder = faulty_copy(artifacts, tmp_path / "a", lambda d: (d / "index.faiss").unlink(), False)
    env = {**os.environ, "PYTHONPATH": str(REPO), "COMPLEMENTME_PORT": "0"}
    result = subprocess.run([sys.executable, "-m", "training", "serve", "--artifacts", str(folder)],
                            cwd=REPO, env=env, capture_output=True, text=True, timeout=120)
    assert result.returncode != 0
    assert "refusing to start" in result.stderr and str(folder / "index.faiss") in result.stderr


def test_copying_keeps_a_loadable_folder(tmp_path: Path, artifacts: Path) -> None:
    # The fault helper itself must not break anything: an unmodified copy loads.
    folder = faulty_copy(artifacts, tmp_path / "a", lambda d: None)
    assert load_artifacts(folder).model_version == read_manifest(artifacts, False)["model_version"]
    shutil.rmtree(folder)


def test_familiarity_bank_faults(tmp_path: Path, artifacts: Path) -> None:
    """The manifest names the bank: missing, unreadable, the wrong width or a bad threshold refuse
    the folder, naming the file."""
    assert read_manifest(artifacts).get("familiarity"), "the shipped folder has a familiarity bank"
    bank = load_npz(artifacts / "familiarity.npz")

    def save_bank(d: Path, arrays: dict[str, np.ndarray]) -> None:
        (d / "familiarity.npz").unlink()
        np.savez(d / "familiarity.npz", **arrays)

    folder = faulty_copy(artifacts, tmp_path / "a", lambda d: (d / "familiarity.npz").unlink(),
                         rewrite_manifest=False)
    refused(folder, str(folder / "familiarity.npz"))
    folder = faulty_copy(artifacts, tmp_path / "b", lambda d: replace(d, "familiarity.npz", b"not a zip"))
    refused(folder, str(folder / "familiarity.npz"))
    folder = faulty_copy(artifacts, tmp_path / "c",
                         lambda d: save_bank(d, {**bank, "descriptors": bank["descriptors"][:, :-1]}))
    refused(folder, str(folder / "familiarity.npz"), "shape")
    folder = faulty_copy(artifacts, tmp_path / "f",
                         lambda d: save_bank(d, {**bank, "components": bank["components"][:, :-1]}))
    refused(folder, str(folder / "familiarity.npz"), "shape")
    folder = faulty_copy(artifacts, tmp_path / "d",
                         lambda d: save_bank(d, {k: v for k, v in bank.items() if k != "mean"}))
    refused(folder, str(folder / "familiarity.npz"))

    def bad_threshold(d: Path) -> None:
        manifest = json.loads((artifacts / "manifest.json").read_text())
        manifest["familiarity"]["threshold"] = -1.0
        replace(d, "manifest.json", json.dumps(manifest).encode())
        write_manifest(d, {k: v for k, v in manifest.items() if k not in ("files", "format_version")})

    folder = faulty_copy(artifacts, tmp_path / "e", bad_threshold, rewrite_manifest=False)
    refused(folder, str(folder / "familiarity.npz"), "threshold")


def test_an_export_without_a_familiarity_bank_still_loads(tmp_path: Path, artifacts: Path) -> None:
    """Exports made before the bank load and serve without the check."""

    def drop(d: Path) -> None:
        (d / "familiarity.npz").unlink()
        manifest = read_manifest(artifacts, verify_checksums=False)
        replace(d, "manifest.json", b"{}")
        dropped = ("files", "format_version", "familiarity")
        write_manifest(d, {k: v for k, v in manifest.items() if k not in dropped})

    folder = faulty_copy(artifacts, tmp_path / "a", drop, rewrite_manifest=False)
    assert load_artifacts(folder).familiarity is None
