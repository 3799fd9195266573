"""Point samples of partial assemblies and parts, and the triplet sampler of Section 5.3.

Everything here reads the cached per-component samples of a ``ProcessedDataset``: sampling an
assembly is drawing, per component, a number of cached points proportional to its area
(area-weighted over the union), so training never touches a mesh.
"""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np

from service.geometry.pointsets import chamfer_distance
from service.geometry.scaling import scaled_area
from service.settings import Settings
from training.config import check_negative_shares
from training.data.processed import ProcessedDataset


def sample_assembly(ds: ProcessedDataset, comps: np.ndarray | list[int], n: int,
                    rng: np.random.Generator, by_area: bool = True) -> np.ndarray:
    """Sample ``n`` points area-weighted over a set of components, in the shape's frame.

    ``by_area=False`` draws components evenly instead (a collection sampled per part, not by
    surface).

    Shapes:
        returns (n, 3) float32.
    """
    comps = np.asarray(comps, dtype=np.int64)
    assert comps.size > 0, "an assembly needs at least one component"
    return draw_area_weighted(ds.points, ds.translation, ds.area, comps, n, rng, by_area)


def draw_area_weighted(samples: np.ndarray, translations: np.ndarray, areas: np.ndarray, rows: np.ndarray,
                       n: int, rng: np.random.Generator, by_area: bool = True) -> np.ndarray:
    """``n`` points over the parts ``rows``: each point's part drawn with probability proportional
    to its area (evenly without ``by_area``, or when no part has area), then one of that part's
    cached (uniform, centred) surface samples, moved by the part's translation.

    One sampler for training batches (``sample_assembly``) and the benchmark's queries
    (``training.evaluate.protocol.sample_rows``), so both see assemblies drawn the same way.

    Shapes:
        samples (P, S, 3); translations (P, 3) float32; areas (P,); rows (r,) int64, r >= 1;
        returns (n, 3) float32.
    """
    area = areas[rows].astype(np.float64)
    even = np.full(len(rows), 1.0 / len(rows))
    probs = area / area.sum() if by_area and area.sum() > 0 else even
    which = rows[rng.choice(len(rows), size=n, p=probs)]
    cached = rng.integers(0, samples.shape[1], size=n)
    return samples[which, cached].astype(np.float32) + translations[which]


def sample_part(ds: ProcessedDataset, comp: int, n: int, rng: np.random.Generator) -> np.ndarray:
    """Sample ``n`` points of one component, centred at its bounding-box centre.

    Shapes:
        returns (n, 3) float32.
    """
    cached = ds.points.shape[1]
    rows = rng.choice(cached, size=n, replace=n > cached)
    return ds.points[comp, rows].astype(np.float32)


def random_connected_subgraph(nodes: list[int], adj: list[set[int]], r: int,
                              rng: np.random.Generator) -> list[int]:
    """Grow a connected subgraph of ``r`` nodes from a random seed node (paper, Section 5.3)."""
    start = nodes[int(rng.integers(len(nodes)))]
    chosen = [start]
    chosen_set = {start}
    frontier = set(adj[start])
    while len(chosen) < r and frontier:
        nxt = sorted(frontier)[int(rng.integers(len(frontier)))]
        chosen.append(nxt)
        chosen_set.add(nxt)
        frontier |= adj[nxt]
        frontier -= chosen_set
    return chosen


def component_descriptors(ds: ProcessedDataset) -> np.ndarray:
    """Where a component sits and how big it is: box centre and box extents, both in the shape's frame.

    Shapes share the canonical frame (y up, unit radius), so a seat sits at a seat's height and
    has a seat's proportions whatever its style.

    Shapes:
        returns (n_components, 6) float32.
    """
    pts = ds.points.astype(np.float32)
    extents = pts.max(axis=1) - pts.min(axis=1)
    return np.concatenate([ds.translation.astype(np.float32), extents], axis=1)


# Boxes thinner than this (unit radius) along an axis give no scale along it: a flat part's
# thickness is noise in its samples, not a size h should learn to match.
MIN_FIT_EXTENT = 0.02
# The largest per-axis rescale h learns to ask for: the service's clip (its settings' defaults,
# a factor of 2 either way).
MAX_FIT_LOG_SCALE = float(min(np.log(Settings.model_fields["scale_max"].default),
                              -np.log(Settings.model_fields["scale_min"].default)))


def substitute_log_scale(target: np.ndarray, part: np.ndarray) -> np.ndarray:
    """Per-axis log scale that gives ``part``'s sample box the extents of ``target``'s, clipped.

    Shapes:
        target (N, 3), part (M, 3) centred samples -> (3,) float32.
    """
    want = np.ptp(target, axis=0)
    have = np.ptp(part, axis=0)
    fit = np.log(np.maximum(want, MIN_FIT_EXTENT) / np.maximum(have, MIN_FIT_EXTENT))
    thin = (want < MIN_FIT_EXTENT) & (have < MIN_FIT_EXTENT)
    return np.clip(np.where(thin, 0.0, fit), -MAX_FIT_LOG_SCALE, MAX_FIT_LOG_SCALE).astype(np.float32)


def lookalike_components(ds: ProcessedDataset, k: int) -> np.ndarray:
    """For every component, its ``k`` nearest components of other shapes of the same category.

    Shapes:
        returns (n_components, k) int64, padded with -1 where a category has too few others.
    """
    from scipy.spatial import cKDTree

    desc = component_descriptors(ds)
    out = np.full((ds.n_components, k), -1, np.int64)
    categories = np.array([str(ds.shapes[int(s)].get("category", "")) for s in ds.shape_of])
    for cat in np.unique(categories):
        members = np.flatnonzero(categories == cat)
        tree = cKDTree(desc[members])
        # Ask for enough neighbours to skip the component's own shape (at most 8 components each).
        want = min(len(members), k + 16)
        _, nn = tree.query(desc[members], k=want)
        nn = members[np.asarray(nn).reshape(len(members), want)]
        for row, comp in enumerate(members):
            others = nn[row][ds.shape_of[nn[row]] != ds.shape_of[comp]][:k]
            out[comp, :len(others)] = others
    return out


# Look-alikes whose samples lie closer than this to a component's (mean symmetric chamfer
# distance of the centred parts, unit radius) count as the same geometry in another shape: as
# negatives of that component they would ask f to pull apart two copies of one part. The
# median look-alike (below) lies 0.027 away, a quarter of them 0.044 or more.
SHAPE_NEGATIVE_MIN_DISTANCE = 0.05
# Samples per part the distance is measured on. Two samplings of one part lie apart by sampling
# noise alone: 0.039 at the median (0.098 at the 0.9 quantile) with 64, 0.020 (0.052) with 256,
# about half that with 512, the first count at which 0.05 is mostly shape and not noise.
SHAPE_DISTANCE_SAMPLES = 512
# Look-alikes searched for those of another shape: with 8, half the components have none (the
# nearest boxes are mostly copies of the same style).
SHAPE_NEGATIVE_NEIGHBOURS = 16


def shape_lookalikes(ds: ProcessedDataset, k: int = SHAPE_NEGATIVE_NEIGHBOURS,
                     min_distance: float = SHAPE_NEGATIVE_MIN_DISTANCE) -> np.ndarray:
    """Each component's ``k`` look-alikes (``lookalike_components``) less those whose geometry is
    its own: kept when the mean symmetric chamfer distance of the centred parts is at least
    ``min_distance``.

    Shapes:
        returns (n_components, k) int64, padded with -1.
    """
    from scipy.spatial import cKDTree

    lookalikes = lookalike_components(ds, k)
    # A fixed subsample (the same samples of every part), so the table depends on the data alone.
    n_cached = ds.points.shape[1]
    pick = np.random.default_rng(0).choice(n_cached, min(SHAPE_DISTANCE_SAMPLES, n_cached), replace=False)
    sub = ds.points[:, np.sort(pick)].astype(np.float64)
    trees = [cKDTree(p) for p in sub]
    out = np.full_like(lookalikes, -1)
    for comp, row in enumerate(lookalikes):
        kept = [int(o) for o in row[row >= 0]
                if chamfer_distance(sub[comp], sub[o], trees[comp], trees[o]) >= min_distance]
        out[comp, :len(kept)] = kept
    return out


@dataclass
class Triplet:
    """One training example: query components X, a positive complement Y and a negative Z.

    ``missing`` holds every component of the shape that X lacks: all of them are valid answers
    to X (the paper's Y is one, adjacent to X), which is what a multimodal g must cover.
    """

    shape: int
    query: list[int]
    positive: int
    negative: int
    missing: list[int]
    # The negative is one of the positive's shape look-alikes (TripletSampler.shape_negatives).
    shape_negative: bool = False


@dataclass(frozen=True)
class Augmentation:
    """Ranges of the shape augmentations (``TrainConfig.augment`` is the share augmented).

    What real collections bring and the generator does not: other proportions, models a little
    rotated about the up axis, frames off centre or off scale, noisy or unevenly sampled
    surfaces and holes.
    """

    axis_log_scale: float = 0.2        # per-axis rescale of the whole shape, exp(U(-a, a))
    yaw_degrees: float = 8.0           # rotation about the up (y) axis
    frame_offset: float = 0.05         # translation of the whole shape (unit radius)
    frame_log_scale: float = 0.1       # uniform rescale of the whole shape
    noise: float = 0.01                # largest per-point Gaussian noise sigma
    hole_probability: float = 0.3      # chance that X loses the points within a random ball
    hole_radius: float = 0.25
    uniform_density_probability: float = 0.3  # chance that X samples components evenly, not by area
    warp_log_slope: float = 0.5        # layout warp: each segment's stretch, exp(U(-a, a)), renormalised
    warp_segments: int = 4             # layout warp: equal segments of [-1, 1] per axis


def augmentation_transform(rng: np.random.Generator, strength: float,
                           ranges: Augmentation = Augmentation()) -> tuple[np.ndarray, np.ndarray]:
    """A random linear map and offset of a whole shape (its parts share the linear map).

    Shapes:
        returns A (3, 3) float32 and t (3,) float32: p -> p @ A.T + t.
    """
    a = ranges.axis_log_scale * strength
    scale = np.exp(rng.uniform(-a, a, 3) + rng.uniform(-1, 1) * ranges.frame_log_scale * strength)
    yaw = np.deg2rad(rng.uniform(-1, 1) * ranges.yaw_degrees * strength)
    c, s = np.cos(yaw), np.sin(yaw)
    rot = np.array([[c, 0.0, s], [0.0, 1.0, 0.0], [-s, 0.0, c]])
    A = rot @ np.diag(scale)
    t = rng.uniform(-1, 1, 3) * ranges.frame_offset * strength
    return A.astype(np.float32), t.astype(np.float32)


def layout_warp(rng: np.random.Generator,
                ranges: Augmentation = Augmentation()) -> tuple[np.ndarray, np.ndarray]:
    """A random monotone piecewise-linear map of [-1, 1] onto itself, one per axis.

    Each of ``warp_segments`` equal segments is stretched by exp(U(-a, a)), then the whole is
    rescaled to span [-1, 1] again: the shape keeps its frame, its proportions change (a taller
    lamp pole, a lower seat, engines further along a wing).

    Shapes:
        returns knots (K + 1,) float64 and warped knots (3, K + 1) float64.
    """
    k = ranges.warp_segments
    knots = np.linspace(-1.0, 1.0, k + 1)
    lengths = np.exp(rng.uniform(-ranges.warp_log_slope, ranges.warp_log_slope, (3, k)))
    warped = np.concatenate([np.zeros((3, 1)), np.cumsum(lengths, axis=1)], axis=1)
    return knots, warped / warped[:, -1:] * 2.0 - 1.0


def warp_boxes(knots: np.ndarray, warped: np.ndarray, centre: np.ndarray, half: np.ndarray
               ) -> tuple[np.ndarray, np.ndarray]:
    """Each box mapped affinely onto the warped image of its corners: new centre and per-axis scale.

    Why boxes, not points: parts stay rigid up to a per-axis rescale (as the service fits a
    catalog part), and two parts that meet at a box face still meet after the warp, since the
    face's coordinate maps to one place for both.

    Shapes:
        knots (K + 1,), warped (3, K + 1), centre (C, 3), half (C, 3) -> centre (C, 3), scale (C, 3)
        float32.
    """
    lo, hi = centre - half, centre + half
    new_lo = np.stack([np.interp(lo[:, a], knots, warped[a]) for a in range(3)], axis=1)
    new_hi = np.stack([np.interp(hi[:, a], knots, warped[a]) for a in range(3)], axis=1)
    segment = np.clip(np.searchsorted(knots, centre) - 1, 0, len(knots) - 2)          # (C, 3)
    slopes = np.diff(warped, axis=1) / np.diff(knots)                                  # (3, K)
    slope = np.take_along_axis(slopes.T, segment, axis=0)   # a thin box takes its segment's stretch
    span = hi - lo
    scale = np.where(span > 1e-4, (new_hi - new_lo) / np.maximum(span, 1e-4), slope)
    return ((new_lo + new_hi) / 2).astype(np.float32), scale.astype(np.float32)


def punch_hole(points: np.ndarray, rng: np.random.Generator, radius: float) -> np.ndarray:
    """Points with those within ``radius`` of a random one of them replaced by other kept points.

    The count stays the same (the networks take a fixed N in a batch), as a scan with a hole
    resampled to N points would.

    Shapes:
        points (N, 3) -> (N, 3).
    """
    centre = points[int(rng.integers(len(points)))]
    keep = np.linalg.norm(points - centre, axis=1) > radius
    if keep.sum() < len(points) // 2:   # never lose most of the query
        return points
    kept = points[keep]
    return np.concatenate([kept, kept[rng.integers(0, len(kept), len(points) - len(kept))]])


class TripletSampler:
    """Samples (X, Y, Z) triplets from contact graphs, as in the paper's Section 5.3.

    X is a random connected subgraph of r in [1, n - 1] nodes of a random shape, Y a random
    component adjacent to X, Z a random component not adjacent to X and not in it (from the same
    shape or, as the paper allows, from any other shape).

    Not in the paper: with probability ``query_negative_fraction`` Z is instead one of X's own
    components. A part the assembly already has is never its missing part, so this negative needs
    no labels (the supervision stays weak), and it is the hard case the paper's random negatives
    almost never show: a chair that has its seat must not be offered another seat. Random
    negatives mostly come from other categories and teach category, not which part is missing.

    With probability ``lookalike_negative_fraction`` Z is a look-alike of one of X's components:
    one of its ``lookalike_neighbours`` nearest components from other shapes of the same category,
    by position and box extent in the shared canonical frame (``component_descriptors``). It
    carries the same lesson to parts of other styles, still without part labels.

    With probability ``shape_negative_fraction`` Z is a look-alike of the positive Y itself (a
    component of another shape of the category at Y's place and size) whose geometry differs
    from Y's (``shape_lookalikes``): the part that does Y's job in another style. Retrieval
    otherwise only learns which job is missing, not which shape of it this assembly wants, and
    ranks the right kind of part by chance among its styles (Table 2's Hausdorff distance).

    With probability ``removal_query_fraction`` X is drawn the other way round: the shape minus a
    random connected group of components. The paper's X is always connected, so a chair without
    its seat (legs and back, which do not touch) never occurs in training; a modeller's "all but
    one part" query often looks like that.

    With ``positive_size_power`` p > 0, Y is drawn among X's adjacent components with
    probability proportional to (box diagonal)^p instead of uniformly: a modeller adds the main
    missing piece (a boat's hull, a rifle's body) before its trims, and uniform positives teach
    g that the many small trims of a kind are as likely as the one large piece.

    With probability ``mixed_query_fraction`` X is a mix of shapes, as an assembly a modeller or
    ``/assemble`` builds from catalog parts is: each of its components is, with probability 1/2,
    swapped for one of its look-alikes from another shape of the category, centred where the
    component was and rescaled per axis to its box (as the service's h fits a part). The
    complements Y and the negatives stay those of the original shape: a mixed chair without its
    back still lacks a back.
    """

    def __init__(self, ds: ProcessedDataset, n_points: int = 1000, query_negative_fraction: float = 0.0,
                 lookalike_negative_fraction: float = 0.0, lookalike_neighbours: int = 8,
                 removal_query_fraction: float = 0.0, positives: int = 1, augment: float = 0.0,
                 augment_strength: float = 1.0, augment_parts: bool = True, scale_augment: float = 0.0,
                 substitute_fraction: float = 0.0,
                 mixed_query_fraction: float = 0.0, layout_warp: float = 0.0,
                 shape_negative_fraction: float = 0.0, positive_size_power: float = 0.0,
                 categories: list[str] | None = None):
        for name, value in (("query_negative_fraction", query_negative_fraction),
                            ("lookalike_negative_fraction", lookalike_negative_fraction),
                            ("shape_negative_fraction", shape_negative_fraction),
                            ("removal_query_fraction", removal_query_fraction),
                            ("substitute_fraction", substitute_fraction),
                            ("mixed_query_fraction", mixed_query_fraction),
                            ("layout_warp", layout_warp)):
            if not 0.0 <= value <= 1.0:
                raise ValueError(f"{name} must be in [0, 1], got {value}")
        if positive_size_power < 0:
            raise ValueError(f"positive_size_power must be >= 0, got {positive_size_power}")
        check_negative_shares(query_negative_fraction, lookalike_negative_fraction, shape_negative_fraction,
                              "TripletSampler")
        self.ds = ds
        self.n_points = n_points
        self.query_negative_fraction = query_negative_fraction
        self.lookalike_negative_fraction = lookalike_negative_fraction
        self.shape_negative_fraction = shape_negative_fraction
        self.removal_query_fraction = removal_query_fraction
        self.positives, self.augment, self.scale_augment = positives, augment, scale_augment
        self.augment_strength, self.augment_parts = augment_strength, augment_parts
        self.substitute_fraction = substitute_fraction
        self.mixed_query_fraction = mixed_query_fraction
        self.layout_warp = layout_warp
        self.ranges = Augmentation()
        # Each component's box extents (component_descriptors owns the box), only for the options
        # that read them: the warp's half extents, and the size-drawn positives' diagonals.
        extents = component_descriptors(ds)[:, 3:] if max(layout_warp, positive_size_power) > 0 else None
        self.half = extents / 2 if extents is not None and layout_warp > 0 else None
        self.size_weight = (np.linalg.norm(extents.astype(np.float64), axis=1) ** positive_size_power
                            if extents is not None and positive_size_power > 0 else None)
        # The full collection's list, so that a subset (the train split) keeps the same indices.
        categories = categories if categories is not None else ds.categories()
        self.category_of_shape = np.array([categories.index(str(m.get("category", ""))) for m in ds.shapes],
                                          np.int64)
        self.lookalikes = (lookalike_components(ds, lookalike_neighbours)
                           if max(lookalike_negative_fraction, substitute_fraction, mixed_query_fraction) > 0
                           else None)
        self.shape_negatives = shape_lookalikes(ds) if shape_negative_fraction > 0 else None
        self.adj = ds.adjacency()
        self.eligible = [s for s in range(ds.n_shapes) if ds.first_comp[s + 1] - ds.first_comp[s] >= 2]
        assert self.eligible, "no shape has two or more components"

    def sample_triplet(self, rng: np.random.Generator) -> Triplet:
        ds = self.ds
        shape = self.eligible[int(rng.integers(len(self.eligible)))]
        nodes = ds.components_of(shape).tolist()
        r = int(rng.integers(1, len(nodes)))  # r in [1, n - 1]: at least one complement remains
        if self.removal_query_fraction > 0 and rng.random() < self.removal_query_fraction:
            # X is the shape minus a connected group of n - r components (usually one part): the
            # "everything but the legs" query, whose X need not be connected.
            removed = set(random_connected_subgraph(nodes, self.adj, len(nodes) - r, rng))
            query = [c for c in nodes if c not in removed]
        else:
            query = random_connected_subgraph(nodes, self.adj, r, rng)
        qset = set(query)
        neighbours = sorted(set().union(*(self.adj[c] for c in query)) - qset)
        if not neighbours:  # disconnected leftovers cannot happen after preprocessing; resample
            return self.sample_triplet(rng)
        if self.size_weight is None:
            positive = neighbours[int(rng.integers(len(neighbours)))]
        else:
            w = self.size_weight[neighbours]
            positive = neighbours[int(rng.choice(len(neighbours), p=w / w.sum()))]
        hard = self.query_negative_fraction + self.lookalike_negative_fraction + self.shape_negative_fraction
        u = rng.random() if hard > 0 else 1.0
        shape_negative = False
        if u < self.query_negative_fraction:
            negative = query[int(rng.integers(len(query)))]
        elif u < self.query_negative_fraction + self.lookalike_negative_fraction:
            lookalike = self._lookalike_of(query[int(rng.integers(len(query)))], rng)
            negative = lookalike if lookalike is not None else self._negative(qset | set(neighbours), rng)
        elif u < hard:
            assert self.shape_negatives is not None
            other = _draw(self.shape_negatives[positive], rng)
            negative = other if other is not None else self._negative(qset | set(neighbours), rng)
            shape_negative = other is not None
        else:
            negative = self._negative(qset | set(neighbours), rng)
        return Triplet(shape=shape, query=query, positive=positive, negative=negative,
                       missing=[c for c in nodes if c not in qset], shape_negative=shape_negative)

    def _negative(self, blocked: set[int], rng: np.random.Generator, tries: int = 64) -> int:
        """A random component outside ``blocked``: rejection sampling, then an explicit draw."""
        for _ in range(tries):
            negative = int(rng.integers(self.ds.n_components))
            if negative not in blocked:
                return negative
        # Only reached when nearly every component is blocked (tiny datasets): draw exactly.
        free = np.setdiff1d(np.arange(self.ds.n_components), np.fromiter(blocked, dtype=np.int64))
        if len(free) == 0:
            raise ValueError(f"no negative component exists: all {self.ds.n_components} components are in "
                             "the query or adjacent to it (the dataset needs more shapes)")
        return int(free[int(rng.integers(len(free)))])

    def batch(self, batch_size: int, rng: np.random.Generator) -> dict[str, np.ndarray]:
        """A batch of triplets as arrays.

        ``P`` holds up to ``positives`` components of X's complement set, the paper's positive
        Y first (``P[:, 0] == Y``), ``P_mask`` which of them are real (a query may lack fewer).
        A share ``augment`` of the triplets is augmented: the shape gets a random linear map and
        offset (its parts the same linear map: they stay centred), X point noise, a hole and
        even-by-component density, in the ranges of ``Augmentation``.
        ``Y_h`` is the part that h sees, rescaled per axis by exp(U(-a, a)) with
        ``a = scale_augment``; ``Y_log_scale`` is the log scale that undoes it. The part is the
        positive, or, for a share ``substitute_fraction`` of the triplets, a look-alike of it (see
        ``substitute``): then ``Y_log_scale`` also takes the look-alike to the positive's size.

        Shapes:
            X (B, N, 3), Y (B, N, 3), Z (B, N, 3), Y_h (B, N, 3) float32; Y_translation (B, 3),
            Y_log_scale (B, 3) float32; P (B, P, N, 3) float32, P_mask (B, P) bool;
            category (B,) int64; Z_shape (B,) bool: Z is a shape look-alike of Y.
        """
        n, npos = self.n_points, self.positives
        X = np.empty((batch_size, n, 3), np.float32)
        Y = np.empty_like(X)
        Z = np.empty_like(X)
        P = np.zeros((batch_size, npos, n, 3), np.float32)
        mask = np.zeros((batch_size, npos), bool)
        T = np.empty((batch_size, 3), np.float32)
        S = np.empty_like(X)                               # the part h sees, before its rescale
        fit = np.zeros((batch_size, 3), np.float32)        # log scale from S to Y's size
        category = np.empty(batch_size, np.int64)
        z_shape = np.zeros(batch_size, bool)
        ranges = self.ranges
        for b in range(batch_size):
            t = self.sample_triplet(rng)
            augmented = self.augment > 0 and rng.random() < self.augment
            by_area = not (augmented and rng.random() < ranges.uniform_density_probability)
            warp = self.warp_of(t.shape, rng)
            X[b] = self.query_points(t.query, n, rng, by_area, warp)
            Y[b] = sample_part(self.ds, t.positive, n, rng)
            Z[b] = sample_part(self.ds, t.negative, n, rng)
            T[b] = self.ds.translation[t.positive]
            others = [c for c in t.missing if c != t.positive]
            extra = rng.permutation(others)[:npos - 1].tolist() if npos > 1 else []
            category[b] = self.category_of_shape[t.shape]
            z_shape[b] = t.shape_negative
            substitute = self.substitute(t.positive, rng)
            S[b] = Y[b] if substitute is None else sample_part(self.ds, substitute, n, rng)
            first = int(self.ds.first_comp[t.shape])   # warp_of's arrays start at the shape's first
            if warp is not None:
                # The shape's own parts take the warp; S stays the catalog geometry h is given,
                # so the fitting scale below learns the warp's rescale of the positive.
                T[b] = warp[0][t.positive - first]
                Y[b] = Y[b] * warp[1][t.positive - first]
                if first <= t.negative < int(self.ds.first_comp[t.shape + 1]):
                    Z[b] = Z[b] * warp[1][t.negative - first]
            P[b, 0] = Y[b]
            for j, comp in enumerate(extra, start=1):
                P[b, j] = sample_part(self.ds, int(comp), n, rng)
                if warp is not None:
                    P[b, j] *= warp[1][int(comp) - first]
            mask[b, :1 + len(extra)] = True
            placed = Y[b]   # the positive as h must fit it: in the augmented shape's frame
            if augmented:
                A, offset = augmentation_transform(rng, self.augment_strength, ranges)
                X[b] = X[b] @ A.T + offset
                placed = Y[b] @ A.T
                if self.augment_parts:  # off: f and g see the parts as the catalog holds them
                    Y[b], Z[b], P[b] = placed, Z[b] @ A.T, P[b] @ A.T
                S[b] = S[b] @ A.T
                T[b] = T[b] @ A.T + offset
                X[b] += rng.normal(0.0, rng.uniform(0, ranges.noise * self.augment_strength), X[b].shape)
                if rng.random() < ranges.hole_probability:
                    X[b] = punch_hole(X[b], rng, ranges.hole_radius)
            if substitute is not None or warp is not None:
                fit[b] = substitute_log_scale(placed, S[b])
        a = self.scale_augment
        log_scale = rng.uniform(-a, a, (batch_size, 3)).astype(np.float32) if a > 0 \
            else np.zeros((batch_size, 3), np.float32)
        # The part h sees is S grown by exp(log_scale); the fitting scale undoes that (and takes a
        # look-alike to the positive's size).
        Y_h = S * np.exp(log_scale)[:, None, :]
        return {"X": X, "Y": Y, "Z": Z, "Y_translation": T, "Y_h": Y_h.astype(np.float32),
                "Y_log_scale": fit - log_scale, "P": P, "P_mask": mask, "category": category,
                "Z_shape": z_shape}

    def warp_of(self, shape: int, rng: np.random.Generator) -> tuple[np.ndarray, np.ndarray] | None:
        """For a share ``layout_warp`` of the triplets, the shape's components under a random
        ``layout_warp``: their new centres and per-axis scales, indexed from the shape's first
        component. None: the shape as it is.

        Why: h learned where each kind of part sits in the training styles and placed a part of a
        style it never saw there (a floor lamp's bulb at a table lamp's height: held-out style
        placement error 0.22 against 0.04 in style, docs/training.md); moved proportions make it
        read where the query leaves room.

        Shapes:
            returns centre (C, 3) float32, scale (C, 3) float32 for the shape's C components.
        """
        if self.half is None or rng.random() >= self.layout_warp:
            return None
        comps = self.ds.components_of(shape)
        knots, warped = layout_warp(rng, self.ranges)
        return warp_boxes(knots, warped, self.ds.translation[comps].astype(np.float64),
                          self.half[comps].astype(np.float64))

    def query_points(self, query: list[int], n: int, rng: np.random.Generator, by_area: bool = True,
                     warp: tuple[np.ndarray, np.ndarray] | None = None) -> np.ndarray:
        """X's samples: the query's own components, or for a share ``mixed_query_fraction`` of the
        queries a mix of look-alikes (see the class doc); ``warp`` (``warp_of``) moves and rescales
        the components.

        Shapes:
            returns (n, 3) float32.
        """
        mixed = self.mixed_query_fraction > 0 and rng.random() < self.mixed_query_fraction
        if not mixed and warp is None:
            return sample_assembly(self.ds, query, n, rng, by_area=by_area)
        ds = self.ds
        rows = np.asarray(query, dtype=np.int64)
        samples = ds.points[rows].astype(np.float32)                        # (r, S, 3) centred
        areas = ds.area[rows].astype(np.float64)
        translations = ds.translation[rows].astype(np.float32)
        if warp is not None:
            local = rows - int(ds.first_comp[ds.shape_of[rows[0]]])
            stretch = warp[1][local]
            samples = samples * stretch[:, None, :]
            areas = np.array([scaled_area(float(a), sc) for a, sc in zip(areas, stretch, strict=True)])
            translations = warp[0][local]
        if not mixed:
            return draw_area_weighted(samples, translations, areas, np.arange(len(rows)), n, rng, by_area)
        for j, comp in enumerate(query):
            other = self._lookalike_of(comp, rng) if rng.random() < 0.5 else None
            if other is None:
                continue
            scale = np.exp(substitute_log_scale(ds.points[comp].astype(np.float32),
                                                ds.points[other].astype(np.float32)))
            if warp is not None:
                scale = scale * stretch[j]
            samples[j] = ds.points[other] * scale
            areas[j] = scaled_area(float(ds.area[other]), scale)
        return draw_area_weighted(samples, translations, areas, np.arange(len(rows)), n, rng, by_area)

    def substitute(self, positive: int, rng: np.random.Generator) -> int | None:
        """For a share ``substitute_fraction`` of the triplets, a look-alike of the positive for h.

        Why: the service places (and fits in size) the parts retrieval returns, which are other
        shapes' parts, while h trained on rescaled true parts only learned to undo a random
        rescale: for a part of the right size it still predicted its kind's typical size (the
        placed-box IoU of the true part fell from 0.645 to 0.603 with fitting on, docs/training.md).
        A look-alike (one of the positive's nearest components of other shapes of the category,
        by box centre and extents: no labels) is such a part; h learns to put it where the
        positive was, at the positive's size. None: h sees the positive.
        """
        if self.substitute_fraction <= 0 or rng.random() >= self.substitute_fraction:
            return None
        return self._lookalike_of(positive, rng)

    def _lookalike_of(self, component: int, rng: np.random.Generator) -> int | None:
        """One of ``component``'s look-alikes, drawn uniformly; None when it has none."""
        assert self.lookalikes is not None
        return _draw(self.lookalikes[component], rng)


def _draw(candidates: np.ndarray, rng: np.random.Generator) -> int | None:
    """One of the row's components (-1 is padding), drawn uniformly; None when it has none."""
    candidates = candidates[candidates >= 0]
    return int(candidates[int(rng.integers(len(candidates)))]) if len(candidates) else None
