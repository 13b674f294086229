"""The aspect graph file: the visible edges of a part from every viewpoint, checked on load.

For each view on the sphere (``viewsphere``) the visible line sections (``hidden_lines``)
are stored twice: in the view's orthographic image plane for the matcher, and as 3D end
points on the model, in metres, for the pose solver.

View coordinates: with ``R_view = view_rotations[i]`` (``geometry.look_at_rotation`` of
the view direction) the orthographic coordinates of a model point X are
``xy = (R_view @ (X - model_center))[:2]`` in metres. They are stored as float32
``seg_xy`` relative to each view's own origin and unit (``xy_origin[i]``, ``xy_scale[i]``:
the sections' length-weighted centroid and RMS radius), so that they keep float32's seven
digits on the part's scale in half the bytes; ``view_xy(i)`` gives them back in metres. The
matcher normalises them itself (``metric_space.outline_normalisation``, on the longest
``matching.max_model_segments`` of a view).

Segments are stored flat (CSR): the sections of view i are rows
``seg_offsets[i]:seg_offsets[i + 1]`` of seg_xy, seg_3d and seg_kind.

The file (MODEL.brepose.npz) is data, never code: a deflated npz read with
``allow_pickle=False`` (deflate halves it: seg_3d repeats the same vertices view after
view), plus a JSON metadata entry with the format version, the sha256 of
the source STEP, the compile parameters, the units and the array shapes, and a sha256 over
the metadata and the array bytes so that any change after writing is detected. A file of
another format version is refused with a message to recompile it.

Symmetries (``offline.symmetry``): the rotations that map the part's edges onto its edges
within a tolerance, found at compile time. A discrete one maps a model point X to
``symmetry_rotations[k] @ X + symmetry_translations[k]``; a continuous one turns the part
by any angle about ``symmetry_axes[c]`` (a point on the axis and its unit direction).
``symmetry_shares`` / ``symmetry_axis_shares`` hold the share of the edges each maps onto
edges: at least ``EXACT_SYMMETRY_SHARE`` is an exact symmetry (the poses are equivalent),
less a near one (twins the image must tell apart: ``online.symmetry``).

The part's surface (``surface_*``, optional): the triangles the compiler tessellated (a STEP
part: normals split between faces) or read (a mesh: smooth normals), model frame, metres,
for the look of the part's silhouette at a pose (``online.appearance``).
"""
from __future__ import annotations

import hashlib
import json
import os
import tempfile
import zipfile
import zlib
from dataclasses import dataclass, field
from functools import cached_property
from pathlib import Path

import numpy as np

from . import __version__
from .chromaticity import BINS as COLOUR_BINS
from .geometry import turned_poses
from .online.kernels import nearest_views_kernel
from .viewsphere import direction_cells

FORMAT = "brepose-aspect-graph"
#: 2: view coordinates as seg_xy / xy_origin / xy_scale; no tetrads (the matcher computes
#: its own features), no view_ups (view_rotations holds them)
#: 3: the part's symmetries (symmetry_*)
FORMAT_VERSION = 3
SUFFIX = ".brepose.npz"

#: name -> (dtype, shape with V = views, S = segments): the file's whole contract.
_ARRAYS = {
    "model_center": (np.float64, ("3",)),
    "view_directions": (np.float64, ("V", "3")),
    "view_rotations": (np.float64, ("V", "3", "3")),
    "seg_offsets": (np.int64, ("V+1",)),
    "seg_xy": (np.float32, ("S", "2", "2")),
    "xy_origin": (np.float64, ("V", "2")),
    "xy_scale": (np.float64, ("V",)),
    "seg_3d": (np.float64, ("S", "2", "3")),
    "seg_kind": (np.uint8, ("S",)),
    "symmetry_rotations": (np.float64, ("Y", "3", "3")),
    "symmetry_translations": (np.float64, ("Y", "3")),
    "symmetry_shares": (np.float64, ("Y",)),
    "symmetry_axes": (np.float64, ("C", "2", "3")),
    "symmetry_axis_shares": (np.float64, ("C",)),
}
#: arrays a file may hold or not (a graph of a part without them, or written before them,
#: reads as before, so this is no new format version): the model's surface colour as a
#: chromaticity histogram (``online.colour_regions``), from a mesh with vertex colours; the
#: part's surface as triangles with per-vertex normals, N vertices and M triangles, for the
#: look of its silhouette at a pose (``online.appearance``), all three or none
_OPTIONAL_ARRAYS = {
    "colour_histogram": (np.float32, ("H", "H")),
    "surface_vertices": (np.float32, ("N", "3")),
    "surface_normals": (np.float32, ("N", "3")),
    "surface_triangles": (np.int32, ("M", "3")),
}
_SURFACE_ARRAYS = ("surface_vertices", "surface_normals", "surface_triangles")

#: a symmetry mapping at least this share of the edges onto edges is exact: what is left
#: unmatched is the sampling of curves, not a feature (a cube's, box's or cylinder's turns
#: match 0.995-1.0, the flange's six-fold turns 0.974-0.978 of its polygonised circles; the
#: half turns that move the notched plate's 8 x 6 mm notch 0.70-0.90)
EXACT_SYMMETRY_SHARE = 0.96


#: size limits checked before anything is inflated: a 1,505-view graph is 1-3 MB on disk and
#: 4-7 MB in memory, a 10,000-view one of a 214-face part about 75 and 50 MB; a file past
#: these limits is not an aspect graph anyone compiled but damage or a zip bomb
MAX_FILE_BYTES = 512 * 1024 * 1024
MAX_INFLATED_BYTES = 1024 * 1024 * 1024
#: the file holds one entry per array plus the metadata
MAX_ENTRIES = len(_ARRAYS) + len(_OPTIONAL_ARRAYS) + 1

_METADATA_KEYS = ("format_version", "step_sha256", "params", "units", "model_diameter", "n_faces", "arrays",
                  "content_sha256")


class AspectGraphError(ValueError):
    """An aspect graph that cannot be compiled or used, with the reason in the message."""


@dataclass(eq=False)
class AspectGraph:
    """Views of a part and their visible line sections (see the module docstring)."""

    step_sha256: str
    params: dict
    model_center: np.ndarray
    model_diameter: float
    n_faces: int
    view_directions: np.ndarray
    view_rotations: np.ndarray
    seg_offsets: np.ndarray
    seg_xy: np.ndarray
    xy_origin: np.ndarray
    xy_scale: np.ndarray
    seg_3d: np.ndarray
    seg_kind: np.ndarray
    # none by default: a graph made in code for a test need not name them
    symmetry_rotations: np.ndarray = field(default_factory=lambda: np.zeros((0, 3, 3)))
    symmetry_translations: np.ndarray = field(default_factory=lambda: np.zeros((0, 3)))
    symmetry_shares: np.ndarray = field(default_factory=lambda: np.zeros(0))
    symmetry_axes: np.ndarray = field(default_factory=lambda: np.zeros((0, 2, 3)))
    symmetry_axis_shares: np.ndarray = field(default_factory=lambda: np.zeros(0))
    #: (COLOUR_BINS, COLOUR_BINS) the surface's chromaticity histogram summing to 1, or None: no colour
    colour_histogram: np.ndarray | None = None
    #: the part's surface (model frame, metres; module doc), or None: compiled before graphs held it
    surface_vertices: np.ndarray | None = None
    surface_normals: np.ndarray | None = None
    surface_triangles: np.ndarray | None = None

    @property
    def n_views(self) -> int:
        return len(self.view_directions)

    @property
    def n_segments(self) -> int:
        return len(self.seg_kind)

    def view_slice(self, i: int) -> slice:
        """Rows of seg_xy, seg_3d and seg_kind that belong to view ``i``."""
        return slice(int(self.seg_offsets[i]), int(self.seg_offsets[i + 1]))

    def nearest_views(self, R: np.ndarray, t: np.ndarray) -> np.ndarray:
        """(B,) index of the view nearest to the direction the camera of each pose R
        (B, 3, 3), t (B, 3) sees the part from: ``geometry.direction_to`` without its
        normalisation, which cannot change the largest product. A compiled loop over the
        views (``kernels.nearest_views_kernel``, the refinement kernels' own arithmetic):
        numpy's product of all views with all poses and its argmax down the strided axis
        held the GIL for 10-100 us a pose. Each pose compares only the views of its
        direction's cell (``view_cells``)."""
        out = np.empty(len(R), np.int64)
        nearest_views_kernel(np.ascontiguousarray(R, np.float64), np.ascontiguousarray(t, np.float64),
                             np.ascontiguousarray(self.view_directions, np.float64),
                             np.ascontiguousarray(self.model_center, np.float64), *self.view_cells, out)
        return out

    @cached_property
    def view_cells(self) -> tuple[np.ndarray, np.ndarray]:
        """``viewsphere.direction_cells`` of the view directions, for the kernels that find a
        pose's nearest view (``kernels._nearest_view``): an occluded latency image asks some
        3,400 times, 3.2 us each over 2,500 views. Derived on first use from the directions,
        which a graph never changes."""
        return direction_cells(self.view_directions)

    def nearest_view(self, R: np.ndarray, t: np.ndarray) -> int:
        """``nearest_views`` of one pose."""
        return int(self.nearest_views(R[None], t[None])[0])

    def visible_segments(self, R: np.ndarray, t: np.ndarray) -> slice:
        """Rows of the segments visible from the view nearest to the pose."""
        return self.view_slice(self.nearest_view(R, t))

    @cached_property
    def surface(self):
        """The part's surface as an ``offline.cad.Mesh`` (float64 vertices), or None."""
        if self.surface_vertices is None:
            return None
        from .offline.cad import Mesh  # offline.cad reads this module's file_sha256 on import

        return Mesh(self.surface_vertices.astype(np.float64), self.surface_triangles, self.surface_normals)

    @property
    def exact_symmetries(self) -> np.ndarray:
        """(Y,) which discrete symmetries are exact (the rest are near ones)."""
        return self.symmetry_shares >= EXACT_SYMMETRY_SHARE

    @property
    def exact_axes(self) -> np.ndarray:
        """(C,) which continuous symmetries are exact."""
        return self.symmetry_axis_shares >= EXACT_SYMMETRY_SHARE

    def symmetric_poses(self, R: np.ndarray, t: np.ndarray, which: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
        """The twins (K, 3, 3), (K, 3) of pose R, t under the discrete symmetries ``which``
        (indices or a mask): the poses that show the part turned back by each symmetry
        X -> S X + b (``geometry.turned_poses``)."""
        return turned_poses(R, t, self.symmetry_rotations[which], self.symmetry_translations[which])

    def view_xy(self, i: int) -> np.ndarray:
        """The orthographic view coordinates (n, 2, 2) of view ``i``'s sections, in metres."""
        return self.seg_xy[self.view_slice(i)] * self.xy_scale[i] + self.xy_origin[i]

    def arrays(self) -> dict[str, np.ndarray]:
        """The file's arrays: every one of the contract and the optional ones the graph has."""
        return {name: getattr(self, name) for name in (*_ARRAYS, *_OPTIONAL_ARRAYS) if getattr(self, name) is not None}

    def _metadata(self) -> dict:
        return {
            "format": FORMAT,
            "format_version": FORMAT_VERSION,
            "brepose_ros_version": __version__,  # a record of what wrote the file; loading ignores it
            "step_sha256": self.step_sha256,
            "params": self.params,
            "units": "m",
            "model_diameter": self.model_diameter,
            "n_faces": self.n_faces,
            "arrays": {name: {"dtype": np.dtype((_ARRAYS | _OPTIONAL_ARRAYS)[name][0]).str, "shape": list(a.shape)}
                       for name, a in self.arrays().items()},
        }

    def save(self, path: str | Path) -> Path:
        """Write MODEL.brepose.npz atomically (a crash leaves no half-written file)."""
        path = Path(path)
        metadata = self._metadata()
        metadata["content_sha256"] = _digest(metadata, self.arrays())
        entries = {name: np.ascontiguousarray(a) for name, a in self.arrays().items()}
        entries["metadata"] = np.array(json.dumps(metadata, sort_keys=True))
        try:
            handle, tmp = tempfile.mkstemp(dir=path.parent, suffix=".part")
        except OSError as error:
            raise AspectGraphError(f"cannot write {path}: {error.strerror}") from error
        try:
            with os.fdopen(handle, "wb") as stream:
                np.savez_compressed(stream, **entries)
            os.chmod(tmp, 0o644)  # mkstemp's 0600 would hide it from a node run by another user
            os.replace(tmp, path)
        except BaseException:
            Path(tmp).unlink(missing_ok=True)
            raise
        return path

    @classmethod
    def load(cls, path: str | Path, step_path: str | Path | None = None) -> AspectGraph:
        """Read and check an aspect graph; with ``step_path``, also that it was compiled
        from that STEP file. Raises AspectGraphError naming what is wrong."""
        path = Path(path)
        metadata, arrays = _read(path)
        _check_arrays(path, metadata, arrays)
        _check_finite(path, arrays, metadata)
        claimed = metadata.pop("content_sha256", None)
        if claimed != _digest(metadata, arrays):
            raise AspectGraphError(f"{path}: content digest mismatch: the file was modified after it "
                                   f"was written (tampered with or corrupted); recompile it")
        if step_path is not None:
            actual = file_sha256(step_path)
            if actual != metadata["step_sha256"]:
                raise AspectGraphError(f"{path} was compiled from a different STEP file than {step_path} "
                                       f"(sha256 {metadata['step_sha256'][:12]}... vs {actual[:12]}...); "
                                       f"recompile it")
        return cls(step_sha256=metadata["step_sha256"], params=metadata["params"],
                   model_diameter=float(metadata["model_diameter"]), n_faces=int(metadata["n_faces"]), **arrays)


def default_path(step_path: str | Path) -> Path:
    """MODEL.brepose.npz in the current directory for MODEL.step."""
    return Path(Path(step_path).stem + SUFFIX)


def file_sha256(path: str | Path) -> str:
    """sha256 of a file's bytes: what ties a compiled graph to its source model file."""
    digest = hashlib.sha256()
    with open(path, "rb") as stream:
        for block in iter(lambda: stream.read(1 << 20), b""):
            digest.update(block)
    return digest.hexdigest()


def _digest(metadata: dict, arrays: dict[str, np.ndarray]) -> str:
    """sha256 over the canonical metadata JSON and every array's name, dtype, shape and bytes."""
    digest = hashlib.sha256(json.dumps(metadata, sort_keys=True).encode())
    for name in sorted(arrays):
        a = np.ascontiguousarray(arrays[name])
        digest.update(f"{name}|{a.dtype.str}|{a.shape}|".encode())
        digest.update(a.tobytes())
    return digest.hexdigest()


def _read(path: Path) -> tuple[dict, dict[str, np.ndarray]]:
    """Metadata and arrays of an aspect graph file, or AspectGraphError saying why not."""
    if not path.is_file():
        raise AspectGraphError(f"aspect graph file {path} does not exist")
    with open(path, "rb") as stream:
        magic = stream.read(4)
    if magic != b"PK\x03\x04":
        raise AspectGraphError(f"{path} is not an aspect graph file (not an npz/zip archive)")
    if not zipfile.is_zipfile(path):
        raise AspectGraphError(f"{path} is truncated (its zip directory is missing); recompile it")
    try:
        _check_sizes(path)
        with np.load(path, allow_pickle=False) as npz:
            if "metadata" not in npz.files:
                raise AspectGraphError(f"{path} is an npz file but not an aspect graph (no metadata)")
            metadata = _parse_metadata(path, str(npz["metadata"]))
            missing = [name for name in _ARRAYS if name not in npz.files]
            if missing:
                raise AspectGraphError(f"{path} lacks the array(s) {', '.join(missing)}")
            arrays = {name: npz[name] for name in (*_ARRAYS, *_OPTIONAL_ARRAYS) if name in npz.files}
    except AspectGraphError:
        raise
    except (zipfile.BadZipFile, zlib.error) as error:
        raise AspectGraphError(f"{path} fails its zip integrity check ({error}): the file was modified "
                               f"after it was written (tampered with or corrupted); recompile it") from error
    except Exception as error:  # zipfile, zlib and numpy report damage in different ways
        raise AspectGraphError(f"{path} is truncated or corrupt ({type(error).__name__}: {error})") from error
    return metadata, arrays


def _parse_metadata(path: Path, text: str) -> dict:
    """The metadata of a graph file of this format version, or AspectGraphError saying why
    not; checked before any array, since the version decides which arrays there are."""
    try:
        metadata = json.loads(text)
    except json.JSONDecodeError as error:
        raise AspectGraphError(f"{path}: its metadata is not valid JSON ({error})") from error
    if not isinstance(metadata, dict) or metadata.get("format") != FORMAT:
        raise AspectGraphError(f"{path} is an npz file but not a {FORMAT} (metadata format "
                               f"{metadata.get('format') if isinstance(metadata, dict) else None!r})")
    version = metadata.get("format_version")
    if not isinstance(version, int) or version < 1:
        raise AspectGraphError(f"{path}: invalid format version {version!r}")
    if version > FORMAT_VERSION:
        raise AspectGraphError(f"{path}: format version {version} is newer than this brepose_ros "
                               f"reads ({FORMAT_VERSION}); update brepose_ros or recompile")
    if version < FORMAT_VERSION:
        raise AspectGraphError(f"{path}: format version {version} is older than this brepose_ros reads "
                               f"({FORMAT_VERSION}); recompile it with brepose-compile")
    missing = [key for key in _METADATA_KEYS if key not in metadata]
    if missing:
        raise AspectGraphError(f"{path}: its metadata lacks {', '.join(missing)}")
    return metadata


def _check_sizes(path: Path) -> None:
    """Refuse a file whose size, zip directory or array headers exceed the limits, before
    np.load inflates anything: the directory states every entry's inflated size (zipfile
    never yields more), and each .npy header the size of the array np.load will allocate."""
    size = path.stat().st_size
    if size > MAX_FILE_BYTES:
        raise AspectGraphError(f"{path} is {size} bytes, over the limit of {MAX_FILE_BYTES} for an aspect graph")
    with zipfile.ZipFile(path) as archive:
        entries = archive.infolist()
        if len(entries) > MAX_ENTRIES:
            raise AspectGraphError(f"{path} holds {len(entries)} entries, an aspect graph at most {MAX_ENTRIES}")
        inflated = sum(entry.file_size for entry in entries)
        if inflated > MAX_INFLATED_BYTES:
            raise AspectGraphError(f"{path} would inflate to {inflated} bytes, over the limit of "
                                   f"{MAX_INFLATED_BYTES}: not an aspect graph (damaged, or a zip bomb)")
        for entry in (e for e in entries if e.filename.endswith(".npy")):  # others np.load reads as bytes
            with archive.open(entry) as stream:
                version = np.lib.format.read_magic(stream)
                read_header = (np.lib.format.read_array_header_1_0 if version == (1, 0)
                               else np.lib.format.read_array_header_2_0)
                shape, _, dtype = read_header(stream)
            if int(np.prod(shape, dtype=np.int64)) * dtype.itemsize > entry.file_size:
                raise AspectGraphError(f"{path}: array {entry.filename} claims shape {shape} of {dtype}, more "
                                       f"than its {entry.file_size} bytes hold (damaged or tampered with)")


def _check_finite(path: Path, arrays: dict[str, np.ndarray], metadata: dict) -> None:
    """Refuse NaN or infinite numbers, which no compiler writes and which would poison every
    pose computed from the graph, and a model diameter that is not a positive number."""
    for name, a in arrays.items():
        if a.dtype.kind == "f" and not np.isfinite(a).all():
            raise AspectGraphError(f"{path}: array {name} holds NaN or infinite values")
    diameter = metadata.get("model_diameter")
    if not (isinstance(diameter, (int, float)) and np.isfinite(diameter) and diameter > 0):
        raise AspectGraphError(f"{path}: model_diameter must be a positive number, got {diameter!r}")


def _check_arrays(path: Path, metadata: dict, arrays: dict[str, np.ndarray]) -> None:
    """Every array has the dtype and shape of the contract, consistent with the others."""
    directions, offsets = arrays["view_directions"], arrays["seg_offsets"]
    n_views = directions.shape[0] if directions.ndim else -1
    n_segments = int(offsets[-1]) if offsets.ndim == 1 and len(offsets) else -1
    surface = [name for name in _SURFACE_ARRAYS if name in arrays]
    if surface and len(surface) < len(_SURFACE_ARRAYS):
        raise AspectGraphError(f"{path}: holds {', '.join(surface)} but not all of {', '.join(_SURFACE_ARRAYS)}")
    sizes = {"V": n_views, "V+1": n_views + 1, "S": n_segments, "Y": len(arrays["symmetry_shares"]),
             "C": len(arrays["symmetry_axis_shares"]), "H": COLOUR_BINS,
             "N": len(arrays["surface_vertices"]) if surface else -1,
             "M": len(arrays["surface_triangles"]) if surface else -1}
    present = {name: _OPTIONAL_ARRAYS[name] for name in _OPTIONAL_ARRAYS if name in arrays}
    for name, (dtype, shape) in (_ARRAYS | present).items():
        a = arrays[name]
        expected = tuple(sizes[s] if s in sizes else int(s) for s in shape)
        if a.dtype != dtype or a.shape != expected:
            raise AspectGraphError(f"{path}: array {name} has dtype {a.dtype} and shape {a.shape}, "
                                   f"expected {np.dtype(dtype)} and {expected}")
        listed = metadata.get("arrays", {}).get(name, {})
        if listed.get("shape") != list(a.shape) or listed.get("dtype") != a.dtype.str:
            raise AspectGraphError(f"{path}: array {name} does not match the shape/dtype its metadata lists")
    if offsets[0] != 0 or np.any(np.diff(offsets) < 0):
        raise AspectGraphError(f"{path}: seg_offsets is not a non-decreasing list starting at 0")
    _check_symmetries(path, arrays)
    if surface:
        _check_surface(path, arrays)
    colour = arrays.get("colour_histogram")
    if colour is not None and (colour.min() < 0 or abs(float(colour.sum()) - 1.0) > 1e-3):
        raise AspectGraphError(f"{path}: colour_histogram is not a histogram (non-negative, summing to 1)")


def _check_surface(path: Path, arrays: dict[str, np.ndarray]) -> None:
    """Triangles index the surface's vertices and its normals are unit vectors: anything else
    would draw another part's silhouette, or none, at every pose."""
    triangles, n_vertices = arrays["surface_triangles"], len(arrays["surface_vertices"])
    if len(triangles) == 0 or triangles.min() < 0 or triangles.max() >= n_vertices:
        raise AspectGraphError(f"{path}: surface_triangles is empty or indexes a vertex outside the "
                               f"{n_vertices} of surface_vertices")
    if np.abs(np.linalg.norm(arrays["surface_normals"], axis=1) - 1.0).max() > 1e-3:
        raise AspectGraphError(f"{path}: surface_normals holds a vector that is not a unit normal")


def _check_symmetries(path: Path, arrays: dict[str, np.ndarray]) -> None:
    """Symmetries are proper rotations and unit axes with shares in [0, 1]: anything else
    would turn twins and evaluation poses into non-rigid maps."""
    rotations = arrays["symmetry_rotations"]
    identity = np.einsum("kji,kjl->kil", rotations, rotations) - np.eye(3)
    if len(rotations) and (np.abs(identity).max() > 1e-6 or np.abs(np.linalg.det(rotations) - 1.0).max() > 1e-6):
        raise AspectGraphError(f"{path}: symmetry_rotations holds a matrix that is not a rotation "
                               f"(orthonormal, determinant 1)")
    directions = arrays["symmetry_axes"][:, 1]
    if len(directions) and np.abs(np.linalg.norm(directions, axis=1) - 1.0).max() > 1e-6:
        raise AspectGraphError(f"{path}: symmetry_axes holds a direction that is not a unit vector")
    for name in ("symmetry_shares", "symmetry_axis_shares"):
        if np.any((arrays[name] < 0) | (arrays[name] > 1)):
            raise AspectGraphError(f"{path}: {name} holds a share outside [0, 1]")
