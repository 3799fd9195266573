"""Probes and model facts: ``GET /healthz``, ``/readyz``, ``/metrics``, ``/model``."""

from __future__ import annotations

from typing import Any

import numpy as np
from fastapi import APIRouter, Request
from starlette.responses import Response

from service.api.deps import MetricsDep, ServedDep, SettingsDep, served_of
from service.api.errors import error_response
from service.api.metrics import CONTENT_TYPE
from service.api.responses import OrjsonResponse
from service.api.schemas import ErrorResponse, Health, ModelInfo

router = APIRouter(tags=["probes"])

_METRICS_EXAMPLE = """\
# HELP complementme_http_requests_total HTTP requests by method, route and status.
# TYPE complementme_http_requests_total counter
complementme_http_requests_total{method="POST",route="/suggest",status="200"} 1520.0
complementme_catalog_parts 4210.0
"""

LIMIT_SETTINGS = ("min_points", "max_points", "default_k", "max_k", "max_place_parts", "max_exclude",
                  "max_batch_items", "max_body_bytes", "max_upload_bytes", "max_mesh_vertices",
                  "max_mesh_faces", "max_page_size")


@router.get("/healthz", response_model=Health, summary="Liveness: the process answers")
async def get_healthz() -> OrjsonResponse:
    return OrjsonResponse({"status": "ok"})


@router.get("/readyz", response_model=Health, summary="Readiness: artifacts loaded and warm-up passed",
            responses={503: {"model": ErrorResponse, "description": "Not ready (yet)."}})
async def get_readyz(request: Request) -> OrjsonResponse:
    """200 once the artifacts are loaded and warm. With the postgres catalog backend the answer also
    says where the replica is in the database's changes, and `status` is `degraded` (still 200:
    suggestions are served from the last snapshot) while the database cannot be reached."""
    served = served_of(request.app)
    if served is None or not request.app.state.ready:
        return error_response(503, "not_ready", "artifacts not loaded or warm-up not passed")
    body: dict[str, Any] = {"status": "ready", "model_version": served.model_version}
    replication = served.writer.replication() if served.writer is not None else None
    if replication is not None:
        body["catalog"] = replication
        if replication["database"] != "up":
            body["status"] = "degraded"
    return OrjsonResponse(body)


@router.get("/metrics", summary="Prometheus metrics", response_class=Response,
            responses={200: {"content": {CONTENT_TYPE: {"example": _METRICS_EXAMPLE}},
                             "description": "Prometheus text format."}})
async def get_metrics(metrics: MetricsDep) -> Response:
    return Response(metrics.render(), media_type=CONTENT_TYPE)


@router.get("/model", response_model=ModelInfo, summary="The loaded model, its catalog and the limits")
async def get_model(served: ServedDep, settings: SettingsDep) -> OrjsonResponse:
    m, cat = served.engine.artifacts.manifest, served.catalog
    counts = np.bincount(cat.category_of, minlength=len(cat.categories))
    body: dict[str, Any] = {
        "model_version": served.model_version, "format_version": m["format_version"],
        "n_points": m["n_points"], "placement_points": served.engine.artifacts.placement_points,
        "embedding_dim": m["embedding_dim"], "n_modes": m["n_modes"],
        "part_count": len(cat),  # shipped + added parts, as the categories below
        "categories": [{"name": n, "parts": int(c)} for n, c in zip(cat.categories, counts, strict=True)],
        "limits": {name: getattr(settings, name) for name in LIMIT_SETTINGS},
    }
    return OrjsonResponse(body)
