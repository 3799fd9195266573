"""ComplementMe service: the torch-free suggestion engine and its HTTP API."""

__version__ = "0.1.0"
