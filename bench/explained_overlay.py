"""Pictures of what the score counts at the true pose: the model's edges over the image's
edge pixels, and which of those inside the part's outline no model edge explains.

    python bench/explained_overlay.py [--parts shaft screw ...] [--conditions clean ...]
                                      [--images 2 4 5] [--out data/bench/overlays]

Per image of the cached bench scenes (bench/accuracy.py's), at the truth refined like a
hypothesis (``occlusion_diagnosis.refined_truth``): the image dimmed, the edge pixels the
explained share counts (``EdgeEvidence.counted_pixels``) in yellow where a model edge
explains them and in red where none does, the other edge pixels in the grown outline
(cells where the part is not seen) in purple, and the visible model edges of the nearest
view drawn three times enlarged, green for sharp edges, blue for outlines, cyan for smooth
ones. The caption gives the score's shares. A wall (the truth scoring below
``pose.min_score`` on a clean image) shows what the red pixels are.
"""
from __future__ import annotations

import argparse
import sys
from pathlib import Path

REPO = Path(__file__).resolve().parents[1]
sys.path.insert(0, str(REPO))

import cv2  # noqa: E402
import numpy as np  # noqa: E402

from bench.accuracy import PARTS, add_scene_arguments, scene_path, step_file  # noqa: E402
from bench.graphs import cached_graph_path  # noqa: E402
from bench.occlusion_diagnosis import refined_truth  # noqa: E402
from brepose_ros.aspect_graph import AspectGraph  # noqa: E402
from brepose_ros.offline.hidden_lines import SHARP  # noqa: E402
from brepose_ros.online.estimator import Estimator  # noqa: E402
from brepose_ros.online.frame import Frame  # noqa: E402
from brepose_ros.online.image_edges import detect_edges  # noqa: E402
from brepose_ros.params import EstimatorParams  # noqa: E402
from brepose_ros.scene_folder import load_scene  # noqa: E402

#: BGR colours of the model edges by kind (offline.hidden_lines.KIND_NAMES: sharp, outline, smooth)
KIND_COLOURS = ((0, 255, 0), (255, 128, 0), (255, 255, 0))
SCALE = 3


def overlay(image: np.ndarray, frame: Frame, graph: AspectGraph, R: np.ndarray, t: np.ndarray,
            params: EstimatorParams) -> tuple[np.ndarray, str]:
    """The enlarged picture around the pose (module doc) and its caption."""
    p = params.pose
    view = graph.view_slice(graph.nearest_view(R, t))
    model_px = frame.camera.project_model(graph.seg_3d[view], R, t)
    evidence = frame.evidence
    soft = graph.seg_kind[view] != SHARP
    labels = evidence.counted_pixels(model_px, p.inlier_pixels, p.min_margin_pixels, soft, p.outline_pixels,
                                      p.seen_pixels)
    outline = evidence.grown_outline(model_px.reshape(-1, 2), p.min_margin_pixels)
    inside = np.zeros(evidence.shape, np.uint8)
    cv2.fillPoly(inside, [np.round(outline).astype(np.int32)], 1)
    gray = cv2.cvtColor(image, cv2.COLOR_BGR2GRAY) if image.ndim == 3 else image
    picture = cv2.cvtColor((gray // 2).astype(np.uint8), cv2.COLOR_GRAY2BGR)
    picture[evidence.edges & (inside > 0) & (labels == 0)] = (128, 0, 128)
    picture[labels == 2] = (0, 200, 255)
    picture[labels == 1] = (0, 0, 255)
    h, w = evidence.shape
    x0, y0 = np.clip(np.floor(outline.min(axis=0)).astype(int) - 10, 0, [w, h])
    x1, y1 = np.clip(np.ceil(outline.max(axis=0)).astype(int) + 10, 0, [w, h])
    big = cv2.resize(picture[y0:y1, x0:x1], None, fx=SCALE, fy=SCALE, interpolation=cv2.INTER_NEAREST)
    for segment, kind in zip(model_px, graph.seg_kind[view]):
        a, b = np.round((segment - [x0, y0]) * SCALE).astype(int)
        cv2.line(big, tuple(int(v) for v in a), tuple(int(v) for v in b), KIND_COLOURS[kind], 1)
    shares = evidence.shares(model_px, p.inlier_pixels, p.min_margin_pixels, soft, p.outline_pixels, p.seen_pixels)
    caption = (f"score {shares.score:.2f}: confirmed {shares.confirmed:.2f}, explained {shares.explained:.2f} "
               f"({(labels == 1).sum()} of {(labels > 0).sum()} counted pixels unexplained), "
               f"significance {shares.significance:.2f}")
    return big, caption


def main(argv=None) -> int:
    parser = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    add_scene_arguments(parser, parts=["shaft", "screw", "motor1_holder", "wrist_mount"], conditions=["clean"])
    parser.add_argument("--images", nargs="*", type=int, default=list(range(6)), help="image indices")
    parser.add_argument("--out", type=Path, default=REPO / "data" / "bench" / "overlays")
    args = parser.parse_args(argv)
    params = EstimatorParams()
    cache = REPO / "data" / "bench"
    args.out.mkdir(parents=True, exist_ok=True)
    for name in args.parts:
        graph = AspectGraph.load(cached_graph_path(step_file(PARTS[name], cache), cache, 5.0))
        estimator = Estimator(graph, params)
        for condition in args.conditions:
            scene = load_scene(scene_path(cache, name, condition))
            for i in args.images:
                entry = scene.entries[i]
                image = cv2.imread(str(entry.path), cv2.IMREAD_UNCHANGED)
                frame = Frame.of(detect_edges(image, params.edges), scene.camera)
                truth = refined_truth(estimator, frame, entry)
                picture, caption = overlay(image, frame, graph, truth.R, truth.t, params)
                path = args.out / f"{name}_{condition}_{i}.png"
                cv2.imwrite(str(path), picture)
                print(f"{path.name}: {caption}", flush=True)
        estimator.close()
    return 0


if __name__ == "__main__":
    sys.exit(main())
