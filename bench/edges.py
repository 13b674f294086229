"""Time each stage of the image edge stage (brepose_ros.online.image_edges) per 640x480 image.

    python bench/edges.py [IMAGE ...] [--repeat N]

Without IMAGE a synthetic scene is used (three grey polygons, blur, noise sigma 4). Every
stage runs N times on the previous stage's output; the table shows the median and the
fastest run in milliseconds (the fastest is the least disturbed by other processes on a
shared machine) and the number of segments or edge pixels the stage produced. The last
row merges 1100 pieces of 100 broken lines, the size the merge has to stay fast for.
"""
from __future__ import annotations

import argparse
import statistics
import time

import cv2
import numpy as np

from brepose_ros.online.image_edges import (
    EdgeParams,
    canny_edges,
    extract_segments,
    hough_segments,
    lsd_segments,
    merge_segments,
    refine_segments,
    to_gray,
)


def synthetic_scene() -> np.ndarray:
    image = np.full((480, 640), 110.0, np.float32)
    polygons = [
        cv2.boxPoints(((170, 150), (220, 120), 17)),
        np.stack([460 + 110 * np.cos(np.deg2rad(10 + 60 * np.arange(6))),
                  300 + 110 * np.sin(np.deg2rad(10 + 60 * np.arange(6)))], axis=1),
        cv2.boxPoints(((200, 360), (160, 90), -35)),
    ]
    for polygon, grey in zip(polygons, (170, 60, 145)):
        mask = np.zeros(image.shape, np.uint8)
        cv2.fillPoly(mask, [np.round(polygon * 16).astype(np.int32)], 255, shift=4)
        image[mask > 0] = grey
    image = cv2.GaussianBlur(image, (0, 0), 1.0) + np.random.default_rng(0).normal(0, 4, image.shape)
    return np.clip(np.round(image), 0, 255).astype(np.uint8)


def broken_lines() -> np.ndarray:
    """1100 pieces: 100 lines (10 directions x 10 offsets), each cut into 11 with 4 px gaps."""
    rng = np.random.default_rng(7)
    pieces = []
    for k in range(10):
        u = np.array([np.cos(np.deg2rad(18 * k)), np.sin(np.deg2rad(18 * k))])
        n = np.array([-u[1], u[0]])
        for offset in range(10):
            origin = np.array([320.0, 240.0]) + (offset - 4.5) * 40 * n - 200 * u
            cuts = np.linspace(0, 400, 12)[1:-1] + rng.uniform(-10, 10, 10)
            for a, b in zip(np.r_[0, cuts + 4], np.r_[cuts, 400]):
                pieces.append([origin + a * u + rng.normal(0, 0.3) * n, origin + b * u + rng.normal(0, 0.3) * n])
    return np.array(pieces)


def timed(repeat: int, function, *args):
    """(result, median ms, fastest ms) of ``repeat`` calls."""
    times = []
    for _ in range(repeat):
        start = time.perf_counter()
        result = function(*args)
        times.append((time.perf_counter() - start) * 1e3)
    return result, statistics.median(times), min(times)


def stage_rows(image: np.ndarray, repeat: int) -> list[tuple[str, float, float, int]]:
    params = EdgeParams()
    lsd = EdgeParams(detector="lsd")
    rows = []

    def run(name, function, *args):
        result, median, fastest = timed(repeat, function, *args)
        count = len(result) if result.ndim == 3 else np.count_nonzero(result) if result.dtype == np.uint8 else -1
        rows.append((name, median, fastest, int(count)))
        return result

    gray = run("gray", to_gray, image)
    edges = run("canny (blur, Sobel, thresholds, Canny)", canny_edges, gray, params)
    raw = run("hough (HoughLinesP)", hough_segments, edges, params)
    merged = run("merge", merge_segments, raw, params)
    refined = run("refine to Canny pixels", refine_segments, merged, edges, params)
    run("merge again", merge_segments, refined, params)
    run("extract_segments, hough (total)", extract_segments, image, params)
    lines = run("lsd (LSD)", lsd_segments, gray, lsd)
    run("lsd merge", merge_segments, lines, lsd)
    run("extract_segments, lsd (total)", extract_segments, image, lsd)
    return rows


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    parser.add_argument("images", nargs="*", help="image files (default: a synthetic 640x480 scene)")
    parser.add_argument("--repeat", type=int, default=20, help="runs per stage (default 20)")
    args = parser.parse_args()

    sources = ([(path, cv2.imread(path, cv2.IMREAD_UNCHANGED)) for path in args.images]
               or [("synthetic", synthetic_scene())])
    for name, image in sources:
        if image is None:
            raise SystemExit(f"cannot read image {name}")
        channels = image.shape[2] if image.ndim == 3 else 1
        print(f"\n{name}: {image.shape[1]}x{image.shape[0]}, {image.dtype}, {channels} channel(s)")
        print(f"{'stage':40s} {'median ms':>10s} {'min ms':>8s} {'output':>8s}")
        for stage, median, fastest, count in stage_rows(image, args.repeat):
            print(f"{stage:40s} {median:10.2f} {fastest:8.2f} {count if count >= 0 else '':>8}")
    pieces = broken_lines()
    merged, median, fastest = timed(max(1, args.repeat // 4), merge_segments, pieces, EdgeParams())
    print(f"\n{f'merge {len(pieces)} pieces of 100 lines':40s} {median:10.2f} {fastest:8.2f} {len(merged):8d}")


if __name__ == "__main__":
    main()
