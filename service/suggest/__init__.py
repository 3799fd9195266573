"""Suggesting the next part: a partial shape in, ranked and placed catalog parts out.

Owns the engine and every step of a suggestion (``engine``, reading only ``engine_settings``):
the immutable catalog a request reads (``snapshot``), g's mixture and its exact log-likelihood
(``mixture``), the search for the nearest parts, numpy brute force or FAISS (``neighbours``),
the complement check (``complement``), the caller's preferences over the mixture's modes
(``preferences``), "suggest for this spot" (``region``), contact-aware placement (``contact``)
and the complete object's frame estimated from a partial upload (``frame_fit``). Plain functions
and objects a test calls without HTTP; no web framework is imported here.
"""
