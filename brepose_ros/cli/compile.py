"""brepose-compile: compile a part's aspect graph (STEP or mesh) into MODEL.brepose.npz (offline).

    brepose-compile MODEL.step [-o MODEL.brepose.npz] [--step-deg D | --lonlat K]
                    [--workers N] [--smooth] [--method exact|poly]
    brepose-compile MODEL.ply|.stl|.obj --units mm|cm|m|in [-o ...] [--crease-angle DEG] ...

Prints a one-line summary (views, segments, time, file size); a bad input prints the
reason on stderr and exits with status 2.
"""
from __future__ import annotations

import argparse
import time
from pathlib import Path

from ..aspect_graph import default_path
from ..offline.compiler import DEFAULT_STEP_DEG, compile_aspect_graph
from ..offline.hidden_lines import DEFAULT_CHORD_TOLERANCE, DEFAULT_METHOD, DEFAULT_MIN_LENGTH, METHODS
from ..offline.mesh import UNITS, is_mesh_file
from ..offline.mesh_lines import DEFAULT_CREASE_ANGLE_DEG
from .common import ArgumentParser, non_negative_float, positive_float, positive_int, run

#: the finest view spacing accepted: 1 degree is already about 37,000 views (a 5-degree graph
#: has 1,505); finer spacings only burn hours and memory
MIN_STEP_DEG = 1.0
#: the densest longitude/latitude grid accepted, K (K - 1) + 2 = 39,802 views
MAX_LONLAT = 200


def step_deg(text: str) -> float:
    value = positive_float(text)
    if not MIN_STEP_DEG <= value <= 90:
        raise argparse.ArgumentTypeError(f"must be in [{MIN_STEP_DEG:g}, 90] degrees, got {text}")
    return value


def lonlat(text: str) -> int:
    value = positive_int(text)
    if not 2 <= value <= MAX_LONLAT:
        raise argparse.ArgumentTypeError(f"must be in [2, {MAX_LONLAT}], got {text}")
    return value


EXAMPLE = """examples:
  brepose-compile my_part.step -o my_part.brepose.npz      # 5 degrees between views, about a minute
  brepose-compile my_part.stl --units mm --step-deg 7.5    # a mesh in millimetres, fewer views"""


def parser() -> argparse.ArgumentParser:
    p = ArgumentParser(prog="brepose-compile", description=__doc__.splitlines()[0], epilog=EXAMPLE)
    p.add_argument("step", type=Path, metavar="MODEL",
                   help="STEP file of the part (any unit), or a PLY, STL or OBJ mesh (give --units); stored in metres")
    p.add_argument("--units", choices=list(UNITS), help="length unit of a mesh file (required for meshes)")
    p.add_argument("-o", "--output", type=Path, help="output file (default: ./MODEL.brepose.npz)")
    views = p.add_mutually_exclusive_group()
    views.add_argument("--step-deg", type=step_deg, default=DEFAULT_STEP_DEG,
                       help=f"angle between neighbouring views on a golden-spiral sphere (default {DEFAULT_STEP_DEG})")
    views.add_argument("--lonlat", type=lonlat, metavar="K",
                       help="the seed paper's longitude/latitude grid of density K instead")
    p.add_argument("--workers", type=positive_int, help="processes (default: one per CPU)")
    p.add_argument("--smooth", action="store_true", help="also keep smooth tangent seams (Rg1 lines)")
    p.add_argument("--method", choices=METHODS,
                   help="STEP only: hidden-line removal on the B-Rep (exact) or its mesh (poly); "
                        f"default {DEFAULT_METHOD}")
    p.add_argument("--crease-angle", type=positive_float, default=DEFAULT_CREASE_ANGLE_DEG, metavar="DEG",
                   help="meshes only: dihedral angle above which an edge is a crease "
                        f"(default {DEFAULT_CREASE_ANGLE_DEG:g})")
    p.add_argument("--chord-tolerance", type=positive_float, default=DEFAULT_CHORD_TOLERANCE,
                   help="largest 2D error of a line section, fraction of the diameter "
                        f"(default {DEFAULT_CHORD_TOLERANCE})")
    p.add_argument("--min-length", type=non_negative_float, default=DEFAULT_MIN_LENGTH,
                   help=f"shortest kept section, fraction of the diameter (default {DEFAULT_MIN_LENGTH})")
    p.add_argument("-q", "--quiet", action="store_true", help="no progress bar")
    return p


def main(argv: list[str] | None = None) -> int:
    args = parser().parse_args(argv)

    def compile_and_save() -> None:
        if is_mesh_file(args.step) and args.units is None:
            raise ValueError(f"{args.step.name} is a mesh: give its length unit with --units "
                             f"({'|'.join(UNITS)}); a mesh file does not say which unit it is in")
        if is_mesh_file(args.step) and args.method is not None:
            raise ValueError("--method chooses the hidden-line removal of STEP parts; it does not apply to meshes")
        started = time.perf_counter()
        graph = compile_aspect_graph(args.step, step_deg=args.step_deg, lonlat=args.lonlat, workers=args.workers,
                                     include_smooth=args.smooth, chord_tolerance=args.chord_tolerance,
                                     min_length=args.min_length, method=args.method or DEFAULT_METHOD,
                                     progress=not args.quiet, units=args.units, crease_angle_deg=args.crease_angle)
        path = graph.save(args.output or default_path(args.step))
        per_view = graph.n_segments / graph.n_views
        print(f"{path}: {graph.n_views} views, {graph.n_segments} segments ({per_view:.0f} per view), "
              f"{time.perf_counter() - started:.1f} s, {path.stat().st_size / 1e6:.1f} MB")

    return run(compile_and_save)


if __name__ == "__main__":
    raise SystemExit(main())
