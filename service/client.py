"""The Python client, for code inside this project: it lives in ``clients/python``
(package ``complementme_client``, installable alone with httpx and numpy) and is re-exported here.
"""

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
