"""A small Python client for the suggestion service, with timeouts and retries.

It needs httpx and numpy only (not the service's onnxruntime, FAISS, scipy or trimesh):
``pip install ./clients/python`` from the repository. ``service.serve.client`` re-exports it.

Retries cover what a restart or a rolling deploy looks like from outside: connection errors,
timeouts while connecting, 503 (not ready, overloaded) and 429 (``too_many_errors``: this client
had too many error answers; refused before it ran). Everything else (4xx, other 5xx) is raised at
once as ``ClientError`` carrying the service's error code and message.

    client = ComplementMeClient("http://127.0.0.1:8000")
    answer = client.suggest(points, k=5, category="chair")
"""

from __future__ import annotations

import base64
import json
import logging
import time
from collections.abc import Iterable
from concurrent.futures import FIRST_COMPLETED, Future, ThreadPoolExecutor, as_completed, wait
from pathlib import Path
from typing import Any, BinaryIO

import httpx
import numpy as np

log = logging.getLogger(__name__)

POINT_SUFFIXES = (".npy", ".xyz", ".pts", ".txt")
REQUEST_SUFFIXES = (".json",)  # a POST /suggest body, e.g. examples/chair-without-legs.json
MESH_SUFFIXES = (".obj", ".ply", ".stl", ".off", ".glb", ".gltf")
# Answers that mean the request did not run and may run later: not ready or overloaded (503), or
# this client past its budget of error answers (429); retried after Retry-After.
RETRIED_STATUSES = frozenset({429, 503})


def points_to_base64(points: np.ndarray) -> str:
    """(N, 3) points -> base64 of little-endian float32, the API's ``points_base64``."""
    return base64.b64encode(np.ascontiguousarray(points, dtype="<f4").tobytes()).decode("ascii")


class ClientError(RuntimeError):
    """The service refused a request (or never answered); ``code`` is the service's error code."""

    def __init__(self, status: int | None, code: str, message: str):
        super().__init__(f"{status or 'no answer'} {code}: {message}")
        self.status = status
        self.code = code
        self.message = message


class ComplementMeClient:
    """Calls the service's routes; arrays go out as base64 float32 (the fast path).

    Args:
        base_url: e.g. ``http://127.0.0.1:8000``.
        timeout: seconds for each request (connect, read and write).
        retries: extra attempts after a connection error, a 503 or a 429.
        backoff: seconds before the first retry; doubled each time (or the answer's Retry-After).
        api_key: the key catalog writes need (sent as ``Authorization: Bearer``).
    """

    def __init__(self, base_url: str, *, timeout: float = 30.0, retries: int = 3, backoff: float = 0.5,
                 transport: httpx.BaseTransport | None = None, api_key: str | None = None):
        self.retries = retries
        self.backoff = backoff
        headers = {"Authorization": f"Bearer {api_key}"} if api_key else None
        self.http = httpx.Client(base_url=base_url.rstrip("/"), timeout=timeout, transport=transport,
                                 headers=headers)

    def close(self) -> None:
        self.http.close()

    def __enter__(self) -> ComplementMeClient:
        return self

    def __exit__(self, *exc: object) -> None:
        self.close()

    # ------------------------------------------------------------------ transport
    def request(self, method: str, path: str, *, idempotent: bool = True, **kwargs: Any) -> httpx.Response:
        """One call with retries; raises ``ClientError`` for an error answer or no answer.

        A call that is not ``idempotent`` (a catalog add) is retried only when it surely did not
        run: the connection failed, or the service refused it with 503 or 429.
        """
        delay = self.backoff
        for attempt in range(self.retries + 1):
            last = attempt == self.retries
            try:
                response = self.http.request(method, path, **kwargs)
            except (httpx.ConnectError, httpx.ConnectTimeout, httpx.RemoteProtocolError) as exc:
                if not idempotent and isinstance(exc, httpx.RemoteProtocolError):
                    raise ClientError(None, "unknown_outcome", f"{method} {path}: the connection broke "
                                      f"after sending ({exc}); the request may have run") from exc
                if last:
                    raise ClientError(None, "unreachable", f"{method} {path}: {exc}") from exc
                log.debug("retrying %s %s after %s", method, path, exc)
            except httpx.TimeoutException as exc:  # a read timeout: the request may have run; no retry
                raise ClientError(None, "timeout", f"{method} {path}: {exc}") from exc
            else:
                if response.status_code in RETRIED_STATUSES and not last:
                    log.debug("retrying %s %s after %d", method, path, response.status_code)
                    delay = max(delay, min(30.0, _retry_after(response)))
                elif response.status_code >= 400:
                    raise _error_of(response)
                else:
                    return response
            time.sleep(delay)
            delay *= 2
        raise AssertionError("unreachable")  # the loop returns or raises

    # ------------------------------------------------------------------ routes
    def suggest(self, points: np.ndarray, **options: Any) -> dict[str, Any]:
        """``POST /suggest`` with points (M, 3); options as in the API (k, category, frame, ...)."""
        body = {"points_base64": points_to_base64(points), **_drop_none(options)}
        return self.request("POST", "/suggest", json=body).json()

    def suggest_mesh(self, path: Path, **options: Any) -> dict[str, Any]:
        """``POST /suggest/mesh`` with a mesh file, sent as the request body (its format from its
        extension; the options in the query string): no multipart form to build or parse."""
        path = Path(path)
        params = {"options": json.dumps(_drop_none(options)), "format": path.suffix.lstrip(".").lower()}
        return self.request("POST", "/suggest/mesh", content=path.read_bytes(), params=params,
                            headers={"Content-Type": "application/octet-stream"}).json()

    def suggest_batch(self, queries: list[np.ndarray], **options: Any) -> dict[str, Any]:
        """``POST /suggest/batch``: one result (or error) per query, same options for all."""
        items = [{"points_base64": points_to_base64(q), **_drop_none(options)} for q in queries]
        return self.request("POST", "/suggest/batch", json={"items": items}).json()

    def place(self, points: np.ndarray, part_ids: list[str], frame: dict[str, Any] | None = None
              ) -> dict[str, Any]:
        body = {"points_base64": points_to_base64(points), "part_ids": part_ids,
                **_drop_none({"frame": frame})}
        return self.request("POST", "/place", json=body).json()

    def part(self, part_id: str) -> dict[str, Any]:
        return self.request("GET", f"/parts/{part_id}").json()

    def part_mesh(self, part_id: str, format: str = "glb") -> bytes:
        return self.request("GET", f"/parts/{part_id}/mesh", params={"format": format}).content

    def parts(self, **filters: Any) -> dict[str, Any]:
        """``GET /parts`` (filters: category, shape_id, offset, limit)."""
        return self.request("GET", "/parts", params=_drop_none(filters)).json()

    def add_part(self, mesh: bytes, filename: str, category: str, **fields: Any) -> dict[str, Any]:
        """``POST /parts``: add a part (fields: shape_id, name, style, label, format, frame).

        Needs the client's ``api_key``. Returns the new part's record (with its ``part_id``).
        """
        data = {"category": category, **{k: (v if isinstance(v, str) else json.dumps(v))
                                        for k, v in _drop_none(fields).items()}}
        return self.request("POST", "/parts", idempotent=False, files={"file": (filename, mesh)},
                            data=data).json()

    def delete_part(self, part_id: str) -> None:
        """``DELETE /parts/{id}``: remove an added part (needs the client's ``api_key``)."""
        self.request("DELETE", f"/parts/{part_id}")

    def model(self) -> dict[str, Any]:
        return self.request("GET", "/model").json()

    def ready(self) -> bool:
        """True when ``/readyz`` answers 200 (one attempt, no retries)."""
        try:
            return self.http.get("/readyz").status_code == 200
        except httpx.HTTPError:
            return False


def _retry_after(response: httpx.Response) -> float:
    try:
        return float(response.headers.get("retry-after", 0))
    except ValueError:
        return 0.0


def _drop_none(d: dict[str, Any]) -> dict[str, Any]:
    return {k: v for k, v in d.items() if v is not None}


def _error_of(response: httpx.Response) -> ClientError:
    try:
        err = response.json()["error"]
        return ClientError(response.status_code, err["code"], err["message"])
    except (ValueError, KeyError, TypeError):
        return ClientError(response.status_code, "http_error", response.text[:500])


def read_points_file(path: Path) -> np.ndarray:
    """Points from ``.npy`` (an (N, 3) array) or text ``.xyz``/``.pts``/``.txt`` (x y z per line).

    Text files may have extra columns (normals, colours: only the first three are read), comment
    lines starting with ``#``, and a first line holding only the point count.

    Shapes:
        returns (N, 3) float32.
    """
    path = Path(path)
    if path.suffix.lower() == ".npy":
        arr = np.load(path, allow_pickle=False)
    else:
        rows = []
        for line in path.read_text().splitlines():
            fields = line.split("#", 1)[0].replace(",", " ").split()
            if len(fields) >= 3:
                rows.append(fields[:3])
            elif fields and not rows and len(fields) == 1:
                continue  # a leading point count
            elif fields:
                raise ValueError(f"{path}: line {line!r} does not hold x y z")
        try:
            arr = np.array(rows, dtype=np.float64).reshape(-1, 3)
        except ValueError as exc:
            raise ValueError(f"{path}: not numeric x y z rows ({exc})") from None
    if arr.ndim != 2 or arr.shape[1] != 3:
        raise ValueError(f"{path}: expected points of shape (N, 3), found {arr.shape}")
    return arr.astype(np.float32)


def read_request_file(path: Path) -> dict[str, Any]:
    """A ``POST /suggest`` body saved as JSON: an object with ``points`` or ``points_base64``."""
    path = Path(path)
    try:
        body = json.loads(path.read_bytes())
    except (json.JSONDecodeError, UnicodeDecodeError) as exc:
        raise ValueError(f"{path}: not valid JSON ({exc})") from None
    if not isinstance(body, dict) or not ({"points", "points_base64"} & body.keys()):
        raise ValueError(f"{path}: not a /suggest request (a JSON object with \"points\" or "
                         "\"points_base64\")")
    return body


QUERY_SUFFIXES = POINT_SUFFIXES + MESH_SUFFIXES + REQUEST_SUFFIXES


def query_files(folder: Path) -> list[Path]:
    """Mesh, point and request files directly inside ``folder``, sorted by name."""
    return sorted(p for p in Path(folder).iterdir() if p.is_file() and p.suffix.lower() in QUERY_SUFFIXES)


def skipped_files(folder: Path) -> list[tuple[Path, str]]:
    """What ``query_files`` leaves out of ``folder``, each with the reason, sorted by name."""
    skipped = []
    for p in sorted(Path(folder).iterdir()):
        if p.is_dir():
            skipped.append((p, "a folder (sub-folders are not read)"))
        elif p.suffix.lower() not in QUERY_SUFFIXES:
            skipped.append((p, f"not a mesh, point or request file ({p.suffix or 'no suffix'})"))
    return skipped


def suggest_file(client: ComplementMeClient, path: Path, **options: Any) -> dict[str, Any]:
    """Suggestions for one file: meshes are uploaded, point files sent as base64 points.

    A ``.json`` request file is sent as it is, with ``options`` that are not None replacing its own.
    """
    suffix = Path(path).suffix.lower()
    if suffix in MESH_SUFFIXES:
        return client.suggest_mesh(path, **options)
    if suffix in REQUEST_SUFFIXES:
        body = {**read_request_file(path), **_drop_none(options)}
        return client.request("POST", "/suggest", json=body).json()
    return client.suggest(read_points_file(path), **options)


def run_batch(client: ComplementMeClient, files: Iterable[Path], out: Path, *, concurrency: int = 4,
              progress: Any = None, **options: Any) -> tuple[int, int]:
    """Send every file with at most ``concurrency`` requests in flight; write JSON Lines.

    Each line is ``{"file", "ok": true, "result"}`` or ``{"file", "ok": false, "error": {"code",
    "message"}}``, in completion order. ``progress`` (e.g. a tqdm bar) gets ``update(1)`` per file.

    Returns:
        (files answered, files failed).
    """
    ok = failed = 0
    def one(path: Path) -> dict[str, Any]:
        try:
            return {"file": str(path), "ok": True, "result": suggest_file(client, path, **options)}
        except ClientError as exc:
            return {"file": str(path), "ok": False, "error": {"code": exc.code, "message": exc.message}}
        except (OSError, ValueError) as exc:  # an unreadable or malformed local file
            return {"file": str(path), "ok": False, "error": {"code": "bad_file", "message": str(exc)}}

    def write(fh: BinaryIO, line: dict[str, Any]) -> None:
        nonlocal ok, failed
        fh.write(json.dumps(line, separators=(",", ":")).encode() + b"\n")
        fh.flush()
        ok, failed = (ok + 1, failed) if line["ok"] else (ok, failed + 1)
        if progress is not None:
            progress.update(1)

    workers = max(1, concurrency)
    pending: set[Future[dict[str, Any]]] = set()
    with open(out, "wb") as fh, ThreadPoolExecutor(max_workers=workers) as pool:
        for path in files:
            # A bounded window of submitted files: results are written as they come, never piled up.
            if len(pending) >= 2 * workers:
                done, pending = wait(pending, return_when=FIRST_COMPLETED)
                for future in done:
                    write(fh, future.result())
            pending.add(pool.submit(one, path))
        for future in as_completed(pending):
            write(fh, future.result())
    return ok, failed
