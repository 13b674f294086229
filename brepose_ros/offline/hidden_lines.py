"""Stage 1 (offline): the visible edges of a part seen from one direction, as line sections
whose end points are known both in the view plane and on the model.

The later pose solver needs 2D-3D correspondences, so every section carries its two 3D end
points (metres, model frame); the 2D ones are their orthographic projection
``xy = (R_view @ (X - center))[:2]`` (``view_coordinates``), exact by construction.

Two ways to find what is visible, both OpenCascade's hidden-line removal (HLR), with an
orthographic projector along the viewing direction:

* ``"exact"``: HLRBRep_Algo on the B-Rep. ``HLRBRep_HLRToShape.CompoundOfEdges(..., In3d=True)``
  hands back every visible piece as a 3D edge on the model (the original curve restricted
  to its visible parameter range; for outlines of curved faces a curve on the surface), so
  no back-projection is needed. Sharp edges, outlines (silhouettes of curved faces) and,
  on request, smooth tangent seams (Rg1 lines) are separate compounds.
* ``"poly"`` (the default): HLRBRep_PolyAlgo on the triangulation. Exact HLR costs 0.1-0.3 s
  a view on the real parts of 135-214 faces (tori, spheres, B-spline faces), too slow for
  thousands of views; PolyAlgo is 1.4-3.5 times faster on those and about as fast on simple
  parts, and finds the same lines: 98-100 % of the exact lines' length lies within 1 % of
  the diameter of its lines and vice versa on the nine real parts. It only returns
  2D pieces, so each piece's end points are lifted onto the 3D segment they lie on: the
  mesh polygon of a B-Rep edge or the outline of a curved face's mesh in this view (the
  front-most one if several project onto the same place).

Curves become line sections by a chord tolerance relative to the model diameter: curves
(or mesh polygons) are sampled at half the tolerance in 3D, joined end to end where exactly
two meet, and simplified in 2D (Douglas-Peucker) at the other half. That bounds the 2D error
of every section by the tolerance directly, and is simpler and more predictable than the
seed paper's split at curvature extrema (section 4); straight edges stay one section, and a
circle seen edge-on becomes one. Sections shorter than ``min_length`` (relative to the
diameter) are dropped: an image line detector does not find them either.
"""
from __future__ import annotations

from dataclasses import dataclass

import numpy as np
from scipy.sparse import coo_matrix
from scipy.sparse.csgraph import connected_components
from scipy.spatial import cKDTree

from .cad import Part

SHARP, OUTLINE, SMOOTH = 0, 1, 2
KIND_NAMES = ("sharp", "outline", "smooth")
METHODS = ("exact", "poly")
DEFAULT_METHOD = "poly"
#: Chord tolerance and shortest kept section, as fractions of the model diameter: 1.5 px
#: on a typical 300-pixel part. The matcher can keep only longer ones (tetrad length).
DEFAULT_CHORD_TOLERANCE = 0.005
DEFAULT_MIN_LENGTH = 0.005
#: End points closer than this (fraction of the diameter) are the same point.
_SAME_POINT = 1e-6
#: Angular deflection of the mesh in "poly" mode (radians). Coarser meshes lose outlines
#: of small curved faces (0.5 rad: 96.6 % instead of 98.4 % of Motor1_holder's exact lines).
_MESH_ANGLE = 0.35


@dataclass(frozen=True)
class ViewSegments:
    """Visible line sections of one view: 3D end points and kind (SHARP, OUTLINE, SMOOTH)."""

    segments_3d: np.ndarray  # (N, 2, 3) float64, metres, model frame
    kinds: np.ndarray  # (N,) uint8


def view_coordinates(points: np.ndarray, rotation: np.ndarray, center: np.ndarray) -> np.ndarray:
    """Orthographic view coordinates ``(R_view @ (X - center))[:2]`` of points (..., 3)."""
    return (np.asarray(points, dtype=float) - center) @ np.asarray(rotation)[:2].T


class HiddenLineRemover:
    """Visible edges of one part, view after view; holds what does not depend on the view."""

    def __init__(self, part: Part, method: str = DEFAULT_METHOD,
                 chord_tolerance: float = DEFAULT_CHORD_TOLERANCE,
                 min_length: float = DEFAULT_MIN_LENGTH, include_smooth: bool = False):
        self.check_options(method, chord_tolerance, min_length)
        self.part = part
        self.method = method
        self.include_smooth = include_smooth
        self.chord = chord_tolerance * part.diameter
        self.min_length = min_length * part.diameter
        self.same_point = _SAME_POINT * part.diameter
        self.shape = part.shape
        self._mesh = _PartMesh(self.shape, self.chord / 2.0) if method == "poly" else None

    @staticmethod
    def check_options(method: str, chord_tolerance: float, min_length: float) -> None:
        """ValueError for options no part could use (checked before any work starts)."""
        if method not in METHODS:
            raise ValueError(f"unknown hidden-line method {method!r}; choose from {', '.join(METHODS)}")
        if not 0.0 < chord_tolerance <= 0.1:
            raise ValueError(f"chord tolerance must be in (0, 0.1] of the diameter, got {chord_tolerance}")
        if not 0.0 <= min_length <= 0.5:
            raise ValueError(f"minimum section length must be in [0, 0.5] of the diameter, got {min_length}")

    def segments(self, rotation: np.ndarray) -> ViewSegments:
        """Visible sections seen with R_view = ``rotation`` (rows x, y, z of the camera)."""
        rotation = np.asarray(rotation, dtype=float)
        if self._mesh is None:
            polylines = _exact_polylines(self.shape, rotation, self.include_smooth, self.chord / 2.0)
        else:
            # PolyAlgo refines outlines on the exact surface and the candidates are on the
            # mesh: each may be half the chord tolerance off, hence the whole for the lift.
            polylines = self._mesh.visible_polylines(rotation, self.include_smooth, self.chord, self.same_point)
        return line_sections(polylines, rotation, self.part.center, self.chord, self.same_point, self.min_length)


def line_sections(polylines: list[tuple[np.ndarray, int]], rotation: np.ndarray, center: np.ndarray,
                  chord: float, same_point: float, min_length: float,
                  min_chain_length: float = 0.0, loops_from_corners: bool = False) -> ViewSegments:
    """Visible 3D polylines with their kind -> line sections: chained per kind, simplified
    in 2D at half the chord tolerance and cut into sections; chains shorter than
    ``min_chain_length`` and sections shorter than ``min_length`` (view plane, metres) dropped.

    A closed chain keeps its start as a section end. B-Rep edges start at vertices, so it
    is a corner; pieces of a mesh crease may start anywhere, and ``loops_from_corners``
    turns each closed chain to start at its sharpest turn in the view.
    """
    segments, kinds = [], []
    for kind in (SHARP, OUTLINE, SMOOTH):
        for line in _chain([p for p, k in polylines if k == kind], same_point):
            xy = view_coordinates(line, rotation, center)
            if loops_from_corners and len(line) > 3 and np.linalg.norm(line[-1] - line[0]) <= same_point:
                k = _sharpest_turn(xy)
                line, xy = (np.concatenate([a[k:-1], a[:k + 1]]) for a in (line, xy))
            if min_chain_length > 0 and np.linalg.norm(np.diff(xy, axis=0), axis=1).sum() < min_chain_length:
                continue
            keep = _simplify(xy, chord / 2.0)
            segments.append(np.stack([line[keep[:-1]], line[keep[1:]]], axis=1))
            kinds.append(np.full(len(keep) - 1, kind, dtype=np.uint8))
    if not segments:
        return ViewSegments(np.zeros((0, 2, 3)), np.zeros(0, dtype=np.uint8))
    segments, kinds = np.concatenate(segments), np.concatenate(kinds)
    xy = view_coordinates(segments, rotation, center)
    long_enough = np.linalg.norm(xy[:, 1] - xy[:, 0], axis=1) >= min_length
    return ViewSegments(segments[long_enough], kinds[long_enough])


def _projector(rotation: np.ndarray):
    """Orthographic HLR projector looking along rotation[2]; its 2D axes are x and -y."""
    from OCP.gp import gp_Ax2, gp_Dir, gp_Pnt
    from OCP.HLRAlgo import HLRAlgo_Projector

    # OCCT's eye looks down the -N axis, and PolyAlgo ignores the origin: keep it at 0.
    return HLRAlgo_Projector(gp_Ax2(gp_Pnt(0.0, 0.0, 0.0), gp_Dir(*(-rotation[2])), gp_Dir(*rotation[0])))


def _edges(compound):
    """The edges of an HLR result compound (a null shape when there are none)."""
    from OCP.TopAbs import TopAbs_EDGE
    from OCP.TopExp import TopExp_Explorer
    from OCP.TopoDS import TopoDS

    if compound is None or compound.IsNull():
        return
    explorer = TopExp_Explorer(compound, TopAbs_EDGE)
    while explorer.More():
        yield TopoDS.Edge_s(explorer.Current())
        explorer.Next()


def exact_hidden_lines(shape, rotation):
    """OCCT's exact hidden-line removal of ``shape`` seen along ``rotation``'s view axis
    (``_projector``): its ``HLRBRep_HLRToShape``, whose compounds hold the visible edges by kind."""
    from OCP.HLRBRep import HLRBRep_Algo, HLRBRep_HLRToShape

    algo = HLRBRep_Algo()
    algo.Add(shape)
    algo.Projector(_projector(rotation))
    algo.Update()
    algo.Hide()
    return HLRBRep_HLRToShape(algo)


def _exact_polylines(shape, rotation, include_smooth, deflection):
    """Visible 3D polylines with their kind from the exact HLR.

    With In3d the outline compound also repeats face boundaries lying on the outline (a
    face seen edge-on), which the sharp compound already has: identical point lists, so
    they are dropped by value.
    """
    from OCP.HLRBRep import HLRBRep_TypeOfResultingEdge as T

    result = exact_hidden_lines(shape, rotation)
    types = [(SHARP, T.HLRBRep_Sharp), (OUTLINE, T.HLRBRep_OutLine)]
    if include_smooth:
        types.append((SMOOTH, T.HLRBRep_Rg1Line))
    polylines, seen = [], set()
    for kind, typ in types:
        for edge in _edges(result.CompoundOfEdges(typ, True, True)):
            points = _discretise(edge, deflection)
            key = np.round(points[[0, len(points) // 2, -1]] / deflection, 3).tobytes()
            if key not in seen:
                seen.add(key)
                polylines.append((points, kind))
    return polylines


def _discretise(edge, deflection: float) -> np.ndarray:
    """(n, 3) points along an edge, chord error <= ``deflection``; a line gives its ends."""
    from OCP.BRepAdaptor import BRepAdaptor_Curve
    from OCP.GCPnts import GCPnts_QuasiUniformDeflection
    from OCP.GeomAbs import GeomAbs_Line

    curve = BRepAdaptor_Curve(edge)
    u0, u1 = curve.FirstParameter(), curve.LastParameter()
    if curve.GetType() == GeomAbs_Line:
        return np.array([curve.Value(u0).Coord(), curve.Value(u1).Coord()])
    sampler = GCPnts_QuasiUniformDeflection(curve, deflection, u0, u1)
    if not sampler.IsDone():
        return np.array([curve.Value(u).Coord() for u in np.linspace(u0, u1, 33)])
    return np.array([sampler.Value(i).Coord() for i in range(1, sampler.NbPoints() + 1)])


class _PartMesh:
    """What "poly" mode needs of the triangulated part: the mesh polygon of every B-Rep
    edge as 3D segments, and the curved faces' mesh with exact surface normals at its
    nodes (for the outlines of each view)."""

    def __init__(self, shape, deflection: float):
        from OCP.BRepMesh import BRepMesh_IncrementalMesh

        from OCP.HLRBRep import HLRBRep_PolyAlgo

        BRepMesh_IncrementalMesh(shape, deflection, False, _MESH_ANGLE, True)
        self.edge_segments = _edge_polygons(shape)
        self.nodes, self.normals, self.triangles = _curved_faces_mesh(shape)
        self.algo = HLRBRep_PolyAlgo()
        self.algo.Load(shape)

    def visible_polylines(self, rotation, include_smooth, tolerance, same_point):
        """Visible pieces from HLRBRep_PolyAlgo with their end points lifted onto the model."""
        from OCP.HLRBRep import HLRBRep_PolyHLRToShape

        self.algo.Projector(_projector(rotation))
        self.algo.Update()
        result = HLRBRep_PolyHLRToShape()
        result.Update(self.algo)
        candidates = np.concatenate([self.edge_segments, self.outline_segments(rotation[2])])
        compounds = [(SHARP, result.VCompound()), (OUTLINE, result.OutLineVCompound())]
        if include_smooth:
            compounds.append((SMOOTH, result.Rg1LineVCompound()))
        pieces = [_pieces_2d(compound, same_point) for _, compound in compounds]
        kinds = np.concatenate([np.full(len(p), kind) for (kind, _), p in zip(compounds, pieces)])
        # Consecutive pieces share their end points: lift each point once.
        points, shared = np.unique(np.concatenate(pieces).reshape(-1, 2), axis=0, return_inverse=True)
        lifted, found = _lift(points, candidates, rotation, tolerance)
        lifted, found = lifted[shared.ravel()].reshape(-1, 2, 3), found[shared.ravel()].reshape(-1, 2).all(axis=1)
        return list(zip(lifted[found], kinds[found]))

    def outline_segments(self, direction: np.ndarray) -> np.ndarray:
        """(M, 2, 3) outline of the curved faces' mesh: where the interpolated normal is
        perpendicular to the viewing direction, one segment per triangle it crosses."""
        if len(self.triangles) == 0:
            return np.zeros((0, 2, 3))
        facing = self.normals @ direction
        tri = self.triangles
        side = facing[tri] > 0.0
        crossed = side.any(axis=1) & ~side.all(axis=1)
        tri = tri[crossed]
        points, crossings = [], []
        for i, j in ((0, 1), (1, 2), (2, 0)):
            # Each mesh edge is cut from its lower node index, so neighbours agree exactly.
            lo, hi = np.minimum(tri[:, i], tri[:, j]), np.maximum(tri[:, i], tri[:, j])
            f_lo, f_hi = facing[lo], facing[hi]
            cut = (f_lo > 0.0) != (f_hi > 0.0)
            t = np.where(cut, f_lo / np.where(cut, f_lo - f_hi, 1.0), 0.0)
            points.append(self.nodes[lo] + t[:, None] * (self.nodes[hi] - self.nodes[lo]))
            crossings.append(cut)
        points, crossings = np.stack(points, axis=1), np.stack(crossings, axis=1)
        first_two = np.argsort(~crossings, axis=1, kind="stable")[:, :2]
        return np.take_along_axis(points, first_two[:, :, None], axis=1)


def _edge_polygons(shape) -> np.ndarray:
    """(C, 2, 3) segments of the mesh polygon of every non-degenerate B-Rep edge."""
    from OCP.BRep import BRep_Tool
    from OCP.TopAbs import TopAbs_EDGE, TopAbs_FACE
    from OCP.TopExp import TopExp
    from OCP.TopLoc import TopLoc_Location
    from OCP.TopoDS import TopoDS
    from OCP.TopTools import TopTools_IndexedDataMapOfShapeListOfShape

    faces_of = TopTools_IndexedDataMapOfShapeListOfShape()
    TopExp.MapShapesAndAncestors_s(shape, TopAbs_EDGE, TopAbs_FACE, faces_of)
    segments = []
    for i in range(1, faces_of.Extent() + 1):
        edge, faces = TopoDS.Edge_s(faces_of.FindKey(i)), faces_of.FindFromIndex(i)
        if BRep_Tool.Degenerated_s(edge) or faces.Size() == 0:
            continue
        location = TopLoc_Location()
        triangulation = BRep_Tool.Triangulation_s(TopoDS.Face_s(faces.First()), location)
        polygon = BRep_Tool.PolygonOnTriangulation_s(edge, triangulation, location) if triangulation else None
        if polygon is None:
            continue
        trsf, nodes = location.Transformation(), polygon.Nodes()
        points = np.array([triangulation.Node(nodes.Value(k)).Transformed(trsf).Coord()
                           for k in range(nodes.Lower(), nodes.Upper() + 1)])
        segments.append(np.stack([points[:-1], points[1:]], axis=1))
    return np.concatenate(segments) if segments else np.zeros((0, 2, 3))


def _curved_faces_mesh(shape):
    """Nodes (N, 3), outward unit normals at the nodes (N, 3) and triangles (T, 3) of the
    non-planar faces; planar faces have no outline inside them."""
    from OCP.BRep import BRep_Tool
    from OCP.BRepAdaptor import BRepAdaptor_Surface
    from OCP.BRepLib import BRepLib_ToolTriangulatedShape
    from OCP.GeomAbs import GeomAbs_Plane
    from OCP.TopAbs import TopAbs_FACE, TopAbs_REVERSED
    from OCP.TopExp import TopExp_Explorer
    from OCP.TopLoc import TopLoc_Location
    from OCP.TopoDS import TopoDS

    nodes, normals, triangles, offset = [], [], [], 0
    explorer = TopExp_Explorer(shape, TopAbs_FACE)
    while explorer.More():
        face = TopoDS.Face_s(explorer.Current())
        explorer.Next()
        location = TopLoc_Location()
        mesh = BRep_Tool.Triangulation_s(face, location)
        if mesh is None or BRepAdaptor_Surface(face).GetType() == GeomAbs_Plane:
            continue
        if not mesh.HasNormals():
            BRepLib_ToolTriangulatedShape.ComputeNormals_s(face, mesh)
        trsf, n = location.Transformation(), mesh.NbNodes()
        rot = np.array([[trsf.Value(r, c) for c in (1, 2, 3)] for r in (1, 2, 3)])
        nrm = np.array([mesh.Normal(i).Coord() for i in range(1, n + 1)]) @ rot.T
        nodes.append(np.array([mesh.Node(i).Transformed(trsf).Coord() for i in range(1, n + 1)]))
        normals.append(-nrm if face.Orientation() == TopAbs_REVERSED else nrm)
        triangles.append(np.array([mesh.Triangle(i).Get() for i in range(1, mesh.NbTriangles() + 1)]) - 1 + offset)
        offset += n
    if not nodes:
        return np.zeros((0, 3)), np.zeros((0, 3)), np.zeros((0, 3), dtype=np.int64)
    return np.concatenate(nodes), np.concatenate(normals), np.concatenate(triangles)


def _pieces_2d(compound, same_point: float) -> np.ndarray:
    """(P, 2, 2) end points of PolyHLRToShape's straight pieces, in view coordinates
    without the centring (the projector's 2D y axis is -y). PolyAlgo reports a piece
    once per face it bounds, in either direction; the copies would break chains."""
    from OCP.BRep import BRep_Tool
    from OCP.TopExp import TopExp

    ends = [(BRep_Tool.Pnt_s(TopExp.FirstVertex_s(e)).Coord(), BRep_Tool.Pnt_s(TopExp.LastVertex_s(e)).Coord())
            for e in _edges(compound)]
    pieces = np.array(ends).reshape(-1, 2, 3)[..., :2] * [1.0, -1.0]
    # Orient every piece the same way (by an arbitrary linear functional), then copies are
    # near-identical 4-vectors.
    forward = pieces[:, 0] @ [1.0, np.pi] <= pieces[:, 1] @ [1.0, np.pi]
    canonical = np.where(forward[:, None, None], pieces, pieces[:, ::-1]).reshape(-1, 4)
    copies = cKDTree(canonical).query_pairs(same_point, output_type="ndarray")
    return np.delete(pieces, np.unique(copies.max(axis=1)), axis=0)


def _lift(points, candidates, rotation, tolerance, neighbours: int = 12):
    """3D points on ``candidates`` (C, 2, 3) that project onto the 2D ``points`` (P, 2).

    Each point goes to the nearest candidate segment in the view; among those as near as
    the nearest (within 1e-3 tolerance) the front-most wins, because where two edges
    project onto the same place only the nearer can be the visible one. Returns (P, 3)
    and a mask of the points that have a candidate within ``tolerance``.
    """
    lifted, found = np.zeros((len(points), 3)), np.zeros(len(points), dtype=bool)
    if len(points) == 0 or len(candidates) == 0:
        return lifted, found
    flat = candidates @ rotation[:2].T
    a, d = flat[:, 0], flat[:, 1] - flat[:, 0]
    length = np.linalg.norm(d, axis=1)
    # Index every candidate by points at most `step` apart: a point lying on a candidate
    # is then within step / 2 + tolerance of one of them.
    step = 2.0 * tolerance
    count = np.ceil(length / step).astype(int) + 1
    owner = np.repeat(np.arange(len(flat)), count)
    first = np.repeat(np.cumsum(count) - count, count)
    frac = (np.arange(len(owner)) - first) / np.repeat(np.maximum(count - 1, 1), count)
    _, near = cKDTree(a[owner] + frac[:, None] * d[owner]).query(
        points, k=min(neighbours, len(owner)), distance_upper_bound=step / 2.0 + tolerance)
    near = near.reshape(len(points), -1)
    valid = near < len(owner)
    c = owner[np.where(valid, near, 0)]  # (P, k) candidate indices
    t = np.clip(np.einsum("pki,pki->pk", points[:, None] - a[c], d[c]) / np.maximum(length[c] ** 2, 1e-300), 0, 1)
    distance = np.linalg.norm(a[c] + t[..., None] * d[c] - points[:, None], axis=2)
    distance[~valid] = np.inf
    on_model = candidates[c, 0] + t[..., None] * (candidates[c, 1] - candidates[c, 0])
    best = distance.min(axis=1, keepdims=True)
    ok = (distance <= tolerance) & (distance <= best + 1e-3 * tolerance)
    choice = np.where(ok, on_model @ rotation[2], np.inf).argmin(axis=1)
    found = ok.any(axis=1)
    lifted = on_model[np.arange(len(points)), choice]
    return lifted, found


def _chain(polylines: list[np.ndarray], same_point: float) -> list[np.ndarray]:
    """Join 3D polylines end to end through every point where exactly two of them meet,
    so that simplification sees whole curves (a circle split into halves, the pieces of
    a mesh polygon). Points where three or more meet (corners) stay ends."""
    polylines = [p for p in polylines if len(p) >= 2]
    if len(polylines) <= 1:
        return polylines
    # End 2 * i is the first point of polyline i, 2 * i + 1 its last.
    ends = np.array([[p[0], p[-1]] for p in polylines]).reshape(-1, 3)
    pairs = cKDTree(ends).query_pairs(same_point, output_type="ndarray")
    graph = coo_matrix((np.ones(len(pairs)), (pairs[:, 0], pairs[:, 1])), shape=(len(ends), len(ends)))
    _, node = connected_components(graph, directed=False)
    order = np.argsort(node, kind="stable")
    first = np.searchsorted(node[order], node[order])
    two = np.bincount(node)[node[order]] == 2
    partner = np.full(len(ends), -1)
    partner[order[two]] = order[np.where(first[two] == np.flatnonzero(two), first[two] + 1, first[two])]
    partner[partner // 2 == np.arange(len(ends)) // 2] = -1  # a closed polyline meets itself
    partner = partner.tolist()

    used = [False] * len(polylines)
    chains = []
    for start in range(len(polylines)):
        if used[start]:
            continue
        # Walk backwards to the chain's first polyline (or once round a closed loop);
        # `side` is the end (0 first point, 1 last) by which the walk enters `line`.
        line, side = start, 0
        while (other := partner[2 * line + side]) >= 0 and other // 2 != start:
            line, side = other // 2, 1 - other % 2
        parts = []
        while True:
            used[line] = True
            piece = polylines[line] if side == 0 else polylines[line][::-1]
            parts.append(piece[1:] if parts else piece)
            other = partner[2 * line + 1 - side]
            if other < 0 or used[other // 2]:
                break
            line, side = other // 2, other % 2
        chains.append(np.concatenate(parts))
    return chains


def _sharpest_turn(loop: np.ndarray) -> int:
    """Index of the vertex where a closed 2D polyline (last point = first) turns most."""
    points = loop[:-1]
    incoming, outgoing = points - np.roll(points, 1, axis=0), np.roll(points, -1, axis=0) - points
    cosine = np.einsum("ij,ij->i", incoming, outgoing) / np.maximum(
        np.linalg.norm(incoming, axis=1) * np.linalg.norm(outgoing, axis=1), 1e-300)
    return int(np.argmin(cosine))


def _simplify(xy: np.ndarray, tolerance: float) -> np.ndarray:
    """Indices of the vertices Douglas-Peucker keeps of a 2D polyline (first and last
    always). A chord shorter than the tolerance (a closed loop) is measured from its start."""
    if len(xy) <= 2:
        return np.arange(len(xy))
    keep = np.zeros(len(xy), dtype=bool)
    keep[[0, -1]] = True
    stack = [(0, len(xy) - 1)]
    while stack:
        i, j = stack.pop()
        if j <= i + 1:
            continue
        chord, rel = xy[j] - xy[i], xy[i + 1: j] - xy[i]
        norm = np.linalg.norm(chord)
        if norm > tolerance:
            dist = np.abs(chord[0] * rel[:, 1] - chord[1] * rel[:, 0]) / norm
        else:
            dist = np.linalg.norm(rel, axis=1)
        k = int(np.argmax(dist))
        if dist[k] > tolerance:
            keep[i + 1 + k] = True
            stack += [(i, i + 1 + k), (i + 1 + k, j)]
    return np.flatnonzero(keep)
