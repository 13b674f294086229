"""Stage 1 for meshes: the visible edges of a triangle mesh seen from one direction, as
line sections with 3D end points, like ``hidden_lines`` gives them for a B-Rep.

A mesh has no B-Rep edges, so the lines an image shows are found on the triangles:

* **creases** (kind SHARP): edges whose two triangles meet at more than the crease angle.
  A scanned surface is noisy, so the dihedral angle is measured between face normals
  smoothed by a bilateral filter (neighbours whose normals differ a lot, i.e. across a real
  crease, hardly count: ``_smoothed_normals``); crease networks shorter in total than
  ``MIN_CREASE_LENGTH`` are noise and dropped; the remaining crease chains are smoothed
  along themselves (``_smooth_chains``), so that a crease that zig-zags along the triangles
  of a scan becomes a straight or smooth line. Edges of one triangle or of more than two
  (the rim of an open scan, a seam) are lines too.
* **outlines** (kind OUTLINE): silhouettes of the smooth regions, where the surface turns
  from facing the camera to facing away. Between the creases the normals are averaged per
  vertex (a vertex touching several smooth regions gets one normal per region), and the
  outline is traced where the interpolated normal is perpendicular to the viewing direction,
  one piece per triangle it crosses (the "interpolated contour" of Hertzmann and Zorin,
  2000). That gives smooth curves on a noisy scan, where the edges between front- and
  back-facing triangles zig-zag by a triangle; on a cylinder both are the same straight line.

Visibility is decided by an exact depth test against the triangles rather than OCCT's
HLRBRep_PolyAlgo: the mesh would first have to become a B-Rep of one face per smooth region
with its creases as edges, and the polygonal HLR of 10,000-50,000 triangles per view is far
slower than testing a few thousand points. Every candidate piece is cut into pieces of at
most the chord tolerance; a piece is visible when no front-facing triangle covers its
midpoint in the view and lies more than ``DEPTH_TOLERANCE`` in front of it (the triangles
are binned on a grid in the view, so each point meets only the few triangles near it). A
crease only counts where one of its triangles faces the camera: an edge between two
back-facing triangles is hidden on a closed surface even where no other triangle lies
exactly in front of it (the back edges of a cube seen face-on).

The visible pieces are chained, simplified with the chord tolerance and cut into sections
as B-Rep curves are (``hidden_lines.line_sections``; the whole tolerance goes to the 2D
simplification, as a mesh polyline needs no sampling); chains shorter than
``MIN_CHAIN_LENGTH`` (the outlines of the bumps of a scan) are dropped.
"""
from __future__ import annotations

import numpy as np
from scipy.sparse import coo_matrix, diags
from scipy.sparse.csgraph import connected_components

from .hidden_lines import (DEFAULT_CHORD_TOLERANCE, DEFAULT_MIN_LENGTH, OUTLINE, SHARP, ViewSegments,
                           line_sections, view_coordinates)
from .mesh import MeshPart, edge_topology

#: Dihedral angle (degrees, between smoothed face normals) above which a mesh edge is a
#: crease. Blender's auto-smooth default; the facets of a 32-sided cylinder (11 degrees)
#: stay smooth, a chamfer of 45 degrees is a crease.
DEFAULT_CREASE_ANGLE_DEG = 30.0
#: Rounds of the bilateral normal filter and its range: neighbours whose normals differ by
#: much more than this angle (a real crease) barely mix; scan noise of a few degrees does.
NORMAL_SMOOTHING_ROUNDS = 4
NORMAL_SMOOTHING_DEG = 15.0
#: A connected crease network shorter in total than this fraction of the diameter is noise
#: (a lone sharp triangle of a scan), not a feature an image line detector could find.
MIN_CREASE_LENGTH = 0.05
#: Taubin smoothing of crease chains (rounds, and the shrink / inflate factors of each):
#: zig-zags of one or two edges vanish, a 64-gon circle shrinks by 0.01 % (the classic
#: -0.53 would inflate it by 0.3 %).
CHAIN_SMOOTHING_ROUNDS = 20
CHAIN_SMOOTHING = (0.5, -0.5)
#: Visible chains shorter than this fraction of the diameter (in the view) are dropped.
MIN_CHAIN_LENGTH = 0.02
#: A triangle hides a point only when it is nearer by more than this fraction of the
#: diameter: chains are smoothed and outlines interpolated inside triangles, so their
#: points lie off the surface by a small fraction of a triangle.
DEPTH_TOLERANCE = 0.005
#: Average number of grid cells a triangle may be binned into for the depth test: bounds
#: its memory and time on meshes of long slivers.
OCCLUDER_ENTRIES = 16
#: A triangle faces the camera when its normal points towards it by more than this cosine
#: (a face seen exactly edge-on faces neither way).
_FRONT_COSINE = 1e-9
#: End points closer than this (fraction of the diameter) are the same point.
_SAME_POINT = 1e-6


class MeshLineRemover:
    """Visible creases and outlines of one mesh, view after view (``hidden_lines.
    HiddenLineRemover``'s interface); holds what does not depend on the view."""

    def __init__(self, part: MeshPart, chord_tolerance: float = DEFAULT_CHORD_TOLERANCE,
                 min_length: float = DEFAULT_MIN_LENGTH, crease_angle_deg: float = DEFAULT_CREASE_ANGLE_DEG):
        self.check_options(chord_tolerance, min_length, crease_angle_deg)
        self.part = part
        d = part.diameter
        self.chord, self.min_length, self.same_point = chord_tolerance * d, min_length * d, _SAME_POINT * d
        self.vertices, self.triangles = part.vertices, part.triangles
        corners = self.vertices[self.triangles]
        cross = np.cross(corners[:, 1] - corners[:, 0], corners[:, 2] - corners[:, 0])
        area = np.linalg.norm(cross, axis=1)
        self.face_normals = cross / area[:, None]
        topology = edge_topology(self.triangles)
        smoothed = _smoothed_normals(self.face_normals, area, topology)
        crease = _creases(self.vertices, smoothed, topology, np.radians(crease_angle_deg), MIN_CREASE_LENGTH * d)
        self.crease_ends = topology.vertices[crease]
        self.crease_segments = _smooth_chains(self.vertices, self.crease_ends)
        self.crease_faces = topology.faces[crease]
        self.corner_region, self.region_normals = _smooth_regions(self.triangles, smoothed, area, topology, crease)
        self.cell = _occluder_cell(corners, d)

    @staticmethod
    def check_options(chord_tolerance: float, min_length: float, crease_angle_deg: float) -> None:
        """ValueError for options no mesh could use (checked before any work starts)."""
        if not 0.0 < chord_tolerance <= 0.1:
            raise ValueError(f"chord tolerance must be in (0, 0.1] of the diameter, got {chord_tolerance}")
        if not 0.0 <= min_length <= 0.5:
            raise ValueError(f"minimum section length must be in [0, 0.5] of the diameter, got {min_length}")
        if not 0.0 < crease_angle_deg < 180.0:
            raise ValueError(f"crease angle must be in (0, 180) degrees, got {crease_angle_deg}")

    def segments(self, rotation: np.ndarray) -> ViewSegments:
        """Visible sections seen with R_view = ``rotation`` (rows x, y, z of the camera)."""
        rotation = np.asarray(rotation, dtype=float)
        direction = rotation[2]
        front = self.face_normals @ direction < -_FRONT_COSINE
        faces = self.crease_faces
        facing = np.where(faces >= 0, front[np.maximum(faces, 0)], True).any(axis=1)
        creases = self.crease_segments[facing]
        outlines, crossed = self.outline_segments(direction)
        candidates = np.concatenate([creases, outlines])
        kinds = np.concatenate([np.full(len(creases), SHARP), np.full(len(outlines), OUTLINE)])
        own = np.concatenate([self.crease_ends[facing][:, [0, 1, 1]], self.triangles[crossed]])
        pieces, owner = self._visible_pieces(candidates, own, rotation, front)
        polylines = list(zip(pieces, kinds[owner]))
        # a B-Rep curve spends half the chord tolerance on its sampling and simplifies at the
        # other half; a mesh polyline needs no sampling, so it simplifies at the whole
        return line_sections(polylines, rotation, self.part.center, 2.0 * self.chord, self.same_point,
                             self.min_length, MIN_CHAIN_LENGTH * self.part.diameter, loops_from_corners=True)

    def outline_segments(self, direction: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
        """(K, 2, 3) pieces of the interpolated outline, where the region normals, linearly
        interpolated over each triangle, are perpendicular to ``direction``, and the (K,)
        triangles they cross. Each crossing is computed from the edge's lower region index,
        so neighbours share it exactly."""
        facing = (self.region_normals @ direction)[self.corner_region]  # (M, 3)
        regions = self.corner_region
        ahead = facing > 0.0
        crossed = ahead.any(axis=1) & ~ahead.all(axis=1)
        tri, facing, regions, ahead = self.triangles[crossed], facing[crossed], regions[crossed], ahead[crossed]
        points, cut = [], []
        for i, j in ((0, 1), (1, 2), (2, 0)):
            swap = regions[:, i] > regions[:, j]
            lo, hi = np.where(swap, j, i), np.where(swap, i, j)
            rows = np.arange(len(tri))
            f_lo, f_hi = facing[rows, lo], facing[rows, hi]
            v_lo, v_hi = self.vertices[tri[rows, lo]], self.vertices[tri[rows, hi]]
            crossing = ahead[:, i] != ahead[:, j]
            t = np.where(crossing, f_lo / np.where(crossing, f_lo - f_hi, 1.0), 0.0)
            points.append(v_lo + t[:, None] * (v_hi - v_lo))
            cut.append(crossing)
        points, cut = np.stack(points, axis=1), np.stack(cut, axis=1)
        first_two = np.argsort(~cut, axis=1, kind="stable")[:, :2]
        return np.take_along_axis(points, first_two[:, :, None], axis=1), np.flatnonzero(crossed)

    def _visible_pieces(self, candidates: np.ndarray, own: np.ndarray, rotation: np.ndarray, front: np.ndarray):
        """The visible runs of the candidate segments (C, 2, 3): a list of (n, 3) polylines
        and, for each, the index of the candidate it lies on. ``own`` (C, 3) are the mesh
        vertices a candidate is made of (a crease's two, an outline piece's triangle's three):
        triangles touching them cannot hide it (``_hidden``)."""
        if len(candidates) == 0:
            return [], np.zeros(0, dtype=np.int64)
        xy = view_coordinates(candidates, rotation, self.part.center)
        count = np.maximum(1, np.ceil(np.linalg.norm(xy[:, 1] - xy[:, 0], axis=1) / self.chord)).astype(np.int64)
        owner = np.repeat(np.arange(len(candidates)), count)
        step = np.arange(len(owner)) - np.repeat(np.cumsum(count) - count, count)
        middle = (step + 0.5) / count[owner]
        points = candidates[owner, 0] + middle[:, None] * (candidates[owner, 1] - candidates[owner, 0])
        visible = ~self._hidden(points, own[owner], rotation, front)
        # runs of consecutive visible pieces of one candidate: steps start..stop, both included
        starts = np.flatnonzero(visible & ~np.r_[False, visible[:-1] & (owner[1:] == owner[:-1])])
        stops = np.flatnonzero(visible & ~np.r_[visible[1:] & (owner[1:] == owner[:-1]), False])
        c = owner[starts]
        fractions = np.stack([step[starts], step[stops] + 1], axis=1) / count[c][:, None]
        runs = candidates[c, :1] + fractions[:, :, None] * (candidates[c, 1:] - candidates[c, :1])
        return list(runs), c

    def _hidden(self, points: np.ndarray, own: np.ndarray, rotation: np.ndarray, front: np.ndarray) -> np.ndarray:
        """(P,) bool: a front-facing triangle covers the point in the view and lies more than
        DEPTH_TOLERANCE in front of it, other than the triangles touching the point's ``own``
        (P, 3) vertices: smoothed creases and interpolated outlines lie a little off their
        own triangles, and a triangle seen at a grazing angle turns that into a large depth.
        Triangles are binned by their 2D bounding boxes on a grid of ``self.cell``; each
        point is tested against the triangles of its cell."""
        view = (self.vertices - self.part.center) @ rotation.T
        tri = self.triangles[front]
        corners = view[tri]  # (K, 3, 3): x, y, depth
        origin = view[:, :2].min(axis=0)
        size = np.floor((view[:, :2].max(axis=0) - origin) / self.cell).astype(np.int64) + 1
        a, b, c = corners[:, 0], corners[:, 1], corners[:, 2]
        lo = np.floor((np.minimum(np.minimum(a[:, :2], b[:, :2]), c[:, :2]) - origin) / self.cell).astype(np.int64)
        hi = np.floor((np.maximum(np.maximum(a[:, :2], b[:, :2]), c[:, :2]) - origin) / self.cell).astype(np.int64)
        span = hi - lo + 1
        per_triangle = span[:, 0] * span[:, 1]
        entry_tri = np.repeat(np.arange(len(tri)), per_triangle)
        k = np.arange(len(entry_tri)) - np.repeat(np.cumsum(per_triangle) - per_triangle, per_triangle)
        cell_x = lo[entry_tri, 0] + k % span[entry_tri, 0]
        cell_y = lo[entry_tri, 1] + k // span[entry_tri, 0]
        key = cell_y * size[0] + cell_x
        order = np.argsort(key, kind="stable")
        key, entry_tri = key[order], entry_tri[order]
        bounds = np.searchsorted(key, np.arange(size[0] * size[1] + 1))

        p = (points - self.part.center) @ rotation.T
        cell = np.floor((p[:, :2] - origin) / self.cell).astype(np.int64)
        inside_grid = np.all((cell >= 0) & (cell < size), axis=1)
        point_key = np.where(inside_grid, cell[:, 1] * size[0] + cell[:, 0], 0)
        first, n = bounds[point_key], np.where(inside_grid, bounds[point_key + 1] - bounds[point_key], 0)
        pair_point = np.repeat(np.arange(len(p)), n)
        pair_tri = entry_tri[np.repeat(first, n) + np.arange(n.sum()) - np.repeat(np.cumsum(n) - n, n)]
        # only a triangle that reaches nearer than the point can hide it: most pairs fail this
        reach = p[:, 2] - DEPTH_TOLERANCE * self.part.diameter
        nearer = np.minimum(np.minimum(a[:, 2], b[:, 2]), c[:, 2])[pair_tri] < reach[pair_point]
        pair_point, pair_tri = pair_point[nearer], pair_tri[nearer]
        # barycentric coordinates (u, v) of the point in the projected triangle
        e1, e2 = b - a, c - a
        det = e1[:, 0] * e2[:, 1] - e1[:, 1] * e2[:, 0]
        r = p[pair_point, :2] - a[pair_tri, :2]
        e1, e2, det = e1[pair_tri], e2[pair_tri], det[pair_tri]
        with np.errstate(divide="ignore", invalid="ignore"):
            u = (r[:, 0] * e2[:, 1] - r[:, 1] * e2[:, 0]) / det
            v = (e1[:, 0] * r[:, 1] - e1[:, 1] * r[:, 0]) / det
        inside = (u >= 0) & (v >= 0) & (u + v <= 1) & (det != 0)
        depth = a[pair_tri, 2] + u * e1[:, 2] + v * e2[:, 2]
        covers = np.flatnonzero(inside & (depth < reach[pair_point]))
        touching = (tri[pair_tri[covers]][:, :, None] == own[pair_point[covers]][:, None, :]).any(axis=(1, 2))
        covers = covers[~touching]
        hidden = np.zeros(len(p), dtype=bool)
        hidden[pair_point[covers]] = True
        return hidden


def _occluder_cell(corners: np.ndarray, diameter: float) -> float:
    """Side of the grid cells the depth test bins triangles on: twice the median edge, so
    that a point meets a few dozen triangles, but coarse enough that long slivers (CAD
    exports) do not fill the grid: at most ``OCCLUDER_ENTRIES`` cells per triangle on
    average (estimated from the triangles' 3D extents)."""
    extent = np.ptp(corners, axis=1).max(axis=1)
    cell = float(np.clip(2.0 * np.median(np.linalg.norm(corners[:, 1] - corners[:, 0], axis=1)),
                         diameter / 256, diameter / 16))
    while np.mean((extent / cell + 1.0) ** 2) > OCCLUDER_ENTRIES and cell < diameter:
        cell *= 1.5
    return cell


def _smoothed_normals(normals: np.ndarray, area: np.ndarray, topology) -> np.ndarray:
    """Face normals after a few rounds of a bilateral filter over edge neighbours: each
    normal becomes the area-weighted mean of its own and its neighbours', a neighbour
    weighted by exp(-(angle / NORMAL_SMOOTHING_DEG)^2 / 2) (on the chord, 2 sin(angle / 2))."""
    a, b = topology.faces[topology.manifold].T
    rows, cols = np.concatenate([a, b, np.arange(len(normals))]), np.concatenate([b, a, np.arange(len(normals))])
    sigma = 2.0 * np.sin(np.radians(NORMAL_SMOOTHING_DEG) / 2.0)
    smoothed = normals
    for _ in range(NORMAL_SMOOTHING_ROUNDS):
        chord2 = np.sum((smoothed[rows] - smoothed[cols]) ** 2, axis=1)
        weight = area[cols] * np.exp(-chord2 / (2.0 * sigma ** 2))
        mixing = coo_matrix((weight, (rows, cols)), shape=(len(normals),) * 2).tocsr()
        smoothed = mixing @ smoothed
        smoothed /= np.linalg.norm(smoothed, axis=1, keepdims=True)
    return smoothed


def _creases(vertices, normals, topology, angle: float, min_network_length: float) -> np.ndarray:
    """(E,) bool: edges that are lines. Manifold edges whose faces' normals differ by more
    than ``angle``, plus every edge of one or more than two faces; networks of such edges
    (connected through vertices) shorter in total than ``min_network_length`` dropped."""
    crease = ~topology.manifold
    f = topology.faces[topology.manifold]
    crease[topology.manifold] = np.einsum("ij,ij->i", normals[f[:, 0]], normals[f[:, 1]]) < np.cos(angle)
    ends = topology.vertices[crease]
    if len(ends) == 0:
        return crease
    n = len(vertices)
    graph = coo_matrix((np.ones(len(ends)), (ends[:, 0], ends[:, 1])), shape=(n, n))
    _, network = connected_components(graph, directed=False)
    length = np.linalg.norm(vertices[ends[:, 1]] - vertices[ends[:, 0]], axis=1)
    total = np.bincount(network[ends[:, 0]], length, minlength=n)
    crease[np.flatnonzero(crease)] = total[network[ends[:, 0]]] >= min_network_length
    return crease


def _smooth_chains(vertices: np.ndarray, ends: np.ndarray) -> np.ndarray:
    """(C, 2, 3) crease segments with the vertices inside chains (exactly two crease edges)
    Taubin-smoothed along the chain; ends and junctions stay where they are."""
    if len(ends) == 0:
        return np.zeros((0, 2, 3))
    n = len(vertices)
    adjacency = coo_matrix((np.ones(2 * len(ends)), (ends.ravel(), ends[:, ::-1].ravel())), shape=(n, n)).tocsr()
    degree = np.asarray(adjacency.sum(axis=1)).ravel()
    inner = degree == 2
    mean = diags(1.0 / np.maximum(degree, 1)) @ adjacency
    points = vertices.copy()
    for _ in range(CHAIN_SMOOTHING_ROUNDS):
        for factor in CHAIN_SMOOTHING:
            points[inner] += factor * (mean @ points - points)[inner]
    return points[ends]


def _smooth_regions(triangles, normals, area, topology, crease):
    """Region of every triangle corner (M, 3) and the unit normal of each region.

    Corners of one vertex belong to one region when their triangles are joined around the
    vertex by edges that are not creases; a region's normal is the area-weighted mean of its
    triangles' (smoothed) normals: a vertex normal that is split at creases.
    """
    smooth = topology.manifold & ~crease
    e = topology.vertices[smooth]
    f = topology.faces[smooth]

    def corner(face, vertex):
        return 3 * face + np.argmax(triangles[face] == vertex[:, None], axis=1)

    n = 3 * len(triangles)
    links = np.concatenate([[corner(f[:, 0], e[:, k]), corner(f[:, 1], e[:, k])] for k in (0, 1)], axis=1)
    _, region = connected_components(coo_matrix((np.ones(links.shape[1]), links), shape=(n, n)), directed=False)
    weighted = np.repeat(normals * area[:, None], 3, axis=0)
    sums = np.stack([np.bincount(region, weighted[:, k]) for k in range(3)], axis=1)
    return region.reshape(-1, 3), sums / np.linalg.norm(sums, axis=1, keepdims=True)
