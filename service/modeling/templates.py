"""What the data's own shapes say an assembly still lacks, read from geometry alone.

A greedy assembly ends when g's mixture wants nothing more than what is placed. g can be sure of
that and wrong: a rifle whose stock, barrel and scope are placed is offered more scopes, though
almost every rifle of the data has a body between them; a sofa of cushions and legs is offered
more cushions, though most sofas have a seat under them. Before such an end the assembly asks the
catalog's own training shapes of its category (``missing_spots``):

1. the ``neighbours`` shapes that hold the placed parts most closely: the smallest mean distance
   from the placed samples to the shape's samples (a shape with more parts than the assembly is
   not penalised: it is what the assembly may grow into);
2. in each of them that has more components than the assembly has parts (a shape with no more
   parts than the assembly is not one the assembly lacks a part of: its uncovered components
   are placed parts of other styles at other places, and a table of four legs, top and
   stretcher would get a fifth leg), the components the placed parts leave uncovered: fewer than
   ``uncovered_share`` of the component's samples within ``cover_distance`` of a placed sample;
3. a *spot* is an uncovered component's centre; it is voted for by every neighbour with an
   uncovered component centred within ``radius`` of it. Spots voted for by at least ``share`` of
   the neighbours are returned, most voted first, each the mean centre of its voters' components
   and at least ``radius`` from a spot before it.

The assembly then asks for suggestions placed at each spot in turn (``SuggestOptions.region``)
and adds the first that does no placed part's job. Labels are never read: only the shapes'
components, their samples and where they sit (the shapes' categories are the collection's
folders, as everywhere else).
"""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np
from scipy.spatial import cKDTree

from service.artifacts.catalog import Catalog, drawn_training_shapes

# Samples kept per component of a template shape: enough to tell a covered component from an
# uncovered one (256 gave the same spots on the training starts), few enough that finding the
# nearest shapes of a category (144 in the shipped catalog) takes a few milliseconds.
TEMPLATE_SAMPLES = 64
# Placed samples compared with the templates at most (a seeded subset beyond it): an assembly of
# nine parts holds 2,304. Ranking the shapes by how closely they hold the assembly takes a mean
# distance, which a smaller subset estimates well enough: it is the step that reads every shape
# (144 KD-tree queries), 70 ms with every sample and about 10 ms with 256.
PLACED_SAMPLES = 2048
FIT_SAMPLES = 256


@dataclass(frozen=True)
class ShapeTemplate:
    """One training shape of the catalog: its components' samples where they sit in the shape.

    Shapes:
        points: (M, 3) float64 canonical.   component: (M,) int64, index of each point's component.
    """

    shape_id: str
    points: np.ndarray
    component: np.ndarray
    n_components: int
    tree: cKDTree


def shape_templates(catalog: Catalog, category: str, max_shapes: int, seed: int = 0,
                    rows_of: dict[str, list[int]] | None = None) -> list[ShapeTemplate]:
    """The catalog's training shapes of ``category`` (every multi-part shape when the catalog has
    no split), at most ``max_shapes`` of them (a seeded draw), as ``ShapeTemplate``s; ``rows_of``
    as ``drawn_training_shapes`` takes it."""
    out: list[ShapeTemplate] = []
    for sid, rows in drawn_training_shapes(catalog, category, max_shapes, seed, rows_of):
        clouds = [catalog.part_points(i)[:TEMPLATE_SAMPLES].astype(np.float64) + catalog.translations[i]
                  for i in rows]
        points = np.concatenate(clouds)
        component = np.repeat(np.arange(len(rows), dtype=np.int64), [len(c) for c in clouds])
        out.append(ShapeTemplate(sid, points, component, len(rows), cKDTree(points)))
    return out


def missing_spots(placed: np.ndarray, templates: list[ShapeTemplate], neighbours: int, cover_distance: float,
                  uncovered_share: float, share: float, radius: float, seed: int = 0, n_parts: int = 0
                  ) -> list[tuple[np.ndarray, int]]:
    """The spots where most of the nearest template shapes have a component the placed parts do
    not cover (see the module doc), most voted first, with their votes. ``n_parts``: how many
    parts the assembly has (only shapes with more components vote).

    Shapes:
        placed: (P, 3) canonical samples of the placed parts -> [((3,) float64 centre, votes)].
    """
    if len(templates) == 0 or len(placed) == 0 or neighbours <= 0:
        return []
    pts = np.asarray(placed, dtype=np.float64)
    rng = np.random.default_rng(seed)
    if len(pts) > PLACED_SAMPLES:
        pts = pts[np.sort(rng.choice(len(pts), PLACED_SAMPLES, replace=False))]
    few = pts[np.sort(rng.choice(len(pts), FIT_SAMPLES, replace=False))] if len(pts) > FIT_SAMPLES else pts
    fit = np.array([float(np.mean(t.tree.query(few, k=1)[0])) for t in templates])
    near = np.argsort(fit, kind="stable")[:neighbours]
    placed_tree = cKDTree(pts)
    owners: list[int] = []        # the neighbour of each uncovered component
    centres: list[np.ndarray] = []
    for j in near:
        t = templates[int(j)]
        if t.n_components <= n_parts:
            continue  # a shape with no more parts than the assembly lacks none of them
        d, _ = placed_tree.query(t.points, k=1, distance_upper_bound=cover_distance)
        covered = np.isfinite(d)
        for c in range(t.n_components):
            mine = t.component == c
            if np.mean(covered[mine]) < uncovered_share:
                owners.append(int(j))
                centres.append(t.points[mine].mean(axis=0))
    if not centres:
        return []
    ctr = np.array(centres)
    own = np.array(owners)
    close = np.linalg.norm(ctr[:, None] - ctr[None], axis=2) < radius          # (U, U)
    votes = np.array([len(set(own[row].tolist())) for row in close])
    need = share * len(near)
    spots: list[tuple[np.ndarray, int]] = []
    for u in np.argsort(-votes, kind="stable"):
        if votes[u] < need:
            break
        centre = ctr[close[u]].mean(axis=0)
        if all(np.linalg.norm(centre - c) >= radius for c, _ in spots):
            spots.append((centre, int(votes[u])))
    return spots
