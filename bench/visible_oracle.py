"""How far a score that does not punish occlusion could lift the truth: an oracle from the
scenes' visible masks.

    python bench/visible_oracle.py [--n 8] [--parts sharp_bracket ...] [--conditions occl30+clutter ...]

Per image of bench/accuracy.py's cached scenes, the truth refined like a hypothesis and
polished (``occlusion_diagnosis.refined_truth``) scored as the estimator scores it, then
with its shares counted where the part is seen, by the scene's mask of the visible part
(masks/, grown by ``GROW`` pixels): *confirmed* on the visible pieces of its model edges
only (what an exact discount of the hidden share would give), *explained* on the edge pixels
inside the mask only (no occluder, background or clutter edge inside the outline counted
against it), and both. The count of refined truths at or above ``pose.min_score`` in each
case is what the best such score could reach (docs/results/verification.md).
"""
from __future__ import annotations

import argparse
import sys
from collections import defaultdict
from pathlib import Path

REPO = Path(__file__).resolve().parents[1]
sys.path.insert(0, str(REPO))

import cv2  # noqa: E402
import numpy as np  # noqa: E402

from bench.accuracy import (TUNING, add_scene_arguments, bench_steps, cached_frames, graph_and_model,  # noqa: E402
                            overridden_params)
from bench.occlusion_diagnosis import refined_truth  # noqa: E402
from brepose_ros.offline.hidden_lines import SHARP  # noqa: E402
from brepose_ros.online.estimator import Estimator  # noqa: E402

#: the visible mask grows by this many pixels, so that a model edge on the part's own outline
#: (the mask's border) stays inside it
GROW = 4
CASES = ("as scored", "confirmed on visible", "explained on visible", "both")


def visible_mask(image_path: Path) -> np.ndarray:
    """The scene's mask of the visible part for one image (masks/ beside images/), grown by GROW."""
    mask = cv2.imread(str(image_path.parent.parent / "masks" / image_path.name), cv2.IMREAD_GRAYSCALE) > 0
    return cv2.dilate(mask.view(np.uint8), np.ones((2 * GROW + 1, 2 * GROW + 1), np.uint8)).view(bool)


def visible_pieces(model_px: np.ndarray, soft: np.ndarray, mask: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    """The pieces of segments (S, 2, 2), pixels, that lie inside ``mask`` (walked a pixel at a
    time), and which are soft like the segment they come from."""
    pieces, kinds = [], []
    h, w = mask.shape
    for (a, b), kind in zip(model_px, soft):
        steps = max(int(np.ceil(np.hypot(*(b - a)))), 1)
        points = a + np.linspace(0.0, 1.0, steps + 1)[:, None] * (b - a)
        x, y = np.rint(points).astype(int).T
        inside = (x >= 0) & (x < w) & (y >= 0) & (y < h)
        inside[inside] = mask[y[inside], x[inside]]
        runs = np.flatnonzero(np.diff(np.concatenate([[0], inside.view(np.int8), [0]])))
        for start, stop in zip(runs[::2], runs[1::2]):
            if stop - start >= 2:
                pieces.append([points[start], points[stop - 1]])
                kinds.append(kind)
    return np.array(pieces, float).reshape(-1, 2, 2), np.array(kinds, bool)


def oracle_scores(estimator: Estimator, frame, entry) -> tuple[float, ...]:
    """The refined truth's score in each of CASES."""
    g, p = estimator.graph, estimator.params.pose
    truth = refined_truth(estimator, frame, entry)
    rows = g.visible_segments(truth.R, truth.t)
    model_px = frame.camera.project_model(g.seg_3d[rows], truth.R, truth.t)
    soft = g.seg_kind[rows] != SHARP
    evidence, mask = frame.evidence, visible_mask(Path(entry.path))
    shares = evidence.shares(model_px, p.inlier_pixels, p.min_margin_pixels, soft, p.outline_pixels, p.seen_pixels)
    pieces, soft_pieces = visible_pieces(model_px, soft, mask)
    seen = evidence.shares(pieces, p.inlier_pixels, p.min_margin_pixels, soft_pieces, p.outline_pixels) if len(pieces) \
        else shares._replace(confirmed=0.0)
    labels = evidence.counted_pixels(model_px, p.inlier_pixels, p.min_margin_pixels, soft, p.outline_pixels,
                                      p.seen_pixels)
    explained = float((labels[mask] == 2).sum() / max((labels[mask] > 0).sum(), 1))
    return (shares.score, shares._replace(confirmed=seen.confirmed).score,
            shares._replace(explained=explained).score,
            shares._replace(confirmed=seen.confirmed, explained=explained).score)


def main(argv=None) -> int:
    parser = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    add_scene_arguments(parser, n=8, parts=TUNING, conditions=["clutter", "occl30+clutter"])
    parser.add_argument("overrides", nargs="*", help="flat parameters, e.g. pose.inlier_pixels=3")
    args = parser.parse_args(argv)
    params = overridden_params(args.overrides)
    cache = REPO / "data" / "bench"
    floor = params.pose.min_score
    above: dict[str, np.ndarray] = defaultdict(lambda: np.zeros(len(CASES), int))
    images: dict[str, int] = defaultdict(int)
    print("| part | condition | image | " + " | ".join(CASES) + " |")
    print("|---|---|---|" + "---|" * len(CASES))
    for name, step in bench_steps(args.parts, cache).items():
        graph, _ = graph_and_model(step, cache)
        estimator = Estimator(graph, params)
        for condition in args.conditions:
            for i, entry, _, frame in cached_frames(cache, name, condition, params, 0, args.n):
                scores = oracle_scores(estimator, frame, entry)
                above[condition] += np.array(scores) >= floor
                images[condition] += 1
                print(f"| {name} | {condition} | {i} | " + " | ".join(f"{s:.3f}" for s in scores) + " |", flush=True)
        estimator.close()
    print(f"\nrefined truths at or above pose.min_score {floor}")
    print("| condition | images | " + " | ".join(CASES) + " |")
    print("|---|---|" + "---|" * len(CASES))
    for condition, counts in above.items():
        print(f"| {condition} | {images[condition]} | " + " | ".join(str(c) for c in counts) + " |")
    return 0


if __name__ == "__main__":
    sys.exit(main())
