"""Which unknown the template search fails to settle on a partly hidden part: its view, its
place or its size. Per image of the cached bench scenes, the rank of the best near-truth
template (``search_oracle.near_templates``: view within 20 degrees, size within 20 %,
position within 10 % of the diameter) among the templates of every graph view (not only
the search's coarse views) x ``search.angles`` in-plane angles, scored by the search's own
kernel (``search.score_templates``, every template ranked) on the coarse cells about a place:

- ``coarse``: the shipped search over the whole image (coarse views, every size and cell;
  ``search.seeds`` 1,024 so that its kernel ranks nearly every template);
- ``view``: the true size, cells within ``--reach`` of the true centre (only the view unknown);
- ``place``: the true size, cells within ``--wide`` of the true centre;
- ``size``: the search's sizes, cells within ``--reach`` of the true centre;
- ``places``: about each of the search's best ``search.windows`` places (``TemplateSearch.places``),
  the place's size and its two neighbours (``search.size_step``), cells within a quarter of
  it: y where a near template is among that place's best ``--top``.

    python bench/place_oracle.py [--n 6] [--parts sharp_bracket ...] [--conditions occl30+clutter ...]

A rank is -1 where no template is near the truth (the part below ``search.min_size_fraction``
for ``coarse`` and ``size``). The last table counts the images with a rank below ``--top``
(``coarse``: below 128, the seeds' share).
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

from bench.accuracy import TUNING, add_scene_arguments, bench_steps, part_set, scene_path  # noqa: E402
from bench.graphs import cached_graph_path  # noqa: E402
from bench.search_oracle import near_templates  # noqa: E402
from brepose_ros.aspect_graph import AspectGraph  # noqa: E402
from brepose_ros.online import search as S  # noqa: E402
from brepose_ros.online.frame import Frame  # noqa: E402
from brepose_ros.online.image_edges import detect_edges  # noqa: E402
from brepose_ros.params import EstimatorParams, SearchParams  # noqa: E402
from brepose_ros.scene_folder import load_scene  # noqa: E402

MODES = ("coarse", "view", "place", "size", "places")


def scores_about(search: S.TemplateSearch, frame: Frame, p: SearchParams, center_px: np.ndarray, sizes: np.ndarray,
                 reach: int, keep: int = 0) -> S.CoarseResult:
    """Every graph view x angle x size scored by the search's kernel on the coarse cells within
    ``reach`` cells of ``center_px`` (the ``keep`` best ranked, 0: all)."""
    f, views = p.coarse_factor, np.arange(search.graph.n_views)
    pad = int(np.ceil(sizes[-1] / f / 2)) + p.spread + 1
    maps = S.ResponseMaps.of(frame.evidence, f, p.spread, pad)
    chance = np.stack([maps.chance(max(3, int(round(d / f)) | 1)) for d in sizes])
    (h, w), (cx, cy) = maps.shape, (center_px // f).astype(int)
    y0, x0 = int(np.clip(cy - reach, 0, h - 1)), int(np.clip(cx - reach, 0, w - 1))
    y1, x1 = max(min(cy + reach + 1, h), y0 + 1), max(min(cx + reach + 1, w), x0 + 1)
    window = np.ascontiguousarray(maps.maps[:, y0:y1 + 2 * pad, x0:x1 + 2 * pad])
    angles = np.arange(p.angles) * (2 * np.pi / p.angles)
    dx, dy, bins = search.templates(views, angles, sizes, f)
    n, per_view = len(dx), p.angles * len(sizes)
    c = S.CoarseResult(score=np.full(n, -1.0), y=np.zeros(n, np.int64), x=np.zeros(n, np.int64),
                       view=np.repeat(views, per_view), angle=np.tile(np.repeat(angles, len(sizes)), len(views)),
                       size=np.tile(sizes, len(views) * p.angles),
                       size_index=np.tile(np.arange(len(sizes)), len(views) * p.angles), factor=f)
    S.score_templates(window, S.block_bounds(window), pad, dx, dy, bins, c.size_index,
                      np.ascontiguousarray(chance[:, :, y0:y1, x0:x1]), search.library.n_points // S.PROBE_STRIDE,
                      S.probe_share(maps, p), keep, c.score, c.y, c.x)
    c.y += y0
    c.x += x0
    return c


def near_rank(c: S.CoarseResult, graph, camera, entry) -> int:
    """The rank of the best near-truth template of a result (-1: none)."""
    near = near_templates(c, graph, camera, entry) & (c.score > -1.0)
    order = np.argsort(-c.score)
    rank = np.empty_like(order)
    rank[order] = np.arange(len(order))
    return int(rank[near].min()) if near.any() else -1


def image_row(search: S.TemplateSearch, frame: Frame, p: SearchParams, entry, args) -> dict:
    graph, camera = search.graph, frame.camera
    center = entry.R @ graph.model_center + entry.t
    true_px = camera.project(center[None])[0]
    true_size = np.array([camera.focal * graph.model_diameter / np.linalg.norm(center)])
    ranked = dataclasses.replace(p, seeds=1024)  # the kernel then ranks nearly every template
    coarse = search.coarse(frame, ranked)
    row = {"coarse": near_rank(coarse, graph, camera, entry),
           "view": near_rank(scores_about(search, frame, p, true_px, true_size, args.reach), graph, camera, entry),
           "place": near_rank(scores_about(search, frame, p, true_px, true_size, args.wide), graph, camera, entry),
           "size": near_rank(scores_about(search, frame, p, true_px, search.sizes(frame, p), args.reach), graph,
                             camera, entry)}
    places = []
    for place, size in search.places(coarse, p.windows):
        sizes = size * p.size_step ** np.array([-1.0, 0.0, 1.0])
        c = scores_about(search, frame, p, place, sizes, int(np.ceil(size / 4 / p.coarse_factor)), keep=4 * args.top)
        places.append(0 <= near_rank(c, graph, camera, entry) < args.top)
    row["places"] = "".join("y" if near else "n" for near in places)
    return row


def main(argv=None) -> int:
    parser = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    add_scene_arguments(parser, n=6, parts=TUNING, conditions=["occl30+clutter"])
    parser.add_argument("--reach", type=int, default=3, help="coarse cells about the true centre (view, size)")
    parser.add_argument("--wide", type=int, default=8, help="coarse cells about the true centre (place)")
    parser.add_argument("--top", type=int, default=16, help="a rank below this counts as found")
    args = parser.parse_args(argv)
    p = EstimatorParams()
    cache = REPO / "data" / "bench"
    rows = []
    print("| part | condition | image | " + " | ".join(MODES) + " |")
    print("|---" * (3 + len(MODES)) + "|")
    for name, step in bench_steps(args.parts, cache).items():
        search = S.TemplateSearch(AspectGraph.load(cached_graph_path(step, cache, 5.0)), p.search)
        for condition in args.conditions:
            scene = load_scene(scene_path(cache, name, condition))
            for entry in scene.entries[:args.n]:
                image = cv2.imread(str(entry.path), cv2.IMREAD_UNCHANGED)
                frame = Frame.of(detect_edges(image, p.edges), scene.camera)
                row = image_row(search, frame, p.search, entry, args)
                rows.append((part_set(name), condition, row))
                print(f"| {name} | {condition} | {Path(entry.image).name} | "
                      + " | ".join(str(row[m]) for m in MODES) + " |", flush=True)
    print(f"\nImages with a near-truth template among the best {args.top} (coarse: 128; places: of any place)\n")
    print("| set | condition | images | " + " | ".join(MODES) + " |")
    print("|---" * (3 + len(MODES)) + "|")
    for key in dict.fromkeys((s, c) for s, c, _ in rows):
        group = [r for s, c, r in rows if (s, c) == key]
        counts = [sum(0 <= r["coarse"] < 128 for r in group)]
        counts += [sum(0 <= r[m] < args.top for r in group) for m in ("view", "place", "size")]
        counts += [sum("y" in r["places"] for r in group)]
        print(f"| {key[0]} | {key[1]} | {len(group)} | " + " | ".join(map(str, counts)) + " |")
    return 0


if __name__ == "__main__":
    sys.exit(main())
