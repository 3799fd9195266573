"""Parts added to the catalog at run time: stored durably, served as immutable snapshots.

Owns the store of added parts, the source of truth (SQLite in a data folder, ``store``, or
PostgreSQL shared by replicas, ``pg_store``, whose changes a replica follows, ``follow``), the
catalogs of shipped plus added parts with their index (``snapshot``), the writer that applies
additions and deletions and publishes the next ``CatalogSnapshot`` to serve (``writer``), the
preparation of an uploaded part mesh for storing (``part_prep``) and the checking and repair of
a data folder (``recovery``). It raises the service's plain errors; only ``service.api`` maps them to HTTP.
"""
