"""Endless streams of training triplet batches, optionally sampled in DataLoader workers.

Sampling a batch (about 10 ms for 32 triplets of 512 points) runs in a worker process when
``num_workers > 0`` so it overlaps the optimisation step. Every (seed, rank, worker, start step)
gets its own generator: ranks of a distributed run draw different triplets, and a resumed run
continues with fresh but reproducible draws.
"""

from __future__ import annotations

from collections.abc import Iterator
from typing import Any

import numpy as np
import torch
from torch.utils.data import DataLoader, IterableDataset, get_worker_info

from training.data.processed import ProcessedDataset
from training.data.sampling import TripletSampler


class TripletBatches(IterableDataset):
    """Yields dicts of tensors (``TripletSampler.batch``), forever.

    ``sampler_options`` are the keyword arguments of ``TripletSampler`` beyond the dataset and N.
    """

    def __init__(self, ds: ProcessedDataset, n_points: int, batch_size: int, seed: int, rank: int = 0,
                 start_step: int = 0, sampler_options: dict[str, Any] | None = None):
        super().__init__()
        self.sampler = TripletSampler(ds, n_points=n_points, **(sampler_options or {}))
        self.batch_size = batch_size
        self.seed, self.rank, self.start_step = seed, rank, start_step

    def __iter__(self) -> Iterator[dict[str, torch.Tensor]]:
        info = get_worker_info()
        worker = info.id if info is not None else 0
        rng = np.random.default_rng([self.seed, self.rank, worker, self.start_step])
        while True:
            batch = self.sampler.batch(self.batch_size, rng)
            yield {k: torch.from_numpy(v) for k, v in batch.items()}


def batch_stream(ds: ProcessedDataset, n_points: int, batch_size: int, seed: int, rank: int = 0,
                 start_step: int = 0, num_workers: int = 0,
                 sampler_options: dict[str, Any] | None = None) -> Iterator[dict[str, torch.Tensor]]:
    """An iterator over training batches; ``num_workers`` > 0 samples in background processes."""
    source = TripletBatches(ds, n_points, batch_size, seed, rank, start_step, sampler_options)
    if num_workers == 0:
        return iter(source)
    loader = DataLoader(source, batch_size=None, num_workers=num_workers, prefetch_factor=4,
                        persistent_workers=False)
    return iter(loader)
