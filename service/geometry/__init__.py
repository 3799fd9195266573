"""Geometry in, and the pure maths on it: what a caller or a data file sends, made safe and uniform.

Owns reading untrusted mesh files (the format checks and size limits that run before trimesh
parses anything, ``mesh``), decoding the point clouds and mesh uploads a request carries into
checked ``(N, 3)`` arrays (``inputs``), the pure surface maths shared with the trainer (areas,
seeded surface sampling and resampling, point-to-mesh distances, ``mesh``), box overlap
(``boxes``), the Chamfer distance between point sets (``pointsets``), and the caller's and the
canonical coordinate frames (``frames``). Nothing here knows the networks, the catalog or HTTP.
"""
