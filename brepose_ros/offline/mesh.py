"""Stage 0 for meshes: read a PLY, STL or OBJ triangle mesh into metres, checked and repaired.

A mesh file has no unit of its own, so the caller names it (``UNITS``); the vertices are
scaled to metres once, here, and the model frame is the file's own: nothing is re-centred
(../shared/CONVENTIONS.md). Parsing is trimesh's; everything a later stage relies on is
checked here first, because trimesh is lenient (a truncated ASCII STL loads as an empty
mesh, NaN vertices are silently dropped):

* the file: present, non-empty, at most ``MAX_MESH_BYTES``, a known suffix, and a header
  and length that fit its format (truncated binary PLY and STL files are caught before
  parsing, as are headers claiming more than ``MAX_MESH_FACES`` triangles);
* the geometry: finite vertices, face indices in range, at least one triangle of non-zero
  area, at most ``MAX_MESH_FACES`` triangles;
* the surface: coincident vertices merged (an STL stores each triangle on its own),
  degenerate and duplicate triangles dropped, at most ``MAX_OPEN_EDGE_SHARE`` of the edges
  bordering one triangle or more than two (a triangle soup has nothing but such edges),
  and oriented consistently, outwards where a piece is closed, since silhouettes are
  where front- and back-facing triangles meet.
"""
from __future__ import annotations

import re
import struct
from dataclasses import dataclass
from pathlib import Path

import numpy as np
from scipy.sparse import coo_matrix
from scipy.sparse.csgraph import breadth_first_order, connected_components

from ..aspect_graph import file_sha256
from ..chromaticity import surface_histogram
from .cad import CadError, checked_size

MESH_SUFFIXES = (".ply", ".stl", ".obj")
#: metres per unit of the lengths in the file
UNITS = {"mm": 1e-3, "cm": 1e-2, "m": 1.0, "in": 0.0254}
#: Refuse larger files before parsing: a 64 MB binary PLY holds about 2.5 million triangles,
#: far more than the edges an image shows need (the LM-O scans have 12,000-46,000).
MAX_MESH_BYTES = 64 * 1024 * 1024
#: Per-view hidden-line work grows with the triangle count; a mesh this fine is a raw scan
#: that should be decimated first (MeshLab, Blender: quadric edge collapse).
MAX_MESH_FACES = 500_000
#: Share of edges that may border one triangle (holes in a scan) or more than two
#: (non-manifold seams) before the file is refused as not being a surface.
MAX_OPEN_EDGE_SHARE = 0.05
#: Triangles with an area below this fraction of the squared bounding-box diagonal have no
#: normal to speak of; they are dropped.
_DEGENERATE_AREA = 1e-14


class MeshError(CadError):
    """A mesh file that cannot be used, with the reason in the message."""


@dataclass
class MeshPart:
    """A triangle mesh of a part's surface, in metres, with what every later stage needs."""

    vertices: np.ndarray  # (N, 3) float64, metres, model frame of the file
    triangles: np.ndarray  # (M, 3) int64, consistently oriented, outward where closed
    sha256: str  # of the mesh file's bytes: ties compiled data to its source
    source: str
    units: str  # the file's unit, a key of UNITS
    center: np.ndarray  # bounding-box centre, metres, model frame
    diameter: float  # bounding-box diagonal, metres (an upper bound of the true diameter)
    n_faces: int  # triangles
    #: the surface's chromaticity histogram (``chromaticity.surface_histogram``) of
    #: its vertex or face colours, None if the file has none
    colour_histogram: np.ndarray | None = None


def is_mesh_file(path: str | Path) -> bool:
    return Path(path).suffix.lower() in MESH_SUFFIXES


def load_mesh(path: str | Path, units: str | None, max_bytes: int = MAX_MESH_BYTES,
              max_faces: int = MAX_MESH_FACES) -> MeshPart:
    """Load a PLY, STL or OBJ mesh whose lengths are in ``units``, in metres.

    Raises MeshError naming the cause for a missing unit, a missing, empty, oversized,
    unknown, truncated or unparsable file, NaN vertices, no triangles, too many triangles,
    a triangle soup or a surface that cannot be oriented.
    """
    path = Path(path)
    if units not in UNITS:
        raise MeshError(f"mesh {path.name} needs its length unit (one of {', '.join(UNITS)}), "
                        f"got {units!r}: a mesh file does not say which unit it is in")
    suffix = path.suffix.lower()
    if suffix not in MESH_SUFFIXES:
        raise MeshError(f"{path} is not a mesh file this reads ({', '.join(MESH_SUFFIXES)})")
    size = checked_size(path, "mesh file", max_bytes, MeshError)
    claimed = _check_container(path, suffix[1:], size)
    if claimed is not None and claimed > max_faces:
        raise MeshError(f"mesh {path} has {claimed} triangles, over the limit of {max_faces}; decimate it first")
    vertices, triangles, colour = _parse(path, suffix[1:])
    if len(triangles) > max_faces:
        raise MeshError(f"mesh {path} has {len(triangles)} triangles, over the limit of {max_faces}; "
                        f"decimate it first")
    vertices, triangles = _cleaned(path, vertices * UNITS[units], triangles)
    triangles = _oriented(path, vertices, triangles)
    lo, hi = vertices.min(axis=0), vertices.max(axis=0)
    return MeshPart(vertices=vertices, triangles=triangles, sha256=file_sha256(path), source=str(path),
                    units=units, center=(lo + hi) / 2.0, diameter=float(np.linalg.norm(hi - lo)),
                    n_faces=len(triangles), colour_histogram=colour)


def _check_container(path: Path, kind: str, size: int) -> int | None:
    """MeshError for a file whose header or length does not fit its format; the triangle
    count its header claims, when it has one."""
    with open(path, "rb") as stream:
        head = stream.read(4096)
    if kind == "ply":
        if not head.startswith(b"ply"):
            raise MeshError(f"{path} is not a PLY file (it does not start with 'ply')")
        end = head.find(b"end_header")
        if end < 0:
            raise MeshError(f"{path} is truncated or not a PLY file (no end_header in its first 4 KB)")
        header = head[:end].decode("ascii", errors="replace")
        faces = re.search(r"^element\s+face\s+(\d+)", header, re.MULTILINE)
        return int(faces.group(1)) if faces else None
    if kind == "stl":
        if size >= 84:
            (count,) = struct.unpack("<I", head[80:84])
            if size == 84 + 50 * count:
                return count  # binary STL of exactly the length its count gives
        if head.lstrip().lower().startswith(b"solid"):
            with open(path, "rb") as stream:
                stream.seek(max(0, size - 512))
                if b"endsolid" not in stream.read().lower():
                    raise MeshError(f"ASCII STL file {path} is truncated (no endsolid at its end)")
            return None
        count = struct.unpack("<I", head[80:84])[0] if size >= 84 else 0
        raise MeshError(f"{path} is truncated or not an STL file ({size} bytes; a binary STL of "
                        f"{count} triangles has {84 + 50 * count})")
    if b"\0" in head:
        raise MeshError(f"{path} is not an OBJ file (it holds binary data)")
    return None


def _parse(path: Path, kind: str) -> tuple[np.ndarray, np.ndarray, np.ndarray | None]:
    """Vertices and triangles as the file holds them, unprocessed (so NaN stays visible), and
    the surface's colour histogram if the file has vertex or face colours."""
    import trimesh

    try:
        mesh = trimesh.load(str(path), file_type=kind, force="mesh", process=False)
    except Exception as error:  # trimesh's parsers report damage with many exception types
        raise MeshError(f"{path} is not a readable {kind.upper()} mesh ({type(error).__name__}: {error})") from None
    vertices = np.asarray(getattr(mesh, "vertices", np.zeros((0, 3))), dtype=np.float64).reshape(-1, 3)
    triangles = np.asarray(getattr(mesh, "faces", np.zeros((0, 3))), dtype=np.int64).reshape(-1, 3)
    if len(triangles) == 0:
        raise MeshError(f"mesh file {path} holds no triangles")
    bad = ~np.isfinite(vertices).all(axis=1)
    if bad.any():
        raise MeshError(f"mesh {path} has {int(bad.sum())} vertices with NaN or infinite coordinates")
    if triangles.min() < 0 or triangles.max() >= len(vertices):
        raise MeshError(f"mesh {path} has triangles referring to vertices it does not have (truncated?)")
    return vertices, triangles, _colour_histogram(mesh, vertices, triangles)


def _colour_histogram(mesh, vertices: np.ndarray, triangles: np.ndarray) -> np.ndarray | None:
    """The chromaticity histogram of a trimesh's vertex or face colours, each weighted by the
    area it colours (a vertex a third of each triangle about it); None without colours."""
    kind = getattr(getattr(mesh, "visual", None), "kind", None)
    corners = vertices[triangles]
    area = np.linalg.norm(np.cross(corners[:, 1] - corners[:, 0], corners[:, 2] - corners[:, 0]), axis=1) / 2
    if kind == "vertex":
        colours, weights = mesh.visual.vertex_colors, np.zeros(len(vertices))
        np.add.at(weights, triangles.ravel(), np.repeat(area / 3, 3))
    elif kind == "face":
        colours, weights = mesh.visual.face_colors, area
    else:
        return None
    return surface_histogram(np.asarray(colours)[:, 2::-1].astype(np.uint8), weights)  # RGBA -> BGR


def _cleaned(path: Path, vertices: np.ndarray, triangles: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    """Coincident vertices merged; degenerate, repeated and unreferenced elements dropped."""
    lo, hi = vertices[triangles].reshape(-1, 3).min(axis=0), vertices[triangles].reshape(-1, 3).max(axis=0)
    diagonal = float(np.linalg.norm(hi - lo))
    if diagonal == 0.0:
        raise MeshError(f"mesh {path} has no extent: all its vertices coincide")
    # Vertices on a grid far below any feature are the same vertex (an STL repeats them per
    # triangle, and exporters print them with float32 noise).
    keys = np.round((vertices - lo) / (1e-9 * diagonal)).astype(np.int64)
    _, first, merged = np.unique(keys, axis=0, return_index=True, return_inverse=True)
    triangles = merged.reshape(-1)[triangles]
    vertices = vertices[first]
    corners = vertices[triangles]
    area = np.linalg.norm(np.cross(corners[:, 1] - corners[:, 0], corners[:, 2] - corners[:, 0]), axis=1) / 2
    distinct = (triangles[:, 0] != triangles[:, 1]) & (triangles[:, 1] != triangles[:, 2]) & \
               (triangles[:, 2] != triangles[:, 0])
    triangles = triangles[distinct & (area > _DEGENERATE_AREA * diagonal ** 2)]
    if len(triangles) == 0:
        raise MeshError(f"mesh {path} has no triangle of non-zero area")
    _, unique = np.unique(np.sort(triangles, axis=1), axis=0, return_index=True)
    triangles = triangles[np.sort(unique)]
    used, triangles = np.unique(triangles, return_inverse=True)
    return vertices[used], triangles.reshape(-1, 3)


@dataclass(frozen=True)
class EdgeTopology:
    """Undirected edges of a triangle mesh and the triangles on each side."""

    vertices: np.ndarray  # (E, 2) vertex indices, ascending
    faces: np.ndarray  # (E, 2) the two triangles of a manifold edge; -1 where there is none
    manifold: np.ndarray  # (E,) bool: exactly two triangles
    corner: np.ndarray  # (3M,) edge of triangle t's side k (corners k, k+1) at 3 t + k


def edge_topology(triangles: np.ndarray) -> EdgeTopology:
    """Edges with their triangles; an edge of one triangle or of more than two has no pair."""
    sides = np.stack([triangles, np.roll(triangles, -1, axis=1)], axis=2).reshape(-1, 2)
    ends, corner, count = np.unique(np.sort(sides, axis=1), axis=0, return_inverse=True, return_counts=True)
    corner = corner.reshape(-1)
    order = np.argsort(corner, kind="stable")
    first = np.searchsorted(corner[order], np.arange(len(ends)))
    manifold = count == 2
    faces = np.full((len(ends), 2), -1, dtype=np.int64)
    faces[manifold, 0] = order[first[manifold]] // 3
    faces[manifold, 1] = order[first[manifold] + 1] // 3
    return EdgeTopology(ends, faces, manifold, corner)


def _oriented(path: Path, vertices: np.ndarray, triangles: np.ndarray) -> np.ndarray:
    """Triangles turned so that neighbours agree, and outward where a piece is closed.

    Each connected piece is walked breadth-first over its manifold edges; a triangle that
    runs over the edge to its parent in the same direction as the parent is flipped. Of the
    piece's two consistent orientations, a closed piece gets the one of positive volume, an
    open one the one that agrees with more of the file's triangles.
    """
    topology = edge_topology(triangles)
    open_share = 1.0 - topology.manifold.mean()
    if open_share > MAX_OPEN_EDGE_SHARE:
        raise MeshError(f"mesh {path} is not a surface: {100 * open_share:.0f} % of its edges border one "
                        f"triangle or more than two (a triangle soup or a broken export)")
    n = len(triangles)
    a, b = topology.faces[topology.manifold].T
    same = coo_matrix((_same_direction(triangles, topology) + 1.0, (a, b)), shape=(n, n)).tocsr()
    same = same.maximum(same.T)  # 2 where the pair runs the same way over its edge, 1 where not
    n_pieces, piece = connected_components(same, directed=False)
    flip = np.zeros(n, dtype=bool)
    for root in np.unique(piece, return_index=True)[1]:
        visit, parent = breadth_first_order(same, root, directed=False)
        children = visit[1:]
        turned = (np.asarray(same[children, parent[children]]).ravel() == 2).tolist()
        flips, parents = flip.tolist(), parent.tolist()  # parents come first in breadth-first order
        for child, turn in zip(children.tolist(), turned):
            flips[child] = flips[parents[child]] ^ turn
        flip = np.array(flips)
    triangles = np.where(flip[:, None], triangles[:, ::-1], triangles)
    if _same_direction(triangles, edge_topology(triangles)).any():
        raise MeshError(f"mesh {path} cannot be oriented consistently (a one-sided surface)")
    corners = vertices[triangles]
    volume = np.bincount(piece, np.einsum("ij,ij->i", corners[:, 0], np.cross(corners[:, 1], corners[:, 2])),
                         minlength=n_pieces)
    open_piece = np.zeros(n_pieces, dtype=bool)
    open_piece[piece[np.flatnonzero((~topology.manifold)[topology.corner]) // 3]] = True
    turn = np.where(open_piece, np.bincount(piece, flip, n_pieces) > np.bincount(piece, None, n_pieces) / 2,
                    volume < 0)
    return np.where(turn[piece][:, None], triangles[:, ::-1], triangles)


def _same_direction(triangles: np.ndarray, topology: EdgeTopology) -> np.ndarray:
    """(manifold edges,) bool: both triangles of the edge run over it in the same direction,
    which consistently oriented neighbours never do."""
    sides = np.stack([triangles, np.roll(triangles, -1, axis=1)], axis=2).reshape(-1, 2)
    forward = sides[:, 0] < sides[:, 1]
    order = np.argsort(topology.corner, kind="stable")
    first = np.searchsorted(topology.corner[order], np.flatnonzero(topology.manifold))
    return forward[order[first]] == forward[order[first + 1]]
