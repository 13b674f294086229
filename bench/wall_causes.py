"""Why the true pose scores low on clean images (the "wall" of bench/occlusion_diagnosis.py):
the model side and the image side, measured at the exact true pose.

    python bench/wall_causes.py [--parts shaft screw ...] [--conditions clean ...] [--n 6]

Per image of the cached bench scenes (bench/accuracy.py's), at the true pose, the score
(``scoring.pose_shares``) with the visible edges

- ``graph``: of the aspect graph's nearest view, as the estimator scores them;
- ``exact``: computed for this pose's exact viewing direction (OCCT's exact hidden-line
  removal, orthographic like the graph's views): what the 5-degree view spacing costs;
- ``persp``: the same with a perspective projector at the camera's eye: what the graph's
  orthographic views cost (an off-centre or near part is seen along diverging rays);

each with the outlines of curved faces looked up within ``pose.inlier_pixels`` like the sharp
edges (``2px``) and within ``pose.outline_pixels`` (the score's default). Then, per kind of
visible model edge of the graph's view (sharp, outline): its length in pixels, the share of
its points (every 2 px) with a like-oriented Canny pixel within ``pose.inlier_pixels``, and
the share whose nearest one lies farther but within twice that (an edge that is there but
off the model's line: a soft silhouette, the face darkening towards it).
"""
from __future__ import annotations

import argparse
import dataclasses
import sys
from pathlib import Path

REPO = Path(__file__).resolve().parents[1]
sys.path.insert(0, str(REPO))

import cv2  # noqa: E402
import numpy as np  # noqa: E402

from bench.accuracy import PARTS, add_scene_arguments, scene_path, step_file  # noqa: E402
from bench.graphs import cached_graph_path  # noqa: E402
from brepose_ros.aspect_graph import AspectGraph  # noqa: E402
from brepose_ros.geometry import look_at_rotation  # noqa: E402
from brepose_ros.offline import hidden_lines  # noqa: E402
from brepose_ros.offline.cad import load_step  # noqa: E402
from brepose_ros.online.frame import Frame  # noqa: E402
from brepose_ros.online.image_edges import detect_edges  # noqa: E402
from brepose_ros.online.lines2d import samples_along  # noqa: E402
from brepose_ros.online.scoring import pose_shares  # noqa: E402
from brepose_ros.params import EstimatorParams  # noqa: E402
from brepose_ros.scene_folder import load_scene  # noqa: E402
from brepose_ros.viewsphere import view_ups  # noqa: E402


def visible_edges(remover: hidden_lines.HiddenLineRemover, rotation: np.ndarray, eye_distance: float | None,
                  center: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    """(segments (S, 2, 3), kinds) seen along ``rotation[2]`` by the exact hidden-line
    removal, orthographic, or with ``eye_distance`` (metres from ``center``) in perspective."""
    from OCP.gp import gp_Ax2, gp_Dir, gp_Pnt
    from OCP.HLRAlgo import HLRAlgo_Projector

    orthographic = hidden_lines._projector
    if eye_distance is not None:  # OCCT's perspective eye sits at the focus along +N from the origin
        hidden_lines._projector = lambda r: HLRAlgo_Projector(
            gp_Ax2(gp_Pnt(*center), gp_Dir(*(-r[2])), gp_Dir(*r[0])), eye_distance)
    try:
        polylines = hidden_lines._exact_polylines(remover.shape, rotation, False, remover.chord / 2.0)
    finally:
        hidden_lines._projector = orthographic
    view = hidden_lines.line_sections(polylines, rotation, remover.part.center, remover.chord, remover.same_point,
                                      remover.min_length)
    return view.segments_3d, view.kinds


def kind_shares(frame: Frame, model_px: np.ndarray, tolerance: float) -> tuple[float, float, float]:
    """Length (px) of the segments, the share of their points (every 2 px) with a like edge
    pixel within ``tolerance``, and the share whose nearest like one lies within twice that."""
    if len(model_px) == 0:
        return 0.0, 0.0, 0.0
    delta = model_px[:, 1] - model_px[:, 0]
    lengths = np.linalg.norm(delta, axis=1)
    segment, frac = samples_along(np.maximum(np.ceil(lengths / 2.0).astype(int), 1))
    points = model_px[segment, 0] + frac[:, None] * delta[segment]
    labels, _, pixels = frame.evidence.nearest_like()  # per direction bin and pixel, the nearest like edge pixel
    height, width = frame.evidence.shape
    x = np.clip(np.rint(points[:, 0]).astype(int), 0, width - 1)
    y = np.clip(np.rint(points[:, 1]).astype(int), 0, height - 1)
    distance = np.hypot(*(pixels[labels[frame.evidence.orientation_bin(model_px)[segment], y, x]] - points).T)
    return float(lengths.sum()), float(np.mean(distance <= tolerance)), float(
        np.mean((distance > tolerance) & (distance <= 2 * tolerance)))


def main(argv=None) -> int:
    parser = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    add_scene_arguments(parser, n=6, parts=["shaft", "screw", "motor1_holder", "wrist_mount"], conditions=["clean"])
    args = parser.parse_args(argv)
    params = EstimatorParams()
    p = params.pose
    sharp_reach = dataclasses.replace(p, outline_pixels=p.inlier_pixels)
    cache = REPO / "data" / "bench"
    print("| part | condition | image | view off (deg) | graph 2px / default | exact 2px / default "
          "| persp 2px / default | sharp: px, within, 1-2x | outline: px, within, 1-2x |")
    print("|---|---|---|---|---|---|---|---|---|")
    for name in args.parts:
        step = step_file(PARTS[name], cache)
        graph = AspectGraph.load(cached_graph_path(step, cache, 5.0))
        remover = hidden_lines.HiddenLineRemover(load_step(step), method="exact")
        for condition in args.conditions:
            scene = load_scene(scene_path(cache, name, condition))
            for i in range(args.n):
                entry = scene.entries[i]
                frame = Frame.of(detect_edges(cv2.imread(str(entry.path), cv2.IMREAD_UNCHANGED), params.edges),
                                 scene.camera)
                R, t = entry.R.astype(float), entry.t.astype(float)
                eye = -R.T @ t
                direction = graph.model_center - eye
                distance = float(np.linalg.norm(direction))
                direction /= distance
                rotation = look_at_rotation(direction, view_ups(direction[None])[0])
                rows = graph.view_slice(graph.nearest_view(R, t))
                edge_sets = {"graph": (graph.seg_3d[rows], graph.seg_kind[rows]),
                             "exact": visible_edges(remover, rotation, None, graph.model_center),
                             "persp": visible_edges(remover, rotation, distance, graph.model_center)}
                scores = []
                for segments, kinds in edge_sets.values():
                    view = dataclasses.replace(graph, seg_3d=segments, seg_kind=kinds,
                                               seg_offsets=np.array([0, len(segments)]),
                                               view_directions=direction[None])
                    scores.append(" / ".join(f"{pose_shares(view, R, t, frame, reach)[0].score:.2f}"
                                             for reach in (sharp_reach, p)))
                off = np.degrees(np.arccos(np.clip(graph.view_directions[graph.nearest_view(R, t)] @ direction,
                                                   -1.0, 1.0)))
                model_px = scene.camera.project_model(graph.seg_3d[rows], R, t)
                kinds = graph.seg_kind[rows]
                by_kind = [kind_shares(frame, model_px[kinds == kind], p.inlier_pixels)
                           for kind in (hidden_lines.SHARP, hidden_lines.OUTLINE)]
                print(f"| {name} | {condition} | {i} | {off:.1f} | " + " | ".join(scores) + " | " + " | ".join(
                    f"{length:.0f}, {within:.2f}, {near:.2f}" for length, within, near in by_kind) + " |", flush=True)
    return 0


if __name__ == "__main__":
    sys.exit(main())
