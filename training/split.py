"""The train/test split by shape, per category, seeded and saved in the run folder.

Training, validation, evaluation and export must agree on which shapes were held out, so the
split is computed once per run and read back from ``split.json`` afterwards.
"""

from __future__ import annotations

import json
from dataclasses import dataclass
from pathlib import Path

import numpy as np

from service.artifacts.layout import write_json_atomic
from training.data.processed import ProcessedDataset

SPLIT_FILE = "split.json"


@dataclass
class Split:
    """Shape indices of the train and test halves (sorted), plus how they were drawn."""

    train: np.ndarray
    test: np.ndarray
    seed: int
    test_fraction: float
    dataset_hash: str

    def split_of_shape(self, n_shapes: int) -> list[str]:
        """``"train"`` or ``"test"`` for every shape index."""
        out = ["train"] * n_shapes
        for s in self.test.tolist():
            out[s] = "test"
        return out


def make_split(ds: ProcessedDataset, test_fraction: float, seed: int, by_style: bool = False) -> Split:
    """Hold out ``round(test_fraction * n)`` shapes of each category (at least one when n >= 2).

    Shapes are shuffled per category with ``np.random.default_rng(seed)``, in sorted category
    order, so the same dataset and seed always give the same split.

    ``by_style`` holds out every shape of one style per category instead (the style drawn with
    the same generator): the leave-one-style-out benchmark. Styles are read here, to measure,
    and nowhere in training.
    """
    if by_style:
        return _style_split(ds, test_fraction, seed)
    rng = np.random.default_rng(seed)
    by_cat: dict[str, list[int]] = {}
    for s, meta in enumerate(ds.shapes):
        by_cat.setdefault(str(meta.get("category")), []).append(s)
    train: list[int] = []
    test: list[int] = []
    for cat in sorted(by_cat):
        members = np.asarray(by_cat[cat])
        rng.shuffle(members)
        # At least one test shape when there are two or more, never the whole category.
        n = len(members)
        n_test = min(max(round(test_fraction * n), 1), n - 1) if n >= 2 else 0
        test += members[:n_test].tolist()
        train += members[n_test:].tolist()
    return Split(train=np.asarray(sorted(train), np.int64), test=np.asarray(sorted(test), np.int64),
                 seed=seed, test_fraction=test_fraction,
                 dataset_hash=ds.info.get("hash") or ds.content_hash())


def _style_split(ds: ProcessedDataset, test_fraction: float, seed: int) -> Split:
    rng = np.random.default_rng(seed)
    by_cat: dict[str, dict[str, list[int]]] = {}
    for s, meta in enumerate(ds.shapes):
        by_cat.setdefault(str(meta.get("category")), {}).setdefault(str(meta.get("style")), []).append(s)
    train: list[int] = []
    test: list[int] = []
    for cat in sorted(by_cat):
        styles = sorted(by_cat[cat])
        held = styles[int(rng.integers(len(styles)))] if len(styles) >= 2 else None
        for style in styles:
            (test if style == held else train).extend(by_cat[cat][style])
    return Split(train=np.asarray(sorted(train), np.int64), test=np.asarray(sorted(test), np.int64),
                 seed=seed, test_fraction=test_fraction,
                 dataset_hash=ds.info.get("hash") or ds.content_hash())


def save_split(split: Split, ds: ProcessedDataset, folder: Path) -> Path:
    """Write ``split.json`` (shape ids and indices) into a run folder."""
    path = Path(folder) / SPLIT_FILE
    write_json_atomic(path, {
        "seed": split.seed, "test_fraction": split.test_fraction, "dataset_hash": split.dataset_hash,
        "train": split.train.tolist(), "test": split.test.tolist(),
        "train_ids": [ds.shapes[s]["shape_id"] for s in split.train.tolist()],
        "test_ids": [ds.shapes[s]["shape_id"] for s in split.test.tolist()],
    })
    return path


def load_split(folder: Path, ds: ProcessedDataset | None = None) -> Split:
    """Read ``split.json``; with ``ds``, check it was made for that dataset (by shape ids)."""
    path = Path(folder) / SPLIT_FILE
    if not path.is_file():
        raise FileNotFoundError(f"split file missing: {path} (written by `complementme train`)")
    try:
        data = json.loads(path.read_text())
        split = Split(train=np.asarray(data["train"], np.int64), test=np.asarray(data["test"], np.int64),
                      seed=int(data["seed"]), test_fraction=float(data["test_fraction"]),
                      dataset_hash=str(data["dataset_hash"]))
    except (json.JSONDecodeError, KeyError, TypeError, ValueError) as exc:
        raise ValueError(f"{path}: not a valid split file ({exc})") from exc
    if ds is not None:
        ids = [s["shape_id"] for s in ds.shapes]
        n = len(ids)
        for name, idx, want in (("train", split.train, data.get("train_ids")),
                                ("test", split.test, data.get("test_ids"))):
            if len(idx) and (idx.min() < 0 or idx.max() >= n):
                raise ValueError(f"{path}: {name} shape index out of range for a dataset of {n} shapes")
            if want is not None and [ids[s] for s in idx.tolist()] != want:
                raise ValueError(f"{path}: {name} shape ids do not match the dataset (was it re-generated?)")
    return split


def subset_components(ds: ProcessedDataset, shapes: np.ndarray) -> np.ndarray:
    """Global component indices of the given shapes, in the order ``ds.subset(shapes)`` uses.

    Row i of ``ds.subset(shapes)`` is component ``subset_components(ds, shapes)[i]`` of ``ds``.
    """
    if len(shapes) == 0:
        return np.zeros(0, np.int64)
    return np.concatenate([ds.components_of(int(s)) for s in shapes]).astype(np.int64)
