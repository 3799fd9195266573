"""The shipped artifacts: the exported folder the trainer writes and the server reads, opened once.

Owns the artifact format (file names, catalog array names, manifest keys and checksums,
``layout``), opening a folder and refusing a bad one with an error that names the file (the ONNX
sessions, ``loading``), the five networks behind typed batch calls (``models``), the catalog of
parts as arrays indexed by row (``catalog``) and the FAISS index chosen by catalog size
(``indexing``), and the one way the project writes a file durably and atomically (``files``,
used by the catalog store, export and training too). It reads and writes files and runs graphs;
it does not rank, place or serve anything.
"""
