"""Do two versions of the code give the same poses, to the bit? For refactors.

    python bench/same_poses.py --save data/bench/poses_before.npz      # on the old code
    python bench/same_poses.py --compare data/bench/poses_before.npz   # on the new code

Runs the estimator at default parameters on a fixed set of bench scenes (the two
brackets and, when ../shared is beside the clone, the SO-ARM100 base attachment; clean,
clutter and 30 % occlusion with clutter; 8 images each, seed 100) and saves or compares
every image's R, t and score. Exit status 1 when any differs, with the first differences
listed. Graphs and scenes are cached under data/bench/ like bench/accuracy.py's.
"""
from __future__ import annotations

import argparse
import sys
from pathlib import Path

import cv2
import numpy as np
from tqdm import tqdm

REPO = Path(__file__).resolve().parents[1]
sys.path.insert(0, str(REPO))

from bench.accuracy import CONDITIONS, step_file  # noqa: E402
from bench.graphs import cached_graph_path  # noqa: E402
from brepose_ros.aspect_graph import AspectGraph  # noqa: E402
from brepose_ros.geometry import rotation_angle_deg  # noqa: E402
from brepose_ros.online.estimator import Estimator  # noqa: E402
from brepose_ros.synthetic.scenes import SceneConfig, generate_scene  # noqa: E402
from brepose_ros.scene_folder import load_scene  # noqa: E402

PARTS = ["sharp_bracket", "rounded_bracket"]
REAL_PART = REPO.parent / "shared" / "data" / "step" / "09_soarm100__Base_attachment.step"
SAME_CONDITIONS = ("clean", "clutter", "occl30+clutter")
N_IMAGES, SEED = 8, 100


def poses() -> dict[str, np.ndarray]:
    """``{"part/condition/image": [R (9), t (3), score, found]}`` for every bench image."""
    cache = REPO / "data" / "bench"
    cache.mkdir(parents=True, exist_ok=True)
    parts = PARTS + ([str(REAL_PART)] if REAL_PART.exists() else [])
    if not REAL_PART.exists():
        print(f"leaving out the Base attachment: {REAL_PART} is not there", file=sys.stderr)
    out = {}
    for name in parts:
        step = step_file(name, cache) if name in PARTS else Path(name)
        estimator = Estimator(AspectGraph.load(cached_graph_path(step, cache, 5.0)))
        for condition in SAME_CONDITIONS:
            folder = cache / f"scene_{step.stem}_{condition}_{N_IMAGES}_{SEED}"
            if not (folder / "gt.json").exists():
                generate_scene(step, folder, N_IMAGES, seed=SEED, config=SceneConfig(**CONDITIONS[condition]))
            for entry in tqdm(load_scene(folder).entries, desc=f"{step.stem[:20]} {condition}"):
                image = cv2.imread(str(entry.path), cv2.IMREAD_UNCHANGED)
                e = estimator.estimate(image, load_scene(folder).camera)
                R = np.full(9, np.nan) if e.R is None else np.asarray(e.R).ravel()
                t = np.full(3, np.nan) if e.t is None else np.asarray(e.t)
                out[f"{step.stem}/{condition}/{entry.image}"] = np.concatenate([R, t, [e.score, e.found]])
        estimator.close()
    return out


def main(argv=None) -> int:
    parser = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    action = parser.add_mutually_exclusive_group(required=True)
    action.add_argument("--save", type=Path, help="write this run's poses here")
    action.add_argument("--compare", type=Path, help="compare this run's poses with a saved run")
    args = parser.parse_args(argv)
    now = poses()
    if args.save:
        np.savez(args.save, **now)
        print(f"{len(now)} poses saved to {args.save}")
        return 0
    with np.load(args.compare) as saved:
        before = {k: saved[k] for k in saved.files}
    run_here = {k.split("/")[0] for k in now}
    not_run = {k for k in before if k.split("/")[0] not in run_here}
    if not_run:
        parts = sorted({k.split("/")[0] for k in not_run})
        print(f"{len(not_run)} saved poses of parts not run here ({', '.join(parts)}) not compared", file=sys.stderr)
    differ = [k for k in sorted((set(before) - not_run) | set(now))
              if k not in before or k not in now or not np.array_equal(before[k], now[k], equal_nan=True)]
    print(f"{len(now)} poses, {len(now) - len(differ)} identical to the bit, {len(differ)} differ")
    both = [k for k in differ if k in before and k in now]
    flipped = [k for k in both if np.isnan(before[k][0]) != np.isnan(now[k][0])]
    moved = [k for k in both if k not in flipped and not np.isnan(now[k][0])]
    if moved:
        rotation = max(rotation_angle_deg(before[k][:9].reshape(3, 3), now[k][:9].reshape(3, 3)) for k in moved)
        translation = max(1000 * np.linalg.norm(before[k][9:12] - now[k][9:12]) for k in moved)
        print(f"  of those found both times, the largest change: {rotation:.2g} deg, {translation:.2g} mm; "
              f"found in one run only: {len(flipped)}")
    for k in differ[:10]:
        print(f"  {k}: {before.get(k)} -> {now.get(k)}")
    return 1 if differ else 0


if __name__ == "__main__":
    sys.exit(main())
