"""The ComplementMe suggestion service's Python client: httpx and numpy, nothing of the server."""

from complementme_client.client import (
    MESH_SUFFIXES,
    POINT_SUFFIXES,
    QUERY_SUFFIXES,
    REQUEST_SUFFIXES,
    ClientError,
    ComplementMeClient,
    points_to_base64,
    query_files,
    read_points_file,
    read_request_file,
    run_batch,
    skipped_files,
    suggest_file,
)

__all__ = [
    "MESH_SUFFIXES",
    "POINT_SUFFIXES",
    "QUERY_SUFFIXES",
    "REQUEST_SUFFIXES",
    "ClientError",
    "ComplementMeClient",
    "points_to_base64",
    "query_files",
    "read_points_file",
    "read_request_file",
    "run_batch",
    "skipped_files",
    "suggest_file",
]
