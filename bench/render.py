"""Time the synthetic renderer (brepose_ros.synthetic.render) against mesh size.

    python bench/render.py [--repeat N]

Renders the rounded bracket (a built-in part) at three tessellation densities, 640 x 480,
and prints the median and the fastest of N renders in milliseconds with the triangle
count (the fastest run is the least disturbed by other processes on a shared machine).
Scene generation renders every image once per object, so a few thousand triangles must
stay well under a second.
"""
from __future__ import annotations

import argparse
import statistics
import sys
import tempfile
import time
from pathlib import Path

import numpy as np

REPO = Path(__file__).resolve().parents[1]
sys.path.insert(0, str(REPO))

from brepose_ros.camera import Camera  # noqa: E402
from brepose_ros.geometry import look_at_rotation  # noqa: E402
from brepose_ros.offline.cad import load_step, tessellate  # noqa: E402
from brepose_ros.synthetic import shapes  # noqa: E402
from brepose_ros.synthetic.render import Placed, render  # noqa: E402

#: (relative deflection, angular deflection) of the tessellations timed, coarse to fine
DENSITIES = ((2e-3, 0.5), (2e-4, 0.1), (5e-5, 0.05))


def main(argv=None) -> int:
    parser = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    parser.add_argument("--repeat", type=int, default=5)
    args = parser.parse_args(argv)
    camera = Camera.from_fov(640, 480, 600.0)
    with tempfile.TemporaryDirectory() as folder:
        part = load_step(shapes.export_step("rounded_bracket", Path(folder) / "rounded_bracket.step"))
    R = look_at_rotation(np.array([-0.4, 0.6, -0.7]))
    print("| triangles | median ms | fastest ms |")
    print("|---|---|---|")
    for relative, angular in DENSITIES:
        mesh = tessellate(part, relative_deflection=relative, angular_deflection=angular)
        objects = [Placed(mesh, R, np.array([0, 0, 0.25]) - R @ part.center)]
        timings = []
        for _ in range(args.repeat):
            started = time.perf_counter()
            render(camera, objects)
            timings.append(1000 * (time.perf_counter() - started))
        print(f"| {len(mesh.triangles)} | {statistics.median(timings):.0f} | {min(timings):.0f} |")
    return 0


if __name__ == "__main__":
    sys.exit(main())
