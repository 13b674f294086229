"""Accuracy of the estimator on generated scenes of varied look, per part, condition and part set.

    python bench/accuracy.py [--n 24] [--parts shaft flange ...] [--conditions clean clutter ...]
                             [--params FILE.yaml] [--label NAME] [--look varied|plain] [--paper-only]
    python bench/accuracy.py --report RESULTS.json [MORE.json ...]   # tables of saved runs

Ten parts: the seed paper's brackets, three built-ins of issue 11 (``shaft``: curved and
rotational, ``flange``: a disc with a bolt circle, ``notched_plate``: symmetric but for one
notch) and five real parts from ../shared/data/step. The tuning set (``TUNING``: parameters
and thresholds may be chosen on these) is reported apart from the leave-out set (everything
else), which is where targets are judged. Conditions: ``clean`` (centred, nothing else in
view), ``clutter`` (anywhere in the central 80 %, 4 shapes behind it), ``occlNN+clutter``
(the same with NN % of the silhouette hidden in front) and ``occl30`` (30 % hidden, centred,
no clutter). Scenes use the varied look (``synthetic.looks``): random lights, gloss,
backgrounds, blur and noise, props of many shapes including other parts, the part spanning
15-70 % of the image. Aspect graphs (5 degrees = 1,505 views) and scenes are cached under
data/bench/ (git-ignored); a scene of more images serves a smaller --n (image i depends on
(seed, i) only). Results (with per-image errors) go to data/bench/results/accuracy_LABEL.json,
rewritten after every row, for ``bench/plot_accuracy.py``; ``--report`` prints the tables of
one or more such files, pooling the images of a part and condition (runs split by part, or
extended with ``--start``). Metrics follow ../shared/CONVENTIONS.md.

Images 0-15 are where the estimator's choices were measured for twenty sessions, and main
sits on a lucky draw there (any change, even a nudge of one threshold, loses about ten of
their 480); images ``FRESH_START`` on were held out. Judge a change on the fresh images
64-95 (``--start 64`` and ``--start 80``, 960 images) with bench/compare_runs.py's sign
test, against the tens of images any change moves, not on images 0-15
(docs/results/accuracy.md, sessions 22 and 23).
"""
from __future__ import annotations

import argparse
import dataclasses
import datetime
import fcntl
import json
import os
import shutil
import subprocess
import sys
from pathlib import Path

REPO = Path(__file__).resolve().parents[1]
sys.path.insert(0, str(REPO))

import cv2  # noqa: E402
import numpy as np  # noqa: E402
import yaml  # noqa: E402
from tqdm import tqdm  # noqa: E402

from bench.graphs import cached_graph_path  # noqa: E402
from brepose_ros.aspect_graph import AspectGraph  # noqa: E402
from brepose_ros.evaluation.metrics import (  # noqa: E402
    NOT_FOUND_ERROR_RATE, ModelPoints, evaluate_scene, scene_summary)
from brepose_ros.offline.cad import load_step, tessellate  # noqa: E402
from brepose_ros.online.estimator import Estimator  # noqa: E402
from brepose_ros.online.frame import Frame  # noqa: E402
from brepose_ros.online.image_edges import detect_edges  # noqa: E402
from brepose_ros.params import EstimatorParams  # noqa: E402
from brepose_ros.scene_folder import load_scene  # noqa: E402
from brepose_ros.synthetic import shapes  # noqa: E402
from brepose_ros.synthetic.scenes import LOOKS, SceneConfig, generate_scene  # noqa: E402

REAL_STEP = REPO.parent / "shared" / "data" / "step"
#: Short name -> built-in part name or STEP file in ../shared/data/step.
PARTS = {
    "sharp_bracket": "sharp_bracket",
    "rounded_bracket": "rounded_bracket",
    "base_attachment": "09_soarm100__Base_attachment.step",
    "shaft": "shaft",
    "flange": "flange",
    "notched_plate": "notched_plate",
    "motor1_holder": "11_soarm100__Motor1_holder.step",
    "wrist_mount": "13_soarm100__SO-ARM101_camera_wrist_mount.step",
    "screw": "06_occt__screw.step",
    "mounting_plate": "10_soarm100__Seeedstudio_Mounting_Plate_SO101.step",
}
#: Parts the estimator may be tuned on; every other part is leave-out.
TUNING = ("sharp_bracket", "rounded_bracket", "base_attachment")
#: Other parts that may appear as occluders and clutter (never one of PARTS: its twin in
#: view would be a right answer that the ground truth calls wrong).
DISTRACTORS = ("sample_bracket", "08_soarm100__STS3215_03a.step", "12_soarm100__4040_base_mount.step")
#: Bump when the scene generator changes, so cached scenes are regrown.
SCENES_VERSION = 1
SPAN = (0.15, 0.70)
#: the first held-out image: before 2026-12-04 no choice of the estimator was measured on the
#: images from here on (that day pose.min_score was chosen on the confidence's records 0-191)
FRESH_START = 64
CLUTTER = 4
OCCLUSIONS = (10, 20, 30, 40, 50)
CONDITIONS = {"clean": dict(), "clutter": dict(offcenter=True, clutter=CLUTTER)}
CONDITIONS |= {f"occl{p}+clutter": dict(offcenter=True, clutter=CLUTTER, occlusion=p / 100) for p in OCCLUSIONS}
CONDITIONS["occl30"] = dict(occlusion=0.3)


def part_set(name: str) -> str:
    return "tune" if name in TUNING else "leave-out"


def add_scene_arguments(parser: argparse.ArgumentParser, *, parts, conditions, n: int | None = None,
                        start: bool = False) -> None:
    """The bench scenes a script runs on: ``--parts`` and ``--conditions`` (with these defaults), and
    ``--n`` images per part and condition and a first image ``--start`` where the script takes them."""
    if n is not None:
        parser.add_argument("--n", type=int, default=n, help=f"images per part and condition (default {n})")
    if start:
        parser.add_argument("--start", type=int, default=0, help="first image index")
    parser.add_argument("--parts", nargs="*", default=list(parts), choices=list(PARTS))
    parser.add_argument("--conditions", nargs="*", default=list(conditions), choices=list(CONDITIONS))


def step_file(source: str, cache: Path) -> Path | None:
    """The STEP file of a built-in part (exported once into the cache) or of a real part;
    None when ../shared/data is not beside the clone."""
    if source in shapes.BUILTIN:
        path = cache / "steps" / f"{source}.step"
        return path if path.exists() else shapes.export_step(source, path)
    path = REAL_STEP / source
    return path if path.exists() else None


def bench_steps(names: list[str], cache: Path) -> dict[str, Path]:
    """The STEP files of the named bench parts; a part whose file is not there (a real part
    without ../shared beside the clone) is left out, and said so on stderr."""
    steps = {name: step_file(PARTS[name], cache) for name in names}
    for name in [name for name, step in steps.items() if step is None]:
        print(f"skipping {name}: {REAL_STEP / PARTS[name]} is not there", file=sys.stderr)
        del steps[name]
    return steps


def graph_and_model(step: Path, cache: Path, step_deg: float = 5.0) -> tuple[AspectGraph, ModelPoints]:
    """A bench part's cached aspect graph and its mesh's points for the pose metrics."""
    graph = AspectGraph.load(cached_graph_path(step, cache, step_deg))
    mesh = tessellate(load_step(step))
    return graph, ModelPoints.from_mesh(mesh.vertices, mesh.triangles)


def scene_path(cache: Path, name: str, condition: str, look: str = "varied", span: tuple[float, float] = SPAN,
               seed: int = 100) -> Path:
    """Where the scene of a bench part in one condition (and look, span, seed) is cached."""
    return cache / scenes_folder(look, span) / f"{name}_{condition}_{seed}"


def cached_frames(cache: Path, name: str, condition: str, params: EstimatorParams, start: int, n: int):
    """Images ``start`` .. ``start + n`` of a bench part's cached scene in one condition
    (``scene_path``): (index, ground-truth entry, image, its edges found at ``params``)."""
    cached = load_scene(scene_path(cache, name, condition))
    for i, entry in enumerate(cached.entries[start:start + n], start=start):
        image = cv2.imread(str(entry.path), cv2.IMREAD_UNCHANGED)
        yield i, entry, image, Frame.of(detect_edges(image, params.edges), cached.camera)


def overridden_params(overrides: list[str]) -> EstimatorParams:
    """The default parameters with flat ``key=value`` overrides (a bench script's positional
    arguments, e.g. ``search.seeds=256``), each value read as a YAML scalar as in a parameter
    file (``false``, ``0.3``) and checked by ``EstimatorParams``."""
    return EstimatorParams().with_flat({k: yaml.safe_load(v) for k, v in (o.split("=", 1) for o in overrides)})


def scene(cache: Path, name: str, step: Path, condition: str, images: int | range, distractors,
          look: str = "varied", span: tuple[float, float] = SPAN, seed: int = 100):
    """Images ``images`` (a range, or a count from the first) of a bench part's cached scene in
    one condition (``scene_path``), grown anew if it holds fewer.

    Bench processes share the cache, so a scene is grown beside the old one under a lock and
    swapped in by renames: another process reading the old images meanwhile still finds them
    (image i depends only on the seed and i, so both folders agree where they overlap)."""
    folder = scene_path(cache, name, condition, look, span, seed)
    config = SceneConfig(span=span, look=look, **CONDITIONS[condition])
    if isinstance(images, int):
        images = range(images)
    folder.parent.mkdir(parents=True, exist_ok=True)
    with open(folder.with_name(folder.name + ".lock"), "w") as lock:
        fcntl.flock(lock, fcntl.LOCK_EX)
        if (folder / "gt.json").exists():
            cached = load_scene(folder)
            if len(cached.entries) >= images.stop:
                return dataclasses.replace(cached, entries=cached.entries[images.start:images.stop])
        growing = folder.with_name(f"{folder.name}.growing-{os.getpid()}")
        shutil.rmtree(growing, ignore_errors=True)
        generate_scene(step, growing, images.stop, seed=seed, config=config, distractors=distractors)
        old = folder.with_name(f"{folder.name}.old-{os.getpid()}")
        if folder.exists():
            folder.rename(old)
        growing.rename(folder)
        shutil.rmtree(old, ignore_errors=True)
    grown = load_scene(folder)
    return dataclasses.replace(grown, entries=grown.entries[images.start:])


def scenes_folder(look: str, span: tuple[float, float]) -> str:
    """The cache folder of scenes of one look and span (the default span keeps its old name)."""
    folder = f"scenes_v{SCENES_VERSION}_{look}"
    return folder if span == SPAN else f"{folder}_span{span[0]:g}-{span[1]:g}"


def distractor_meshes(cache: Path) -> list:
    """The meshes of the DISTRACTORS found (occluders and clutter of the scenes)."""
    steps = [step_file(source, cache) for source in DISTRACTORS]
    return [tessellate(load_step(step)) for step in steps if step is not None]


def row_fields(name: str, condition: str) -> dict:
    """The fields that place a results row (one part in one condition), which
    ``bench/plot_accuracy.py`` and ``--report`` pool by."""
    return {"part": name, "set": part_set(name), "condition": condition,
            "occlusion": CONDITIONS[condition].get("occlusion", 0.0), "clutter": CONDITIONS[condition].get("clutter", 0)}


def image_record(result) -> dict:
    e = result.errors
    record = {"image": result.image, "found": e is not None, "score": float(result.estimate.score),
              "error_ratio": float(result.estimate.error_ratio), "confidence": float(result.estimate.confidence),
              "ms": 1000.0 * result.estimate.timings.get("total", 0.0),
              # the twin check's margin (None: the part has no twin), which the confidence weighs
              "symmetry_margin": result.estimate.symmetry_margin}
    if result.estimate.skipped:  # the steps search.time_budget_ms left out
        record["skipped"] = list(result.estimate.skipped)
    if result.estimate.shading_fit is not None:
        record["shading_fit"] = float(result.estimate.shading_fit)
    return record | (e.to_dict() if e is not None else {})


def at_found_rule(row: dict, min_confidence: float, min_score: float = 0.0, min_shading: float = 0.0) -> dict:
    """A results row as if ``pose.min_confidence``, ``pose.min_score`` and
    ``pose.min_shading_fit`` had been these: a found pose of lower confidence, score or shading
    fit becomes not found (records without a confidence or a fit are kept as found; a rule can
    only drop poses the run found)."""
    dropped = [i for i in row["images"] if i["found"] and (i.get("confidence", 1.0) < min_confidence or
                                                           i["score"] < min_score or
                                                           i.get("shading_fit", 1.0) < min_shading)]
    images = [{"image": i["image"], "found": False, "score": i["score"], "error_ratio": i["error_ratio"],
               "confidence": i["confidence"], "ms": i["ms"]} if i in dropped else i for i in row["images"]]
    return row | {"images": images}


def git(*args) -> str:
    try:
        return subprocess.run(["git", "-C", str(REPO), *args], capture_output=True, text=True,
                              check=True).stdout.strip()
    except (OSError, subprocess.CalledProcessError):
        return "unknown"


def rates(images: list[dict]) -> dict:
    """Success (plain, and up to the part's exact symmetries: the flange turned by its bolt
    circle is the same pose), ADD-S < 0.1 d and er < 0.01 rates, median errors (of found
    poses) and median time, from per-image records (so rows of split runs can be pooled)."""
    n = max(len(images), 1)
    found = [i for i in images if i["found"]]

    def median(key):
        return float(np.median([i[key] for i in found])) if found else float("nan")

    return {"n": len(images), "success": sum(i.get("success", False) for i in found) / n,
            # records written before success_sym existed had no symmetric parts
            "success_sym": sum(i.get("success_sym", i.get("success", False)) for i in found) / n,
            "add_s": sum(i["add_s"] < 0.1 for i in found) / n,
            "er": sum(i["error_rate"] < 0.01 for i in found) / n,
            "rot": median("rotation_deg"), "trans": median("translation_mm"),
            "mean_er": float(np.mean([i["error_rate"] if i["found"] else NOT_FOUND_ERROR_RATE for i in images]))
            if images else float("nan"),
            "ms": float(np.median([i["ms"] for i in images])) if images else float("nan")}


def print_tables(rows: list[dict]) -> None:
    """Per part and condition, then per set; rows of one part and condition are pooled."""
    pooled: dict[tuple, list] = {}
    for row in rows:
        pooled.setdefault((row["set"], row["part"], row["condition"]), []).extend(row["images"])
    print("\n| set | part | condition | images | success | success up to symmetry | ADD-S < 0.1 d | er < 0.01 | "
          "median rot (deg) | median trans (mm) | mean er | median ms |")
    print("|---|---|---|---|---|---|---|---|---|---|---|---|")
    for (part_set_name, part, condition), images in pooled.items():
        r = rates(images)
        print(f"| {part_set_name} | {part} | {condition} | {r['n']} | {r['success']:.2f} | {r['success_sym']:.2f} | "
              f"{r['add_s']:.2f} | "
              f"{r['er']:.2f} | {r['rot']:.1f} | {r['trans']:.1f} | {r['mean_er']:.3f} | {r['ms']:.0f} |")
    sets = sorted({key[0] for key in pooled}, reverse=True)  # tune first
    conditions = list(dict.fromkeys(key[2] for key in pooled))
    print("\nPer set (pooled over its parts' images): success / success up to symmetry / ADD-S < 0.1 d / "
          "median ms\n")
    print("| condition | " + " | ".join(f"{s} ({len({k[1] for k in pooled if k[0] == s})} parts)"
                                        for s in sets) + " |")
    print("|---|" + "---|" * len(sets))
    for condition in conditions:
        cells = []
        for name in sets:
            r = rates([i for key, images in pooled.items() if key[0] == name and key[2] == condition
                       for i in images])
            cells.append(f"{r['success']:.2f} / {r['success_sym']:.2f} / {r['add_s']:.2f} / {r['ms']:.0f}")
        print(f"| {condition} | " + " | ".join(cells) + " |")


def print_found(rows: list[dict]) -> None:
    """Per set, how many images a pose was reported for and how many of those were right
    (up to symmetry): what a user of the found poses sees."""
    print("\n| set | images | found | right (up to symmetry) | right of found |\n|---|---|---|---|---|")
    for name in sorted({row["set"] for row in rows}, reverse=True):
        images = [i for row in rows if row["set"] == name for i in row["images"]]
        found = [i for i in images if i["found"]]
        right = sum(i.get("success_sym", i.get("success", False)) for i in found)
        print(f"| {name} | {len(images)} | {len(found)} | {right} | {right / max(len(found), 1):.2f} |")


def main(argv=None) -> int:
    parser = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    add_scene_arguments(parser, n=24, parts=PARTS, conditions=CONDITIONS)
    parser.add_argument("--params", type=Path, help="estimator YAML (config/estimator.yaml layout)")
    parser.add_argument("--label", help="names the results file and the plot's line "
                                        "(default: the --params file's stem, else 'default')")
    parser.add_argument("--paper-only", action="store_true",
                        help="the seed paper's method alone: the matched view as the pose, no refinement")
    parser.add_argument("--look", default="varied", choices=LOOKS, help="scene look (default varied)")
    parser.add_argument("--step-deg", type=float, default=5.0, help="aspect graph view spacing")
    parser.add_argument("--seed", type=int, default=100)
    parser.add_argument("--span", type=float, nargs=2, default=SPAN, metavar=("LOW", "HIGH"),
                        help=f"the part's projected size, share of the image's smaller side (default {SPAN[0]:g} "
                             f"{SPAN[1]:g}); other spans get scene folders of their own")
    parser.add_argument("--start", type=int, default=0,
                        help="first image index: --start 12 --n 12 adds images 12-23 to a run of --n 12; "
                             f"--start {FRESH_START} the held-out images (module doc)")
    parser.add_argument("--out", type=Path, help="results JSON (default data/bench/results/accuracy_LABEL.json)")
    parser.add_argument("--report", type=Path, nargs="+", metavar="RESULTS",
                        help="print the tables of saved results files instead of running")
    parser.add_argument("--min-confidence", type=float, default=0.0,
                        help="with --report: the tables as if pose.min_confidence had been this (a pose of lower "
                             "confidence not found)")
    parser.add_argument("--min-shading", type=float, default=0.0,
                        help="with --report: the same for pose.min_shading_fit (runs record the found poses' fit)")
    parser.add_argument("--min-score", type=float, default=0.0,
                        help="with --report: the same for pose.min_score (a rule can only drop poses the run found; "
                             "not the same as a run at that floor: the twin check takes only twins scoring at least "
                             "pose.min_score as rivals, so choose a floor by running at it)")
    args = parser.parse_args(argv)
    if args.report:
        rows = [row for path in args.report for row in json.loads(path.read_text())["rows"]]
        rows = [at_found_rule(row, args.min_confidence, args.min_score, args.min_shading) for row in rows]
        print_tables(rows)
        print_found(rows)
        return 0
    if args.n < 1 or args.start < 0:
        parser.error("--n must be at least 1 and --start not negative")
    params = EstimatorParams.load(args.params) if args.params else EstimatorParams()
    label = args.label or (args.params.stem if args.params else "default")
    cache = REPO / "data" / "bench"
    out = args.out or cache / "results" / f"accuracy_{label}.json"

    distractors = distractor_meshes(cache)
    parts = bench_steps(args.parts, cache)

    run = {"label": label, "commit": git("rev-parse", "--short", "HEAD"),
           "dirty": bool(git("status", "--porcelain", "--untracked-files=no")),
           "date": datetime.datetime.now(datetime.timezone.utc).isoformat(timespec="seconds"),
           "command": " ".join(["python", "bench/accuracy.py", *(argv if argv is not None else sys.argv[1:])]),
           "paper_only": args.paper_only, "n": args.n, "start": args.start, "look": args.look, "seed": args.seed, "step_deg": args.step_deg, "span": tuple(args.span),
           "tuning": list(TUNING), "params": params.to_dict(), "rows": []}
    rows = run["rows"]
    out.parent.mkdir(parents=True, exist_ok=True)
    progress = tqdm(total=len(parts) * len(args.conditions) * args.n, desc="images", unit="img")
    for name, step in parts.items():
        progress.set_postfix_str(f"{name}: aspect graph")
        graph, model = graph_and_model(step, cache, args.step_deg)
        estimator = Estimator(graph, params)
        for condition in args.conditions:
            progress.set_postfix_str(f"{name}: {condition}")
            images = range(args.start, args.start + args.n)
            results = evaluate_scene(scene(cache, name, step, condition, images, distractors, args.look,
                                           tuple(args.span), args.seed),
                                     estimator, model, on_image=lambda *_: progress.update(),
                                     paper_only=args.paper_only)
            rows.append(row_fields(name, condition) | {
                "views": graph.n_views, "summary": scene_summary(results),
                "images": [image_record(r) for r in results]})
            out.write_text(json.dumps(run, indent=1) + "\n")
        estimator.close()
    progress.close()

    print_tables(rows)
    print(f"\nwrote {out}", file=sys.stderr)
    return 0


if __name__ == "__main__":
    sys.exit(main())
