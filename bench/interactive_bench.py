"""Benchmark e: the interactive paths a designer waits on, one request at a time (issue 20, item 2).

Against our service on the shipped artifacts, started as the HTTP benchmark starts it (one
``complementme serve`` per usable core behind HAProxy), at concurrency 1, each path is requested
``requests`` times after ``warmup`` untimed requests, and the client's wall time per request is
summarised (count, p50, p99):

- ``suggest_mesh_glb`` / ``suggest_mesh_obj``: ``/suggest/mesh`` with one ~100k-triangle mesh,
  as GLB and as OBJ (k = 10) in a multipart form, read in the frame it is in (``fit_frame``
  false: the caller knows it, as the page's own parts are);
- ``suggest_mesh_glb_body`` / ``suggest_mesh_obj_body``: the same meshes sent as the request body
  (``Content-Type: model/gltf-binary`` / ``model/obj``, the options in the query string), as the
  project's clients send them (``service.api.mesh_upload``);
- ``suggest_mesh_glb_fit``: the GLB sent as a designer's file is, without a frame, so the service
  fits one (``COMPLEMENTME_FIT_FRAME_UPLOADS``, on by default; ``service.suggest.frame_fit``);
- ``place_5``: ``/place`` of five parts (the first five suggestions of the query) next to the
  benchmark query's points;
- ``suggest_contact_off`` / ``suggest_contact_on``: ``/suggest`` of the benchmark query (1000
  points, k = 10) with ``refine_contact`` false and true;
- ``assemble``: ``/assemble`` of a whole object from one catalog part (greedy, default settings).

What each stage costs comes from what the service reports: for every path the differences of
its ``/metrics`` histograms over that path's requests (the route's server-side duration, the
networks, the search, the scoring, the micro-batcher's queue wait), ``/assemble``'s own
``timings`` in its answers, and for the uploads the service's own parse and sampling functions
(``service.geometry``) timed in this process on the same bytes. The engine's contact stage is not
in ``/metrics``, so the two ``/suggest`` variants are also run through the engine in this process
(``bench.engine_bench.request_once``), whose ``timings`` name it.

The mesh is made at run time, deterministically: the parts of one catalog shape but its last, at
their places, with the largest triangles split until it has about ``target_faces`` faces (no
download, nothing large committed).
"""

from __future__ import annotations

import json
import logging
import os
import time
from collections import defaultdict
from collections.abc import Callable, Sequence
from dataclasses import dataclass, field
from pathlib import Path
from typing import Any

import httpx
import numpy as np
import trimesh

from bench.http_bench import DEFAULT_SERVER_ENV, our_service
from bench.machine import usable_cores
from bench.query import BenchQuery
from bench.stats import summarize_seconds
from service.artifacts.catalog import Catalog

log = logging.getLogger(__name__)

PATHS = ("suggest_mesh_glb", "suggest_mesh_obj", "suggest_mesh_glb_body", "suggest_mesh_obj_body",
         "suggest_mesh_glb_fit", "place_5", "suggest_contact_off", "suggest_contact_on", "assemble")
METRIC_PREFIX = "complementme_"
# Requests that are not the timed path's: the snapshots' own, and HAProxy's health checks.
PROBE_ROUTES = ("/metrics", "/readyz", "/healthz")


@dataclass(frozen=True)
class InteractiveBenchConfig:
    """Settings of the interactive-paths benchmark."""

    requests: int = 20          # timed requests per path
    warmup: int = 2             # untimed requests per path first
    parse_reps: int = 5         # in-process parse + sample repetitions per mesh format
    target_faces: int = 100_000
    place_parts: int = 5
    k: int = 10
    timeout: float = 120.0      # seconds before one request counts as failed
    processes: int = field(default_factory=usable_cores)  # server processes, behind HAProxy if several
    server_env: tuple[tuple[str, str], ...] = tuple(DEFAULT_SERVER_ENV.items())

    def as_dict(self) -> dict[str, Any]:
        return {"requests": self.requests, "warmup": self.warmup, "parse_reps": self.parse_reps,
                "target_faces": self.target_faces, "place_parts": self.place_parts, "k": self.k,
                "timeout": self.timeout, "processes": self.processes, "server_env": dict(self.server_env)}


# --- the query mesh ------------------------------------------------------------------------------

def query_shape(catalog: Catalog, category: str = "chair", min_parts: int = 3) -> list[int]:
    """Catalog rows of the first shape (by id) of ``category`` with at least ``min_parts`` parts."""
    by_shape: dict[str, list[int]] = defaultdict(list)
    for i, rec in enumerate(catalog.records):
        if rec.get("category") == category:
            by_shape[rec["shape_id"]].append(i)
    for shape in sorted(by_shape):
        if len(by_shape[shape]) >= min_parts:
            return by_shape[shape]
    raise ValueError(f"the catalog has no {category} shape with at least {min_parts} parts")


def category_starts(catalog: Catalog) -> dict[str, str]:
    """A start part per category: the first part of its first shape (by id) with two or more."""
    return {cat: catalog.part_ids[query_shape(catalog, cat, 2)[0]] for cat in catalog.categories}


def time_first_assembles(client: httpx.Client, starts: dict[str, str]) -> dict[str, Any]:
    """One ``/assemble`` per category, each the server's first of that category: what a designer's
    first auto-complete after a start costs (the per-category data the assembly reads is made by
    the server's warm-up; without it this paid 13-80 ms more a category). Wall ms per category."""
    out: dict[str, float] = {}
    for cat, part in starts.items():
        t0 = time.perf_counter()
        r = client.post("/assemble", content=json.dumps({"part_id": part}).encode(),
                        headers={"Content-Type": "application/json"})
        ms = (time.perf_counter() - t0) * 1000
        if r.status_code != 200:
            raise RuntimeError(f"POST /assemble from {part} answered {r.status_code}: {r.text[:300]}")
        out[cat] = round(ms, 2)
    return {"starts": starts, "ms": out}


def refine_to_faces(vertices: np.ndarray, faces: np.ndarray, target: int) -> tuple[np.ndarray, np.ndarray]:
    """Split the largest triangles (each into four) until the mesh has at least ``target`` faces.

    Deterministic (stable sort by area). Splitting only some triangles leaves T-junctions, which
    do not matter for surface sampling. Each split adds three faces, so the count overshoots
    ``target`` by at most two.

    Shapes:
        vertices (V, 3), faces (F, 3) -> (V', 3) float64, (F', 3) int64 with F' >= target.
    """
    v = np.asarray(vertices, dtype=np.float64)
    f = np.asarray(faces, dtype=np.int64)
    while len(f) < target:
        need = -(-(target - len(f)) // 3)
        areas = np.linalg.norm(np.cross(v[f[:, 1]] - v[f[:, 0]], v[f[:, 2]] - v[f[:, 0]]), axis=1)
        chosen = np.argsort(-areas, kind="stable")[:min(need, len(f))]
        v, f = trimesh.remesh.subdivide(v, f, face_index=np.sort(chosen))
        f = np.asarray(f, dtype=np.int64)
    return v, f


def query_mesh(catalog: Catalog, target_faces: int) -> tuple[trimesh.Trimesh, dict[str, Any]]:
    """One shape's parts but its last, at their places, refined to about ``target_faces`` faces."""
    rows = query_shape(catalog)[:-1]
    verts, faces, offset = [], [], 0
    for i in rows:
        v, f = catalog.mesh(i)
        verts.append(np.asarray(v, np.float64) + np.asarray(catalog.records[i]["translation"], np.float64))
        faces.append(np.asarray(f, np.int64) + offset)
        offset += len(v)
    v, f = refine_to_faces(np.concatenate(verts), np.concatenate(faces), target_faces)
    mesh = trimesh.Trimesh(vertices=v, faces=f, process=False)
    info = {"shape_id": catalog.records[rows[0]]["shape_id"], "parts": [catalog.part_ids[i] for i in rows],
            "vertices": len(v), "faces": len(f)}
    return mesh, info


def mesh_files(mesh: trimesh.Trimesh, folder: Path) -> dict[str, bytes]:
    """The mesh as GLB and OBJ bytes (also written to ``folder`` to look at)."""
    folder.mkdir(parents=True, exist_ok=True)
    glb = mesh.export(file_type="glb")
    obj = mesh.export(file_type="obj", include_normals=False)
    assert isinstance(glb, bytes) and isinstance(obj, str), (type(glb), type(obj))
    out = {"glb": glb, "obj": obj.encode()}
    for fmt, data in out.items():
        (folder / f"interactive-query.{fmt}").write_bytes(data)
    return out


# --- in-process stages -----------------------------------------------------------------------------

def time_mesh_stages(data: bytes, fmt: str, reps: int, settings: Any, n: int) -> dict[str, Any]:
    """Parse and sample ``data`` with the service's own functions, as ``MeshUploads.sample`` does.

    ``parse``: ``load_mesh_surface`` with the settings' limits (the triangles' areas included);
    ``sample``: ``sample_surface``; ``collect``: the full garbage collection ``MeshUploads.sample``
    runs after an upload over ``MeshUploads.COLLECT_BYTES``; ``upload_sample``: the whole
    ``MeshUploads.sample``. The collection's cost depends on how many objects it walks: the server
    freezes what it loaded at start-up (``gc.freeze`` in ``service.api.app``), and so does this
    process first (unfrozen, the bench's engine made it 130 ms; frozen, 0.1 ms in a bare process
    after one upload, and 5-50 ms measured in a serving process, which holds more young objects).
    """
    import gc

    from service.geometry.inputs import MeshUploads
    from service.geometry.mesh import load_mesh_surface, sample_surface

    gc.collect()
    gc.freeze()

    uploads = MeshUploads(settings)
    stages: dict[str, list[float]] = {"parse": [], "sample": [], "collect": [], "upload_sample": []}
    for _ in range(reps):
        t0 = time.perf_counter()
        mesh = load_mesh_surface(data, fmt, name=f"query.{fmt}", max_vertices=settings.max_mesh_vertices,
                                 max_faces=settings.max_mesh_faces, ignore_obj_materials=True,
                                 max_nodes=settings.max_mesh_nodes, max_nesting=settings.max_mesh_nesting)
        t1 = time.perf_counter()
        sample_surface(mesh.vertices, mesh.faces, n, settings.seed, areas=mesh.areas)
        t2 = time.perf_counter()
        del mesh
        gc.collect()
        t3 = time.perf_counter()
        uploads.sample(data, fmt, n=n, name=f"query.{fmt}")
        t4 = time.perf_counter()
        stages["parse"].append(t1 - t0)
        stages["sample"].append(t2 - t1)
        stages["collect"].append(t3 - t2)
        stages["upload_sample"].append(t4 - t3)
    return {k: summarize_seconds(v) for k, v in stages.items()}


def time_engine_contact(engine: Any, bodies: dict[str, bytes], reps: int, warmup: int) -> dict[str, Any]:
    """The /suggest variants through the engine in process: its ``timings`` per stage (ms summaries)."""
    from bench.engine_bench import request_once

    out = {}
    for name, body in bodies.items():
        for _ in range(warmup):
            request_once(engine, body)
        timings: dict[str, list[float]] = defaultdict(list)
        for _ in range(reps):
            stages, engine_timings, _ = request_once(engine, body)
            timings["suggest (wall)"].append(stages["suggest"])
            for k, v in engine_timings.items():
                timings[k].append(v)
        out[name] = {k: summarize_seconds(v) for k, v in timings.items()}
    return out


# --- server-side metrics -----------------------------------------------------------------------------

def histogram_totals(text: str, prefix: str = METRIC_PREFIX) -> dict[str, float]:
    """``_sum`` and ``_count`` samples of the service's histograms in Prometheus text, by name and
    labels (``name{label=value,...}``; a ``pid`` label is left out and its samples summed)."""
    from prometheus_client.parser import text_string_to_metric_families

    out: dict[str, float] = {}
    for family in text_string_to_metric_families(text):
        for s in family.samples:
            if s.name.startswith(prefix) and s.name.endswith(("_sum", "_count")):
                labels = ",".join(f"{k}={v}" for k, v in sorted(s.labels.items()) if k != "pid")
                key = f"{s.name}{{{labels}}}" if labels else s.name
                out[key] = out.get(key, 0.0) + float(s.value)
    return out


def _probe(key: str) -> bool:
    return any(f"route={route}" in key for route in PROBE_ROUTES)


def histogram_means(before: dict[str, float], after: dict[str, float]) -> dict[str, dict[str, float]]:
    """Per histogram (and labels) observed between two snapshots: count and mean (ms for seconds)."""
    out: dict[str, dict[str, float]] = {}
    for key, total in after.items():
        name, _, labels = key.partition("{")
        if not name.endswith("_count"):
            continue
        base = name[: -len("_count")]
        count = total - before.get(key, 0.0)
        if count <= 0 or _probe(labels):  # the snapshots' own requests, health checks
            continue
        sum_key = base + "_sum" + ("{" + labels if labels else "")
        dsum = after.get(sum_key, 0.0) - before.get(sum_key, 0.0)
        mean = dsum / count
        short = base[len(METRIC_PREFIX):].removesuffix("_seconds").removesuffix("_duration")
        label = ("{" + labels) if labels else ""
        if base.endswith("_seconds"):
            out[short + label] = {"count": count, "mean_ms": mean * 1000}
        else:
            out[short + label] = {"count": count, "mean": mean}
    return out


def metric_snapshot(client: httpx.Client, metrics_urls: Sequence[str], settle: float = 0.05, tries: int = 40
                    ) -> dict[str, float]:
    """The service's histogram totals, summed over its server processes' ``metrics_urls``, once they
    stop changing (the probes' routes left out: the scrapes' own, HAProxy's health checks).

    The server records a request's duration after its answer has gone out: a snapshot taken right
    after the last answer can miss it (seen: the warm-up request counted among the timed ones). So
    the scrape is repeated until two in a row agree (at most ``tries`` times, ``settle`` seconds apart).
    """
    def scrape() -> dict[str, float]:
        out: dict[str, float] = {}
        for url in metrics_urls:
            r = client.get(url, timeout=30.0)
            totals = histogram_totals(r.text) if r.status_code == 200 else {}
            for k, v in totals.items():
                if not _probe(k):
                    out[k] = out.get(k, 0.0) + v
        return out

    last = scrape()
    for _ in range(tries):
        time.sleep(settle)
        now = scrape()
        if now == last:
            break
        last = now
    return last


# --- the timed paths -----------------------------------------------------------------------------

def time_path(client: httpx.Client, make: Callable[[], httpx.Request], requests: int, warmup: int,
              metrics_urls: Sequence[str], check: Callable[[dict[str, Any]], None] | None = None
              ) -> dict[str, Any]:
    """``warmup`` then ``requests`` sequential requests (concurrency 1): wall times, statuses, answers'
    per-request ``timings`` when they have them, and the /metrics histograms over the timed ones."""
    for _ in range(warmup):
        client.send(make())
    before = metric_snapshot(client, metrics_urls)
    seconds: list[float] = []
    statuses: dict[str, int] = defaultdict(int)
    answer_timings: dict[str, list[float]] = defaultdict(list)
    errors: list[str] = []
    last: dict[str, Any] = {}
    for _ in range(requests):
        req = make()  # built outside the timed span: the multipart encoding is the client's cost
        t0 = time.perf_counter()
        r = client.send(req)
        body = r.content
        seconds.append(time.perf_counter() - t0)
        statuses[str(r.status_code)] += 1
        if r.status_code != 200:
            if len(errors) < 3:
                errors.append(body[:300].decode(errors="replace"))
            continue
        last = json.loads(body)
        for k, v in (last.get("timings") or {}).items():
            answer_timings[k].append(float(v))
        if check is not None:
            check(last)
    after = metric_snapshot(client, metrics_urls)
    return {"latency": summarize_seconds(seconds), "statuses": dict(statuses), "errors": errors,
            "answer_timings": {k: summarize_seconds(v) for k, v in answer_timings.items()},
            "server_metrics": histogram_means(before, after), "last_answer": last}


def _mesh_request(client: httpx.Client, data: bytes, fmt: str, k: int, fit: bool = False,
                  body: bool = False) -> Callable[[], httpx.Request]:
    """``/suggest/mesh`` of ``data``: a multipart form, or (``body``) the file as the body."""
    mime = {"glb": "model/gltf-binary", "obj": "model/obj"}[fmt]
    options = json.dumps({"k": k} if fit else {"k": k, "fit_frame": False})

    def make() -> httpx.Request:
        if body:
            return client.build_request("POST", "/suggest/mesh", content=data, params={"options": options},
                                        headers={"Content-Type": mime})
        return client.build_request("POST", "/suggest/mesh", files={"file": (f"query.{fmt}", data, mime)},
                                    data={"options": options})
    return make


def _json_request(client: httpx.Client, path: str, body: bytes) -> Callable[[], httpx.Request]:
    def make() -> httpx.Request:
        return client.build_request("POST", path, content=body, headers={"Content-Type": "application/json"})
    return make


def _summary(answer: dict[str, Any], path: str) -> dict[str, Any]:
    """What the last answer of a path was (to see the paths did real work)."""
    if path.startswith("suggest"):
        return {"suggestions": len(answer.get("suggestions", [])),
                "top_part": answer["suggestions"][0]["part_id"] if answer.get("suggestions") else None}
    if path == "place_5":
        return {"placements": len(answer.get("placements", []))}
    return {"nodes": len(answer.get("nodes", [])), "steps": len(answer.get("steps", [])),
            "stop_reason": answer.get("stop_reason")}


def run_interactive_bench(query: BenchQuery, cfg: InteractiveBenchConfig, cache: Path) -> dict[str, Any]:
    """Make the mesh, time the in-process stages, start the service and time every path."""
    from bench.engine_bench import load_engine
    from service.settings import get_settings

    load_at_start = [round(x, 2) for x in os.getloadavg()]
    settings = get_settings()
    engine = load_engine(settings)
    n = engine.artifacts.n_points
    mesh, mesh_info = query_mesh(engine.catalog, cfg.target_faces)
    files = mesh_files(mesh, cache)
    mesh_info["bytes"] = {fmt: len(data) for fmt, data in files.items()}
    log.info("query mesh: %d faces, GLB %d bytes, OBJ %d bytes", mesh_info["faces"], len(files["glb"]),
             len(files["obj"]))
    mesh_stages = {fmt: time_mesh_stages(data, fmt, cfg.parse_reps, settings, n)
                   for fmt, data in files.items()}
    suggest_bodies = {"suggest_contact_off": query.body("json", refine_contact=False),
                      "suggest_contact_on": query.body("json", refine_contact=True)}
    engine_stages = time_engine_contact(engine, suggest_bodies, cfg.requests, cfg.warmup)
    catalog = engine.catalog
    start_part = catalog.part_ids[query_shape(catalog)[0]]
    starts = category_starts(catalog)
    del engine  # the server loads its own

    paths: dict[str, dict[str, Any]] = {}
    with our_service(cache, dict(cfg.server_env), cfg.processes) as server, \
            httpx.Client(base_url=server.url, timeout=cfg.timeout) as client:
        first = client.post("/suggest", content=suggest_bodies["suggest_contact_off"],
                            headers={"Content-Type": "application/json"})
        if first.status_code != 200:
            raise RuntimeError(f"POST /suggest answered {first.status_code}: {first.text[:500]}")
        place_ids = [s["part_id"] for s in first.json()["suggestions"]][:cfg.place_parts]
        place_body = json.dumps({"points": np.round(query.points.astype(np.float64), 6).tolist(),
                                 "part_ids": place_ids}).encode()
        makers = {
            "suggest_mesh_glb": _mesh_request(client, files["glb"], "glb", cfg.k),
            "suggest_mesh_obj": _mesh_request(client, files["obj"], "obj", cfg.k),
            "suggest_mesh_glb_body": _mesh_request(client, files["glb"], "glb", cfg.k, body=True),
            "suggest_mesh_obj_body": _mesh_request(client, files["obj"], "obj", cfg.k, body=True),
            "suggest_mesh_glb_fit": _mesh_request(client, files["glb"], "glb", cfg.k, fit=True),
            "place_5": _json_request(client, "/place", place_body),
            "suggest_contact_off": _json_request(client, "/suggest", suggest_bodies["suggest_contact_off"]),
            "suggest_contact_on": _json_request(client, "/suggest", suggest_bodies["suggest_contact_on"]),
            "assemble": _json_request(client, "/assemble", json.dumps({"part_id": start_part}).encode()),
        }
        # Before any other /assemble: each category's first call after the server started.
        first_assembles = time_first_assembles(client, starts)
        for name in PATHS:
            log.info("timing %s (%d requests)", name, cfg.requests)
            row = time_path(client, makers[name], cfg.requests, cfg.warmup, server.metrics_urls)
            row["answer"] = _summary(row.pop("last_answer"), name)
            paths[name] = row
    return {
        "query": {"source": query.source, "points": len(query.points), "k": query.k},
        "mesh": mesh_info,
        "place_parts": place_ids,
        "assemble_start": start_part,
        "assemble_first": first_assembles,
        "paths": paths,
        "mesh_stages_in_process": mesh_stages,
        "engine_stages_in_process": engine_stages,
        # The host is shared: its load before and after this benchmark's own work.
        "load_average": {"start": load_at_start, "end": [round(x, 2) for x in os.getloadavg()]},
    }
