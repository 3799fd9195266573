"""The HTTP face of the service: the only package that knows HTTP, FastAPI or Starlette.

Owns the app factory and its lifespan (``app``), what is served (``served``: the engine, the
current catalog snapshot, the batcher, the catalog writer), typed dependencies (``deps``), who
may write (``auth``), bounded work under load and the error budget (``overload``), the micro-batcher that
runs concurrent requests as one engine call (``batching``), middleware and body limits,
Prometheus metrics (``metrics``), the routes by resource (``routes``), request and response
schemas, the rendering of engine results into responses, the JSON error envelope, and the
modeling page's files (``static/``). Core packages never import it.
"""
