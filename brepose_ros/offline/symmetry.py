"""Compile-time symmetry detection: the rotations that map a part onto itself.

A camera cannot tell two poses of a part apart when a rotation of the part maps its edges
and silhouettes onto themselves: the image is the same. Such rotations are found here and
stored in the graph (``aspect_graph``) for the run-time twin check (``online.symmetry``) and
the evaluation (``evaluation.metrics``). Plain numpy/scipy, so STEP and mesh parts alike.

1. Two samplings of the part, each sample with an orientation: its edges (the sharp and
   smooth sections of the graph's views, deduplicated, every ``SAMPLE_SPACING`` diameters,
   with their direction) and its surface (random points of its triangle mesh by area, with
   their outward normal). Outlines are left out: a curved face's silhouette lies elsewhere in
   every view; the surface stands for it (the Motor1 holder is mostly outlines).
2. Candidate axes through the surface's centroid: the principal axes of the points and of
   the orientations, the dominant edge directions and normals, and the cross products,
   sums and differences of pairs and the signed sums of triples of them (a cube's face
   normals, edge mid-point axes and body diagonals).
3. Candidate rotations about each axis by k/n turns, n = 2..6, and by three generic angles
   (a continuous symmetry, such as a cylinder's, passes all three).
4. A candidate's *share* per sampling: the share of samples mapped within ``TOLERANCE``
   diameters of a like sample (an edge) or of a like sample's tangent plane (the surface).
   A candidate that passes a loose screen is aligned by ICP (rotation and translation: a
   near symmetry's axis need not pass through the centroid, which the odd feature shifts),
   then scored. Its share is the smaller of the two.

Shares of at least ``aspect_graph.EXACT_SYMMETRY_SHARE`` are exact symmetries (equivalent
poses); a candidate of which either sampling reaches ``NEAR_SHARE`` is a near one (a twin
the image must decide between).
"""
from __future__ import annotations

import itertools
from dataclasses import dataclass

import numpy as np
from scipy.spatial import cKDTree

from ..aspect_graph import EXACT_SYMMETRY_SHARE
from ..geometry import rotation_about
from .hidden_lines import OUTLINE

#: bump when a change finds other symmetries in the same graph: cached bench graphs
#: (bench/graphs.py) are then copied with their symmetries found anew. 2: discrete turns
#: about near continuous axes, mapped samples matched against all well-seen sections. 3: a near
#: symmetry that an exact discrete one turns into one kept already is that one
DETECTION_VERSION = 3
#: a rotated edge sample matches when an edge sample of like direction lies this close, in
#: model diameters: twice the compile's chord tolerance, so that polygonised curves match
#: their rotated selves, and far below any feature a camera resolves at a useful scale
TOLERANCE = 0.01
#: spacing of the edge samples, in diameters: well inside the tolerance
SAMPLE_SPACING = 0.004
#: directions alike within this angle (polygonised curves turn by up to ~15 deg per section)
DIRECTION_TOLERANCE_DEG = 25.0
#: a rotation mapping at least this share of the edges or of the surface onto itself is a near
#: symmetry, a twin the run-time check compares (which costs only time): the Motor1 holder,
#: which the estimator flipped by 176 degrees on clean images, maps 0.67 of its surface
NEAR_SHARE = 0.6
#: discrete rotations tried about every axis: k/n turns for the orders of common parts
ORDERS = (2, 3, 4, 5, 6)
#: ... and the other sampling at least this share: a plate's surface maps onto itself under a
#: half turn about any axis in its mid-plane (its faces onto each other's planes) while its
#: edges do not (0.03-0.09 of the notched plate's; the Motor1 holder's twin maps 0.24)
MIN_SHARE = 0.15
#: turns that no finite order below 7 shares: a rotation by all three maps a continuous symmetry
GENERIC_TURNS = (0.1234, 0.3771, 0.6180)
#: a grid cell of edge samples is kept when the views' sections reach it at least this share
#: of the times the most visible edges are (their 95th percentile; ``edge_cloud``)
MIN_SUPPORT = 0.1
#: ... but the samples a mapped one may land on need only this share, and up to this many:
#: which cells pass MIN_SUPPORT depends on how the view grid meets each edge, so an exact
#: turn maps well-seen samples onto cells that fell below it (the flange's six-fold turns
#: matched 0.85-0.88 of the samples against the kept ones, 0.975-0.978 against these)
TARGET_SUPPORT = 0.02
MAX_TARGETS = 60000
#: fewer edge samples than this are no edges to compare (a smooth scan)
MIN_EDGE_SAMPLES = 20
#: the surface, sampled evenly and free of the views' gaps, must map this share onto itself
#: for an exact symmetry: the edges may leave ``1 - EXACT_SYMMETRY_SHARE`` of their samples
#: unmatched (curves sampled differently in different views), which would hide a small
#: feature (the notched plate's half turn maps 0.95-0.96 of its edges on a 15-degree graph
#: but 0.986 of its surface; the flange's six-fold turns 0.996-0.998)
SURFACE_EXACT = 0.99
#: random samples of the surface, and how far (in tolerances) a mapped one looks for the
#: tangent plane of a like sample (the samples of a 100 mm part lie about 1 mm apart)
SURFACE_SAMPLES = 6000
SURFACE_REACH = 3.0
#: at most this many edge samples score a candidate (the spacing grows for larger clouds), and
#: at most this many are drawn from the sections before the grid and the support filter
MAX_SAMPLES = 6000
MAX_RAW_SAMPLES = 2_000_000
#: the loose screen before ICP: this many samples, matched within SCREEN_FACTOR tolerances
SCREEN_SAMPLES = 250
SCREEN_FACTOR = 3.0
#: samples the ICP aligns (a rigid map has 6 unknowns; more only cost time)
ALIGN_SAMPLES = 1500
#: ICP rounds, their match radius in tolerances shrinking to the final one
ICP_RADII = (3.0, 2.0, 1.0, 1.0)
#: dominant edge directions: peaks of at least this share of the samples within 5 degrees
DOMINANT_SHARE = 0.03
MAX_DOMINANT = 8
#: rotations closer than this are the same symmetry (the best-scoring one is kept)
SAME_ROTATION_DEG = 3.0
#: near symmetries closer than this are one twin (the ICP of a near symmetry settles a few
#: degrees apart from different candidate axes; the run-time refinement closes the rest)
SAME_NEAR_DEG = 25.0
#: near symmetries kept at most, the best shares first: each costs a twin check per image
MAX_NEAR = 4
#: a candidate this near a symmetry found already is not aligned again (candidate axes from
#: different sums of noisy directions differ by a few degrees)
KNOWN_DEG = 6.0
#: kept at most: a cube has 23 symmetries besides the identity
MAX_SYMMETRIES = 24
MAX_AXES = 3


@dataclass
class Symmetries:
    """A part's symmetries, in the model frame (metres).

    Discrete ones map a model point X to ``rotations[k] @ X + translations[k]``; continuous
    ones turn the part by any angle about ``axes[c] = (a point on the axis, its unit
    direction)``. ``shares`` and ``axis_shares`` are the share of edge samples mapped onto
    edges (module doc): exact at ``EXACT_SYMMETRY_SHARE`` and above, near below.
    """

    rotations: np.ndarray  # (K, 3, 3)
    translations: np.ndarray  # (K, 3)
    shares: np.ndarray  # (K,)
    axes: np.ndarray  # (C, 2, 3)
    axis_shares: np.ndarray  # (C,)

    @classmethod
    def none(cls) -> Symmetries:
        return cls(np.zeros((0, 3, 3)), np.zeros((0, 3)), np.zeros(0), np.zeros((0, 2, 3)), np.zeros(0))


def detect_symmetries(seg_3d: np.ndarray, kinds: np.ndarray, diameter: float,
                      surface: tuple[np.ndarray, np.ndarray] | None = None) -> Symmetries:
    """The exact and near symmetries of the part whose edge sections (S, 2, 3) of kinds (S,)
    an aspect graph holds, and whose ``surface`` is the triangle mesh (vertices, triangles),
    if given (module doc)."""
    tolerance = TOLERANCE * diameter
    clouds = []
    points, directions = edge_cloud(seg_3d[kinds != OUTLINE], diameter)
    if len(points) >= MIN_EDGE_SAMPLES:
        targets = edge_cloud(seg_3d[kinds != OUTLINE], diameter, TARGET_SUPPORT, MAX_TARGETS)
        clouds.append(OrientedCloud(points, directions, tolerance, on_surface=False, targets=targets))
    if surface is not None:
        clouds.append(OrientedCloud(*surface_samples(*surface), tolerance, on_surface=True))
    if not clouds:
        return Symmetries.none()  # no sharp edges and no surface: nothing to compare
    samples = PartSamples(clouds)
    center = clouds[-1].points.mean(axis=0)  # the surface's centroid if there is one
    found: list[tuple[float, np.ndarray, np.ndarray]] = []
    axes: list[tuple[float, np.ndarray]] = []  # (share, (point, direction))
    for axis in candidate_axes(clouds, center):
        continuous = _continuous_axis(samples, axis, center)
        if continuous is not None:
            axes.append(continuous)
            if continuous[0] >= EXACT_SYMMETRY_SHARE:
                continue
            # a near continuous axis may still carry exact or near turns (a flange's bolt
            # circle, a shaft's flat turned half round): they are tried about the refined axis
            axis = continuous[1][1]
        for n in ORDERS:
            for k in range(1, n):
                if np.gcd(k, n) != 1:
                    continue  # the same rotation as k/n in lowest terms
                S = rotation_about(axis, 2 * np.pi * k / n)
                known = [axis[1] for share, axis in axes if share >= EXACT_SYMMETRY_SHARE]
                if any(_same_rotation(S, other, known, KNOWN_DEG) for _, other, _ in found):
                    continue  # found already from another candidate axis
                if not samples.passes_screen(S, center - S @ center):
                    continue
                S, b = samples.align(S, center - S @ center)
                share = samples.share(S, b)
                if share is not None:
                    found.append((share, S, b))
    axes = _distinct_axes(axes)
    exact_axes = [axis[1] for share, axis in axes if share >= EXACT_SYMMETRY_SHARE]
    kept: list[tuple[float, np.ndarray, np.ndarray]] = []
    for share, S, b in sorted(found, key=lambda f: -f[0]):
        # the identity (the ICP may fall back onto it), or a symmetry kept already: alike up
        # to a turn about an exact continuous axis, or, for a near one, up to an exact discrete
        # symmetry (kept first, their shares being higher): the screw's near quarter turns
        # either way are one map of the part under its exact half turn, and two copies of one
        # twin leave the run-time twin check no margin between them
        within = SAME_ROTATION_DEG if share >= EXACT_SYMMETRY_SHARE else SAME_NEAR_DEG
        exact = [k[1] for k in kept if k[0] >= EXACT_SYMMETRY_SHARE] if share < EXACT_SYMMETRY_SHARE else []
        known = [np.eye(3)] + [k[1] for k in kept]
        if any(_same_rotation(S, E @ other, exact_axes, within) for other in known for E in [np.eye(3)] + exact):
            continue
        if share < EXACT_SYMMETRY_SHARE and sum(k[0] < EXACT_SYMMETRY_SHARE for k in kept) == MAX_NEAR:
            continue
        kept.append((share, S, b))
    kept = kept[:MAX_SYMMETRIES]
    return Symmetries(
        rotations=np.array([S for _, S, _ in kept]).reshape(-1, 3, 3),
        translations=np.array([b for _, _, b in kept]).reshape(-1, 3),
        shares=np.array([s for s, _, _ in kept], dtype=np.float64),
        axes=np.array([axis for _, axis in axes]).reshape(-1, 2, 3),
        axis_shares=np.array([s for s, _ in axes], dtype=np.float64))


def surface_samples(vertices: np.ndarray, triangles: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    """``SURFACE_SAMPLES`` points spread over a triangle mesh by area (the same ones on every
    run) and the outward unit normals of their triangles."""
    corners = vertices[triangles]
    normals = np.cross(corners[:, 1] - corners[:, 0], corners[:, 2] - corners[:, 0])
    area = np.linalg.norm(normals, axis=1)
    keep = area > 0
    corners, normals, area = corners[keep], normals[keep] / area[keep, None], area[keep]
    rng = np.random.default_rng(0)
    pick = rng.choice(len(area), SURFACE_SAMPLES, p=area / area.sum())
    u, v = rng.random((2, SURFACE_SAMPLES))
    flip = u + v > 1
    u[flip], v[flip] = 1 - u[flip], 1 - v[flip]
    chosen = corners[pick]
    points = chosen[:, 0] + u[:, None] * (chosen[:, 1] - chosen[:, 0]) + v[:, None] * (chosen[:, 2] - chosen[:, 0])
    return points, normals[pick]


def edge_cloud(seg_3d: np.ndarray, diameter: float, min_support: float = MIN_SUPPORT,
               max_samples: int = MAX_SAMPLES) -> tuple[np.ndarray, np.ndarray]:
    """Samples (N, 3) along the distinct edge sections and their unit directions (N, 3).

    Views repeat the same sections (or pieces of them), so the sections are deduplicated
    first and the samples then on a grid of the spacing, per direction. A grid cell that few
    views' sections reach is dropped (``min_support``): the hidden-line removal of a view
    that sees a face edge-on may lift a 2D line onto the wrong 3D edge (a face's diagonal), and
    a curve seen edge-on becomes a chord across it, but only in those few views."""
    if len(seg_3d) == 0:
        return np.zeros((0, 3)), np.zeros((0, 3))
    ends = np.round(seg_3d / (1e-4 * diameter)).astype(np.int64)
    swap = _lexless(ends[:, 1], ends[:, 0])
    ends[swap] = ends[swap][:, ::-1]
    _, first, views = np.unique(ends.reshape(len(ends), 6), axis=0, return_index=True, return_counts=True)
    segments = np.array(seg_3d[first])
    delta = segments[:, 1] - segments[:, 0]
    lengths = np.linalg.norm(delta, axis=1)
    segments, delta, lengths, views = (a[lengths > 0] for a in (segments, delta, lengths, views))
    # the sections hold many stray ones, so the raw samples are capped, not the kept ones
    spacing = max(SAMPLE_SPACING * diameter, lengths.sum() / MAX_RAW_SAMPLES)
    for _ in range(8):  # the grid keeps about 1 sample per cell and direction: widen until few enough
        counts = np.maximum(np.ceil(lengths / spacing).astype(int), 1)
        segment = np.repeat(np.arange(len(counts)), counts)
        frac = (np.arange(len(segment)) - np.repeat(np.cumsum(counts) - counts, counts) + 0.5) / counts[segment]
        points = segments[segment, 0] + frac[:, None] * delta[segment]
        directions = (delta / lengths[:, None])[segment]
        canonical = directions * np.where(_first_nonzero_sign(directions) < 0, -1.0, 1.0)[:, None]
        keys = np.concatenate([np.floor(points / spacing), np.round(canonical * 3.0)], axis=1).astype(np.int64)
        _, unique, cell = np.unique(keys, axis=0, return_index=True, return_inverse=True)
        support = np.bincount(cell.ravel(), weights=views[segment])
        unique = unique[support >= min_support * np.quantile(support, 0.95)]
        if len(unique) <= max_samples:
            break
        spacing *= np.sqrt(len(unique) / max_samples) * 1.1
    return points[unique], directions[unique]


class OrientedCloud:
    """Samples with a direction (edges, sign-free) or an outward normal (surface), in a k-d
    tree, for scoring and aligning candidate rotations.

    A mapped edge sample matches a like sample of ``targets`` (by default the samples
    themselves) within the tolerance; a mapped surface
    sample matches when it lies within the tolerance of the tangent plane of a like surface
    sample within ``SURFACE_REACH`` tolerances (random surface samples lie farther apart than
    the tolerance, and a plane does not care where along it the sample falls)."""

    #: neighbours looked at per sample: the nearest may run across (at a corner)
    NEIGHBOURS = 6

    def __init__(self, points: np.ndarray, directions: np.ndarray, tolerance: float, on_surface: bool,
                 targets: tuple[np.ndarray, np.ndarray] | None = None):
        self.points, self.directions, self.tolerance = points, directions, tolerance
        self.target_points, self.target_directions = targets if targets is not None else (points, directions)
        self.on_surface = on_surface
        self.reach = SURFACE_REACH * tolerance if on_surface else tolerance
        self.tree = cKDTree(self.target_points)
        self.min_cos = np.cos(np.radians(DIRECTION_TOLERANCE_DEG))
        rng = np.random.default_rng(0)
        self.screen = rng.choice(len(points), min(SCREEN_SAMPLES, len(points)), replace=False)
        self.fit = rng.choice(len(points), min(ALIGN_SAMPLES, len(points)), replace=False)

    def matches(self, S: np.ndarray, b: np.ndarray, subset=slice(None), factor: float = 1.0):
        """For the samples of ``subset`` mapped by X -> S X + b: whether each found a like
        target within ``factor`` tolerances, and which (its index; any where not found)."""
        mapped = self.points[subset] @ S.T + b
        turned = self.directions[subset] @ S.T
        distance, index = self.tree.query(mapped, k=self.NEIGHBOURS, distance_upper_bound=factor * self.reach)
        index = np.minimum(index, len(self.target_points) - 1)
        cos = np.einsum("nd,nkd->nk", turned, self.target_directions[index])
        good = np.isfinite(distance) & ((cos if self.on_surface else np.abs(cos)) >= self.min_cos)
        if self.on_surface:
            offset = np.einsum("nkd,nkd->nk", mapped[:, None] - self.target_points[index],
                               self.target_directions[index])
            good &= np.abs(offset) <= factor * self.tolerance
        first = np.argmax(good, axis=1)  # the nearest like sample: query sorts by distance
        return good.any(axis=1), index[np.arange(len(index)), first]

    def share(self, S: np.ndarray, b: np.ndarray, subset=slice(None), factor: float = 1.0) -> float:
        """Share of the samples mapped onto like samples by X -> S X + b."""
        return float(np.mean(self.matches(S, b, subset, factor)[0]))


class PartSamples:
    """The part's edge and surface samples together: a candidate is near a symmetry when
    either maps onto itself, exact when both do (its share is the smaller)."""

    def __init__(self, clouds: list[OrientedCloud]):
        self.clouds = clouds

    def passes_screen(self, S: np.ndarray, b: np.ndarray) -> bool:
        """The loose test before the ICP: on a few samples, within ``SCREEN_FACTOR`` tolerances."""
        return any(c.share(S, b, subset=c.screen, factor=SCREEN_FACTOR) >= NEAR_SHARE for c in self.clouds)

    def share(self, S: np.ndarray, b: np.ndarray) -> float | None:
        """The smaller share of the clouds, or None when no cloud reaches ``NEAR_SHARE`` or
        one stays below ``MIN_SHARE``; below exact when the surface's is below
        ``SURFACE_EXACT``."""
        shares = [c.share(S, b) for c in self.clouds]
        if max(shares) < NEAR_SHARE or min(shares) < MIN_SHARE:
            return None
        if any(c.on_surface and share < SURFACE_EXACT for c, share in zip(self.clouds, shares)):
            return min(min(shares), float(np.nextafter(EXACT_SYMMETRY_SHARE, 0.0)))
        return min(shares)

    def align(self, S: np.ndarray, b: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
        """ICP: the rigid map near X -> S X + b that best maps the samples onto their like
        neighbours, the match radius shrinking round by round (``ICP_RADII``); edges and
        surface weigh alike."""
        for factor in ICP_RADII:
            source, target, weights = [], [], []
            for cloud in self.clouds:
                found, index = cloud.matches(S, b, subset=cloud.fit, factor=factor)
                source.append(cloud.points[cloud.fit][found])
                target.append(cloud.target_points[index[found]])
                weights.append(np.full(found.sum(), 1.0 / max(found.sum(), 1)))
            if sum(len(w) for w in weights) < 6:
                break
            S, b = rigid_fit(np.concatenate(source), np.concatenate(target), np.concatenate(weights))
        return S, b


def rigid_fit(source: np.ndarray, target: np.ndarray, weights: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    """Kabsch: the rotation S and translation b minimising sum w |S source + b - target|^2."""
    weights = weights / weights.sum()
    mu_s, mu_t = weights @ source, weights @ target
    u, _, vt = np.linalg.svd((target - mu_t).T @ ((source - mu_s) * weights[:, None]))
    d = np.sign(np.linalg.det(u @ vt))
    S = u @ np.diag([1.0, 1.0, d]) @ vt
    return S, mu_t - S @ mu_s


def candidate_axes(clouds: list[OrientedCloud], center: np.ndarray) -> list[np.ndarray]:
    """Unit axes a symmetry may turn about (module doc), distinct up to sign."""
    axes, dominant = [], []
    for cloud in clouds:
        offsets = cloud.points - center
        axes += list(np.linalg.eigh(offsets.T @ offsets)[1].T)
        axes += list(np.linalg.eigh(cloud.directions.T @ cloud.directions)[1].T)
        dominant += dominant_directions(cloud.directions)
    dominant = _distinct(dominant)[:MAX_DOMINANT]
    axes += dominant
    for a, b in itertools.combinations(dominant, 2):
        axes += [np.cross(a, b), a + b, a - b]
    for a, b, c in itertools.combinations(dominant[:4], 3):
        axes += [a + b + c, a + b - c, a - b + c, -a + b + c]
    return _distinct(axes)


def _distinct(axes: list[np.ndarray]) -> list[np.ndarray]:
    """The unit axes, each once up to sign (within a degree), in order."""
    distinct: list[np.ndarray] = []
    for axis in axes:
        norm = np.linalg.norm(axis)
        if norm < 1e-6:
            continue
        axis = axis / norm
        if all(abs(axis @ other) < np.cos(np.radians(1.0)) for other in distinct):
            distinct.append(axis)
    return distinct


def dominant_directions(directions: np.ndarray) -> list[np.ndarray]:
    """The edge directions shared by many samples (a box's three), strongest first."""
    rng = np.random.default_rng(1)
    sample = directions[rng.choice(len(directions), min(1500, len(directions)), replace=False)]
    near = np.abs(sample @ sample.T) >= np.cos(np.radians(5.0))
    left = np.ones(len(sample), bool)
    out = []
    while len(out) < MAX_DOMINANT:
        counts = (near & left[None, :]).sum(axis=1) * left
        best = int(np.argmax(counts))
        if counts[best] < DOMINANT_SHARE * len(sample):
            break
        members = sample[near[best] & left]
        out.append(np.linalg.eigh(members.T @ members)[1][:, -1])
        left &= ~near[best]
    return out


def _continuous_axis(samples: PartSamples, axis: np.ndarray, center: np.ndarray) -> tuple[float, np.ndarray] | None:
    """(share, (point, direction)) of the continuous symmetry about (nearly) ``axis``, or
    None: turns by each of ``GENERIC_TURNS`` must map the edges onto edges. The axis, from
    the noisy principal axes, is refined by aligning each turn (ICP)."""
    turns = []
    for turn in GENERIC_TURNS:
        S = rotation_about(axis, 2 * np.pi * turn)
        if not samples.passes_screen(S, center - S @ center):
            return None
        turns.append(samples.align(S, center - S @ center))
    shares = [samples.share(S, b) for S, b in turns]
    if any(share is None for share in shares):
        return None
    directions = np.array([_rotation_axis(S) for S, _ in turns])
    directions *= np.sign(directions @ axis)[:, None]
    direction = directions.mean(axis=0) / np.linalg.norm(directions.mean(axis=0))
    # the axis passes through the fixed points of the turns X -> S X + b: (I - S) p = b
    stacked = np.concatenate([np.eye(3) - S for S, _ in turns])
    point = np.linalg.lstsq(stacked, np.concatenate([b for _, b in turns]), rcond=None)[0]
    point = center + (point - center) - ((point - center) @ direction) * direction  # nearest the centre
    return min(shares), np.array([point, direction])


def _rotation_axis(S: np.ndarray) -> np.ndarray:
    """The unit axis of a rotation (its eigenvector of eigenvalue 1)."""
    w, v = np.linalg.eig(S)
    axis = np.real(v[:, np.argmin(np.abs(w - 1.0))])
    return axis / np.linalg.norm(axis)


def _same_rotation(S: np.ndarray, other: np.ndarray, continuous_axes: list[np.ndarray],
                   within_deg: float = SAME_ROTATION_DEG) -> bool:
    """Whether S and ``other`` differ by less than ``within_deg`` or by a turn about one of
    the continuous axes (then both map that axis alike)."""
    difference = S.T @ other
    if np.degrees(np.arccos(np.clip((np.trace(difference) - 1.0) / 2.0, -1.0, 1.0))) < within_deg:
        return True
    return any(np.linalg.norm(difference @ axis - axis) < np.radians(within_deg) for axis in continuous_axes)


def _distinct_axes(axes: list[tuple[float, np.ndarray]]) -> list[tuple[float, np.ndarray]]:
    kept: list[tuple[float, np.ndarray]] = []
    for share, axis in sorted(axes, key=lambda a: -a[0]):
        if all(abs(axis[1] @ other[1]) < np.cos(np.radians(SAME_ROTATION_DEG)) for _, other in kept):
            kept.append((share, axis))
    return kept[:MAX_AXES]


def _lexless(a: np.ndarray, b: np.ndarray) -> np.ndarray:
    """Row-wise: whether integer rows of ``a`` sort before those of ``b``."""
    differ = a != b
    first = np.argmax(differ, axis=1)
    rows = np.arange(len(a))
    return differ.any(axis=1) & (a[rows, first] < b[rows, first])


def _first_nonzero_sign(v: np.ndarray) -> np.ndarray:
    """Sign of each row's first clearly non-zero component (a direction's canonical sign)."""
    nonzero = np.abs(v) > 1e-9
    return np.sign(v[np.arange(len(v)), np.argmax(nonzero, axis=1)])
