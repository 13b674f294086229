"""Where the template search loses the truth: for each image of a cached bench scene, the
rank among all coarse templates (``online/search.py``) of the best template near the true
pose (view within 20 degrees, size within 20 %, position within 10 % of the part's
diameter), its score against the best score, and whether a hypothesis handed to the
refinement is near the truth.

    python bench/search_oracle.py GRAPH.brepose.npz SCENE_DIR [--first 12] [search.param=value ...]

The kernel ranks only its best 8 x max(seeds, hypotheses, windows) templates (the others
score -1 and have no position): a rank beyond that shows as -1 (no near template); pass
``search.seeds=1024`` to rank nearly all of them.
"""
from __future__ import annotations

import argparse
import sys
from pathlib import Path

import cv2
import numpy as np

REPO = Path(__file__).resolve().parents[1]
sys.path.insert(0, str(REPO))

from bench.accuracy import overridden_params  # noqa: E402
from brepose_ros.aspect_graph import AspectGraph  # noqa: E402
from brepose_ros.camera import virtual_alignment  # noqa: E402
from brepose_ros.geometry import rot_z, rotation_angle_deg  # noqa: E402
from brepose_ros.online.frame import Frame  # noqa: E402
from brepose_ros.online.image_edges import detect_edges  # noqa: E402
from brepose_ros.online.refinement import pose_from_similarity  # noqa: E402
from brepose_ros.online.search import TemplateSearch  # noqa: E402
from brepose_ros.scene_folder import load_scene  # noqa: E402

NEAR_DEG, NEAR_SIZE, NEAR_POSITION = 20.0, 1.2, 0.1


def main(argv=None) -> int:
    parser = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    parser.add_argument("graph")
    parser.add_argument("scene")
    parser.add_argument("--first", type=int, default=12, help="images of the scene")
    parser.add_argument("overrides", nargs="*", help="flat parameters, e.g. search.angles=36")
    args = parser.parse_args(argv)
    p = overridden_params(args.overrides)
    graph = AspectGraph.load(args.graph)
    search = TemplateSearch(graph, p.search)
    scene = load_scene(args.scene)
    camera = scene.camera
    coarse_ranks, kept_near = [], []
    print("| image | templates | best score | best near-truth score | its rank | hypotheses near truth |")
    print("|---|---|---|---|---|---|")
    for entry in scene.entries[:args.first]:
        frame = Frame.of(detect_edges(cv2.imread(str(entry.path), cv2.IMREAD_UNCHANGED), p.edges), camera)
        c = search.coarse(frame, p.search)
        near = near_templates(c, graph, camera, entry)
        order = np.argsort(-c.score)
        rank = np.empty_like(order)
        rank[order] = np.arange(len(order))
        best_rank = int(rank[near].min()) if near.any() else -1
        hypotheses = search.hypotheses(frame, p.search)
        near_hypotheses = sum(hypothesis_near(graph, h, entry) for h in hypotheses)
        coarse_ranks.append(best_rank)
        kept_near.append(near_hypotheses > 0)
        print(f"| {entry.image} | {len(c.score)} | {c.score[order[0]]:.2f} | "
              f"{c.score[near].max() if near.any() else float('nan'):.2f} | {best_rank} | "
              f"{near_hypotheses} of {len(hypotheses)} |", flush=True)
    ranks = np.array(coarse_ranks)
    found = ranks >= 0
    print(f"\nnear-truth template among the best 32 / 100 / 1000: {np.mean(found & (ranks < 32)):.2f} / "
          f"{np.mean(found & (ranks < 100)):.2f} / {np.mean(found & (ranks < 1000)):.2f}; "
          f"a hypothesis handed to the refinement near the truth: {np.mean(kept_near):.2f}")
    return 0


def near_templates(c, graph, camera, entry) -> np.ndarray:
    """Which coarse templates lie near the true pose (module doc)."""
    center = entry.R @ graph.model_center + entry.t
    center_n = center[:2] / center[2]
    R_virtual = virtual_alignment(center_n).T @ entry.R
    true_size = camera.focal * graph.model_diameter / np.linalg.norm(center)
    true_px = np.array([camera.fx * center_n[0] + camera.cx, camera.fy * center_n[1] + camera.cy])
    angles, views = np.unique(c.angle), np.unique(c.view)
    turned = np.einsum("aij,vjk->avik", np.stack([rot_z(a) for a in angles]), graph.view_rotations[views])
    cos = (np.einsum("avij,ij->av", turned, R_virtual) - 1) / 2
    rotation = np.degrees(np.arccos(np.clip(cos, -1, 1)))[np.searchsorted(angles, c.angle),
                                                          np.searchsorted(views, c.view)]
    x, y = c.center_px()
    return (rotation < NEAR_DEG) & (np.abs(np.log(c.size / true_size)) < np.log(NEAR_SIZE)) \
        & (np.hypot(x - true_px[0], y - true_px[1]) < NEAR_POSITION * true_size)


def hypothesis_near(graph, h, entry) -> bool:
    R, t = pose_from_similarity(graph.view_rotations[h.view], graph.model_center, scale=h.scale, phi=h.phi,
                                shift=h.shift, R_align=h.region.R_align)
    true_center, center = entry.R @ graph.model_center + entry.t, R @ graph.model_center + t
    lateral = np.linalg.norm(true_center[:2] / true_center[2] - center[:2] / center[2]) * true_center[2]
    return bool(rotation_angle_deg(R, entry.R) < NEAR_DEG and lateral < NEAR_POSITION * graph.model_diameter
                and abs(np.log(center[2] / true_center[2])) < np.log(NEAR_SIZE))


if __name__ == "__main__":
    sys.exit(main())
