"""The Python client, for code inside this project: it lives in ``clients/python``
(package ``complementme_client``, installable alone with httpx and numpy) and is re-exported here
with the package's own list of names, so that the two cannot drift apart.
"""

from complementme_client import *  # noqa: F403
from complementme_client import __all__ as __all__
