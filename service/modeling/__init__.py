"""Modeling on top of suggestions: whole shapes assembled part by part, and assemblies as files.

Owns the paper's automatic shape synthesis (``assembly``: start from a part, a cloud or a mesh,
then repeatedly suggest, place and add) and the export of an assembly of catalog parts as one
GLB or OBJ mesh in the caller's frame (``export_mesh``). It uses the suggestion engine and the
catalog; it knows nothing of HTTP.
"""
