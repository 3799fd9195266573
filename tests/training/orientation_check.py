"""How many OBJ files of a folder have their highest points behind their centre (front +x).

Shared by the tests that read Debian's outside collections (test_sweethome3d, test_flightgear):
a chair's back and a plane's fin lie behind the centre once turned front +x, in front of it when
turned the other way round.
"""

from __future__ import annotations

from pathlib import Path

import numpy as np


def top_behind_and_ahead(folder: Path, top_share: float) -> tuple[int, int]:
    """(files whose top ``top_share`` of height lies behind the centre, files where it lies ahead),
    each by more than 5% of the depth."""
    behind = ahead = 0
    for obj in folder.glob("*.obj"):
        v = np.array([[float(x) for x in line.split()[1:4]] for line in obj.read_text().splitlines()
                      if line.startswith("v ")])
        lo, hi = v.min(axis=0), v.max(axis=0)
        top = v[v[:, 1] > lo[1] + (1 - top_share) * (hi[1] - lo[1])]
        x = (top[:, 0].mean() - (lo[0] + hi[0]) / 2) / (hi[0] - lo[0])
        behind += bool(x < -0.05)
        ahead += bool(x > 0.05)
    return behind, ahead
