"""Performance benchmarks of the suggestion service (issue 6): ``python -m bench --help``.

Not part of the service: ``service/`` never imports this package. It may import torch and
``training`` (the peer baseline rebuilds the networks in torch from the exported graphs).
"""
