"""Training side of ComplementMe: shape data, preprocessing, the three networks, export, evaluation.

Torch is imported only by the modules that need it, so the data commands run without it.
"""
