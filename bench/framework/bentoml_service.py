"""The framework peer on BentoML: ``bentoml serve bench.framework.bentoml_service:Suggest``.

Written as BentoML's documentation recommends for a model behind its adaptive batching
(guides: Services, Adaptive batching, Distributed Services, Workers):

- ``SuggestModel`` holds the model (loaded in ``__init__``, once per worker) and exposes one
  batchable API: a list of queries in, a list of answers out, ``max_batch_size`` and
  ``max_latency_ms`` set on ``@bentoml.api``. A batchable API takes exactly one parameter, the
  batch, so a request carrying points and k cannot be batched there directly:
- ``Suggest`` is the public Service: ``POST /suggest`` takes the same JSON body as our service
  (``{"points": [[x, y, z], ...], "k": 10}``), checks it, and calls the model Service through
  ``bentoml.depends``; the model Service's dispatcher forms the batches from those calls (the
  documentation's multi-Service batching).

Both Services run one worker process per core (``workers`` from the bench's config). Run by the
bench in the peer's venv, with the repository on ``PYTHONPATH`` and ``FRAMEWORK_PEER_CONFIG``
set (``bench.framework_bench``).
"""

from __future__ import annotations

from typing import Any

import bentoml
from bentoml.exceptions import InvalidArgument

from bench.framework.pipeline import PeerConfig, PeerModel, RequestError, parse_request

CONFIG = PeerConfig.from_env()
# One worker process per core; no access log (our server runs without one in the bench too).
SERVICE = {"workers": CONFIG.workers, "traffic": {"timeout": 60}, "logging": {"access": {"enabled": False}}}


@bentoml.service(**SERVICE)
class SuggestModel:
    """The exported graphs, FAISS index and catalog, answering batches."""

    def __init__(self) -> None:
        self.model = PeerModel(CONFIG)

    @bentoml.api(batchable=True, max_batch_size=CONFIG.max_batch_size,
                 max_latency_ms=int(CONFIG.max_latency_ms))
    def suggest_batch(self, queries: list[dict[str, Any]]) -> list[list[dict[str, Any]]]:
        return self.model.suggest_batch([parse_request(q, CONFIG) for q in queries])


@bentoml.service(**SERVICE)
class Suggest:
    """The public API: one /suggest request, answered through the batching model Service."""

    model = bentoml.depends(SuggestModel)

    @bentoml.api(route="/suggest")
    async def suggest(self, points: list[list[float]], k: int = CONFIG.default_k) -> dict[str, Any]:
        body = {"points": points, "k": k}
        try:
            parse_request(body, CONFIG)  # refuse bad input here (400), before it joins a batch
        except RequestError as exc:
            raise InvalidArgument(str(exc)) from None
        answers = await self.model.to_async.suggest_batch([body])
        return {"suggestions": answers[0]}
