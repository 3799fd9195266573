"""The framework peers: the shipped graphs, index and catalog served by an established serving
framework with its own batching (BentoML, LitServe), in a venv of their own (``venv``); the
model code both share is ``pipeline``. Benchmark f (``bench.framework_bench``) runs them."""
