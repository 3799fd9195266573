"""Benchmark a: one /suggest through the real engine, stage by stage, without HTTP.

Each repetition runs the path of ``service/api/routes/suggest.py:post_suggest`` in process:

- ``parse``: the body's JSON to Python objects, as the suggestion routes' ``request.json()`` does
  (``service/api/batched_route.py``: orjson, the standard library for what orjson refuses);
- ``validate``: ``SuggestRequest`` validation, ``to_points`` (the list or base64 decode) and
  ``to_options``, as FastAPI's body validation and the handler do;
- ``suggest``: ``SuggestionEngine.suggest``, whose own per-stage ``timings`` are recorded too
  (prepare = canonical frame + resample, g, h_query, search, score, h_head, complement, contact,
  total);
- ``serialise``: ``render_suggest`` and orjson, as ``OrjsonResponse`` renders the answer.

``resample`` (canonical frame + resampling to the networks' N points) is also timed on its own,
outside the end-to-end sum, because the engine reports it inside ``prepare``.
"""

from __future__ import annotations

import json
import logging
import time
from collections import defaultdict
from dataclasses import asdict, dataclass
from typing import Any

import orjson

from bench.query import BODY_KINDS, BenchQuery
from bench.stats import summarize_seconds
from service.api.render import render_suggest
from service.api.schemas import SuggestRequest
from service.artifacts.loading import load_served_artifacts
from service.settings import Settings
from service.suggest.engine import SuggestionEngine
from service.suggest.engine_settings import EngineSettings

log = logging.getLogger(__name__)


@dataclass(frozen=True)
class EngineBenchConfig:
    """Settings of the engine benchmark."""

    reps: int = 1000          # timed repetitions per variant
    warmup: int = 50          # untimed repetitions first (caches, allocator, branch predictors)
    max_seconds: float = 90.0  # a variant stops early past this many seconds (its count is recorded)
    bodies: tuple[str, ...] = BODY_KINDS
    # Contact refinement: None = the request does not say (the service's default,
    # COMPLEMENTME_SUGGEST_REFINE_CONTACT), True / False = the request asks for it / not.
    contact: tuple[bool | None, ...] = (None, True)


def load_engine(settings: Settings) -> SuggestionEngine:
    """The engine as the server's lifespan builds it (``service/api/app.py``), without warm-up."""
    return SuggestionEngine(load_served_artifacts(settings), settings)


def parse_body(body: bytes) -> Any:
    """A request body's JSON, parsed as the suggestion routes parse it (orjson, else ``json``)."""
    try:
        return orjson.loads(body)
    except orjson.JSONDecodeError:
        return json.loads(body)


def request_once(engine: SuggestionEngine, body: bytes) -> tuple[dict[str, float], dict[str, float], bytes]:
    """One request through the route's path; returns stage seconds, engine timings and the answer."""
    s = engine.config
    t0 = time.perf_counter()
    obj = parse_body(body)
    t1 = time.perf_counter()
    req = SuggestRequest.model_validate(obj)
    points = req.to_points(s.max_points)
    options = req.to_options()
    t2 = time.perf_counter()
    result = engine.suggest(points, options)
    t3 = time.perf_counter()
    answer = orjson.dumps(render_suggest(result, engine.model_version), option=orjson.OPT_SERIALIZE_NUMPY)
    t4 = time.perf_counter()
    engine.resample(engine.canonical(points, options.frame))
    t5 = time.perf_counter()
    stages = {"parse": t1 - t0, "validate": t2 - t1, "suggest": t3 - t2, "serialise": t4 - t3,
              "end_to_end": t4 - t0, "resample": t5 - t4}
    return stages, dict(result.timings), answer


def run_variant(engine: SuggestionEngine, body: bytes, reps: int, warmup: int,
                max_seconds: float = float("inf")) -> dict[str, Any]:
    """Per-stage summaries (ms) over ``reps`` requests (fewer past ``max_seconds``), after ``warmup``."""
    for _ in range(warmup):
        request_once(engine, body)
    stages: dict[str, list[float]] = defaultdict(list)
    timings: dict[str, list[float]] = defaultdict(list)
    answer = b""
    deadline = time.perf_counter() + max_seconds
    for _ in range(reps):
        if time.perf_counter() > deadline:
            break
        st, tm, answer = request_once(engine, body)
        for key, value in st.items():
            stages[key].append(value)
        for key, value in tm.items():
            timings[key].append(value)
    top = orjson.loads(answer)["suggestions"]
    return {
        "stages": {k: summarize_seconds(v) for k, v in stages.items()},
        "engine_timings": {k: summarize_seconds(v) for k, v in timings.items()},
        "body_bytes": len(body),
        "answer_bytes": len(answer),
        "suggestions": len(top),
        "top_part": top[0]["part_id"] if top else None,
    }


def run_engine_bench(engine: SuggestionEngine, settings: Settings, query: BenchQuery, cfg: EngineBenchConfig
                     ) -> dict[str, Any]:
    """Every (body kind, contact refinement) variant; ``refine_contact`` None is the default request."""
    variants = []
    default = contact_default(engine.config)
    for kind in cfg.bodies:
        for contact in cfg.contact:
            log.info("engine: %s body, refine_contact %s, %d reps", kind, contact, cfg.reps)
            body = query.body(kind) if contact is None else query.body(kind, refine_contact=contact)
            res = run_variant(engine, body, cfg.reps, cfg.warmup, cfg.max_seconds)
            variants.append({"body": kind, "refine_contact": contact,
                             "contact_applied": default if contact is None else contact, **res})
    return {
        "query": {"source": query.source, "points": len(query.points), "k": query.k},
        "network_points": engine.artifacts.n_points,
        "placement_points": engine.artifacts.placement_points,
        "catalog_parts": len(engine.catalog),
        "index": type(engine.index).__name__,
        "settings": _timing_settings(settings),
        "variants": variants,
    }


def contact_default(s: EngineSettings) -> bool:
    """Whether /suggest refines contact when a request does not say (the service's setting)."""
    return s.suggest_refine_contact


def _timing_settings(s: Settings) -> dict[str, Any]:
    """The settings that change the timings (recorded with the results)."""
    keys = ("onnx_threads", "faiss_threads", "faiss_blas_threshold", "max_points_per_run",
            "neighbours_per_mode", "suggest_refine_contact", "contact_search_points", "contact_part_samples",
            "contact_cache_parts")
    data = s.model_dump()
    return {k: data[k] for k in keys if k in data}


def config_dict(cfg: EngineBenchConfig) -> dict[str, Any]:
    d = asdict(cfg)
    d["bodies"] = list(cfg.bodies)
    d["contact"] = list(cfg.contact)
    return d
