"""Routers, one module per resource: suggestions and placement, catalog parts, probes."""
