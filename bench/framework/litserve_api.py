"""The framework peer on LitServe: ``python -m bench.framework.litserve_api --port PORT``.

Written as LitServe's documentation recommends for a batched model (LitAPI, LitServer,
Batching): ``setup`` loads the model once per inference worker; ``decode_request`` turns one
request body (the same JSON as our service's: ``{"points": [[x, y, z], ...], "k": 10}``) into a
query; LitServe collects up to ``max_batch_size`` decoded requests, waiting at most
``batch_timeout`` seconds, and hands them to ``predict`` as one batch (``batch`` keeps them a
list: the queries differ in size); ``unbatch`` and ``encode_response`` give each request its
answer. ``workers_per_device`` inference workers on the CPU, one per core, and as many HTTP
server processes (LitServe's default), linked by ZeroMQ (``fast_queue``). Run by the bench in
the peer's venv, with the repository on ``PYTHONPATH`` and ``FRAMEWORK_PEER_CONFIG`` set
(``bench.framework_bench``).
"""

import argparse
from typing import Any

import litserve as ls
from fastapi import HTTPException

from bench.framework.pipeline import PeerConfig, PeerModel, Query, RequestError, parse_request

CONFIG = PeerConfig.from_env()


class SuggestAPI(ls.LitAPI):
    """/suggest: one request's points and k in, its ranked and placed suggestions out."""

    def setup(self, device: str) -> None:
        self.model = PeerModel(CONFIG)

    # LitServe reads this parameter's annotation as the request's type: without one it hands over
    # the JSON body as it came (and this module keeps annotations evaluated: no __future__ import).
    def decode_request(self, request) -> Query:
        try:
            return parse_request(request, CONFIG)
        except RequestError as exc:
            raise HTTPException(status_code=422, detail=str(exc)) from None

    def batch(self, inputs: list[Query]) -> list[Query]:
        return list(inputs)

    def predict(self, queries: list[Query]) -> list[list[dict[str, Any]]]:
        return self.model.suggest_batch(queries)

    def unbatch(self, output: list[list[dict[str, Any]]]) -> list[list[dict[str, Any]]]:
        return list(output)

    def encode_response(self, output: list[dict[str, Any]]) -> dict[str, Any]:
        return {"suggestions": output}


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("--port", type=int, required=True)
    args = parser.parse_args()
    api = SuggestAPI(max_batch_size=CONFIG.max_batch_size, batch_timeout=CONFIG.max_latency_ms / 1000,
                     api_path="/suggest")
    # fast_queue: ZeroMQ between the API servers and the workers, which the documentation
    # recommends past 100 requests per second (the loads here reach several hundred).
    server = ls.LitServer(api, accelerator="cpu", workers_per_device=CONFIG.workers, timeout=60,
                          fast_queue=True)
    # num_api_servers stays LitServe's default: as many HTTP server processes as inference workers.
    server.run(host="127.0.0.1", port=args.port, generate_client_file=False, log_level="warning",
               access_log=False)


if __name__ == "__main__":
    main()
