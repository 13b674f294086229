"""Peer baseline (issue 5): OpenCV's LINE-2D template matcher side by side with our estimator.

    python bench/peer_linemod.py                      # sharp_bracket, 12 clean images
    python bench/peer_linemod.py --occluded           # + 12 images with 30 % occlusion, clutter
    python bench/peer_linemod.py --part rounded_bracket --images 20 --peer-step 7.5
    python bench/peer_linemod.py --bench --n 16 --start 64 --label line2d   # bench/accuracy.py's scenes

(run with the project venv: ``env -u _ROS_WHEELS_BOOTSTRAP_COMPLETE -u LD_LIBRARY_PATH
.venv/bin/python bench/peer_linemod.py``.)

LINE-2D is ``cv2.linemod`` from opencv-contrib, whose wheel cannot share an environment with
the project's opencv-python-headless, so this script plays two roles:

1. project role (project venv): writes the built-in part's STEP file, generates the scene(s)
   with ``scenes.generate_scene``, compiles (or reuses) our aspect graph, renders the LINE-2D
   base templates of the same STEP model (grey image + part mask, one per view direction of
   a golden-spiral sphere like the aspect graph's and per distance), runs our ``Estimator``
   over every scene and times it;
2. peer role (``data/peer-venv``, created and filled by the first run with ``python -m venv``
   and ``pip install opencv-contrib-python-headless numpy``): the project role calls that
   venv's python on this file with ``--role peer``; it turns every base template into
   ``360 / --inplane-step`` templates by rotating the image about the principal point (a
   rotation about the optical axis is exactly an image rotation about the principal point
   for a pinhole camera; only the lights, fixed to the camera in the scenes, turn with it),
   trains ``cv2.linemod.getDefaultLINE()`` with ``Detector.addTemplate``, matches every
   scene image with ``Detector.match`` and maps the best match back to a pose: R is the
   template's, the part's centre lies on the ray of the matched reference pixel at the
   template's distance (the camera turned onto that ray, so an off-centre part keeps its
   look); it writes predictions JSON (CONVENTIONS.md) with per-image times.

The project role then scores both with ``evaluation.pose_errors`` and prints one table.

With ``--bench`` LINE-2D runs instead on ``bench/accuracy.py``'s own scenes (its parts, varied
look, conditions and image range, templates per part for the bench's span of sizes) and its
results go to ``data/bench/results/accuracy_LABEL.json`` in that script's layout, so that
``bench/plot_accuracy.py`` draws the peer beside the estimator's runs (issue 11's Fig. 9).
Every file goes under ``--out`` (default data/peer, git-ignored): scenes, graph, templates
(reused when their parameters match) and per-run predictions / summary.json.

How LINE-2D is set up, and why:
- OpenCV's ColorGradient modality takes features only on the border of the template mask
  (``extractTemplate`` subtracts the eroded mask), i.e. the part's silhouette, which is what
  LINE-2D with object masks is. ``--interior`` passes no mask instead: templates rendered on
  a black background then give features on every strong gradient, the inner edges too.
- The modality reads 3-channel images only (``quantizedOrientations`` walks 3 channels), so
  grey templates and images are converted to BGR first.
- Views: ``fibonacci_directions(--peer-step)`` with ``view_ups``, the aspect graph's sampling
  and up vectors. Default 10 degrees against the graph's 5, in-plane every 15 degrees, 4
  distances: 376 x 24 x 4 = 36,096 templates, about 1.5 minutes of training on a busy 2-core
  machine (``addTemplate`` costs 1-3 ms at half size). At 5 / 10 degrees it would be about
  220,000 templates and 10 minutes or more. Distances: ``--scales`` per view, set so that
  the projected diameter of the part takes sizes spaced evenly in log over the scene
  generator's range of part sizes.
- ``--downscale 2``: LINE-2D works on half-size images and templates (fx / 2). Its spreading
  (T = 5 and 8 pixels on its two pyramid levels) is meant for parts of about 100 pixels;
  the scenes' parts are 120 to 370 pixels, where the same pose steps move the outline
  twice as many pixels. Templates are 4 times cheaper to train and match, too.
- The pose is the best match's (highest similarity). The top ``--top-k`` templates are kept
  per image; the "oracle" row picks the one nearest the truth, to show how much a
  verification step could add. It is not a method: it reads the ground truth.
"""
from __future__ import annotations

import argparse
import json
import os
import subprocess
import sys
import time
from pathlib import Path

import numpy as np

ROOT = Path(__file__).resolve().parents[1]
CLEAN_ENV = {k: v for k, v in os.environ.items() if k not in ("_ROS_WHEELS_BOOTSTRAP_COMPLETE", "LD_LIBRARY_PATH")}
PEER_PACKAGES = ["opencv-contrib-python-headless", "numpy"]
CLASS_ID = "part"


# ---------------------------------------------------------------------------------------
# Small geometry shared by both roles (numpy only: the peer venv has no brepose_ros)
# ---------------------------------------------------------------------------------------
def rot_z(angle: float) -> np.ndarray:
    c, s = np.cos(angle), np.sin(angle)
    return np.array([[c, -s, 0.0], [s, c, 0.0], [0.0, 0.0, 1.0]])


def turn_onto(ray: np.ndarray) -> np.ndarray:
    """The smallest rotation taking the optical axis (0, 0, 1) onto the unit vector ``ray``."""
    z = np.array([0.0, 0.0, 1.0])
    v, c = np.cross(z, ray), float(z @ ray)
    vx = np.array([[0, -v[2], v[1]], [v[2], 0, -v[0]], [-v[1], v[0], 0]])
    return np.eye(3) + vx + vx @ vx / (1.0 + c)


def template_pose(R_view: np.ndarray, angle: float, distance: float, center: np.ndarray,
                  pixel: np.ndarray, fx: float, fy: float, cx: float, cy: float):
    """Pose of a template (view R, in-plane ``angle``, centre at ``distance`` on the axis)
    whose reference pixel (the projected model centre) was found at ``pixel``."""
    R = rot_z(angle) @ R_view
    ray = np.array([(pixel[0] - cx) / fx, (pixel[1] - cy) / fy, 1.0])
    Q = turn_onto(ray / np.linalg.norm(ray))
    R_est = Q @ R
    t_est = Q @ (np.array([0.0, 0.0, distance]) - R @ center)
    return R_est, t_est


# ---------------------------------------------------------------------------------------
# Peer role: runs in data/peer-venv with opencv-contrib
# ---------------------------------------------------------------------------------------
def peer_main(args) -> int:
    import cv2

    if not hasattr(cv2, "linemod"):
        print(f"cv2 {cv2.__version__} at {cv2.__file__} has no linemod module", file=sys.stderr)
        return 3
    index = json.loads((Path(args.templates) / "index.json").read_text())
    angles = np.radians(np.arange(0.0, 360.0, args.inplane_step))
    detector = cv2.linemod.getDefaultLINE()
    started = time.perf_counter()
    table = []  # template id -> (base, angle index, reference pixel in the cropped frame)
    skipped = 0
    for b, base in enumerate(index["bases"]):
        image = cv2.imread(str(Path(args.templates) / base["image"]), cv2.IMREAD_GRAYSCALE)
        mask = cv2.imread(str(Path(args.templates) / base["mask"]), cv2.IMREAD_GRAYSCALE)
        c = base["center_px"]
        size = (image.shape[1], image.shape[0])
        for a, angle in enumerate(angles):
            # rot_z(angle) turns camera x towards y: that is cv2's rotation by -angle.
            M = cv2.getRotationMatrix2D((c[0], c[1]), -np.degrees(angle), 1.0)
            warped = cv2.warpAffine(image, M, size, flags=cv2.INTER_LINEAR, borderValue=0)
            warped_mask = cv2.warpAffine(mask, M, size, flags=cv2.INTER_NEAREST, borderValue=0)
            sources = [cv2.cvtColor(warped, cv2.COLOR_GRAY2BGR)]
            if args.interior:
                tid, bb = detector.addTemplate(sources, CLASS_ID, None)
            else:
                tid, bb = detector.addTemplate(sources, CLASS_ID, warped_mask)
            if tid < 0:
                skipped += 1
                continue
            assert tid == len(table)
            table.append((b, a, (c[0] - bb[0], c[1] - bb[1])))
    train_seconds = time.perf_counter() - started
    print(f"LINE-2D: {len(table)} templates ({skipped} without enough features) trained in "
          f"{train_seconds:.1f} s, cv2 {cv2.__version__}", file=sys.stderr)

    cam = index["camera"]  # of the (downscaled) images LINE-2D works on
    down = index["downscale"]
    center = np.array(index["model_center"])
    results = []
    for scene in args.scene:
        scene = Path(scene)
        gt = json.loads((scene / "gt.json").read_text())
        predictions = []
        for entry in gt[args.first:None if args.count is None else args.first + args.count]:
            image = cv2.imread(str(scene / entry["image"]), cv2.IMREAD_UNCHANGED)
            t0 = time.perf_counter()  # as for ours: from the decoded image to the pose
            if down > 1:
                image = cv2.resize(image, (cam["width"], cam["height"]), interpolation=cv2.INTER_AREA)
            bgr = cv2.cvtColor(image, cv2.COLOR_GRAY2BGR) if image.ndim == 2 else image
            matches, _ = detector.match([bgr], args.threshold)
            record = {"image": entry["image"], "R": None, "t": None, "score": 0.0, "error_ratio": None,
                      "matches": len(matches), "candidates": []}
            seen = set()
            for m in matches:  # best first; the first match of each of the top_k templates
                if m.template_id in seen:
                    continue
                seen.add(m.template_id)
                b, a, ref = table[m.template_id]
                base = index["bases"][b]
                R, t = template_pose(np.array(base["R_view"]).reshape(3, 3), angles[a], base["distance"],
                                     center, np.array([m.x + ref[0], m.y + ref[1]]),
                                     cam["fx"], cam["fy"], cam["cx"], cam["cy"])
                record["candidates"].append({
                    "R": R.ravel().tolist(), "t": t.tolist(), "score": float(m.similarity) / 100.0,
                    "template": int(m.template_id), "view": base["view"], "scale": base["scale"],
                    "inplane_deg": float(np.degrees(angles[a])), "x": int(m.x), "y": int(m.y)})
                if len(seen) == args.top_k:
                    break
            if record["candidates"]:
                best = record["candidates"][0]
                record.update(R=best["R"], t=best["t"], score=best["score"])
            record["seconds"] = time.perf_counter() - t0
            predictions.append(record)
        results.append({"scene": str(scene), "predictions": predictions})
        times = [p["seconds"] for p in predictions]
        print(f"LINE-2D: {scene.name}: {len(predictions)} images, median {np.median(times):.2f} s", file=sys.stderr)
    Path(args.output).write_text(json.dumps({
        "cv2_version": cv2.__version__, "templates": len(table), "skipped_templates": skipped,
        "train_seconds": train_seconds, "threshold": args.threshold, "interior": bool(args.interior),
        "results": results}, indent=1) + "\n")
    return 0


# ---------------------------------------------------------------------------------------
# Project role
# ---------------------------------------------------------------------------------------
def peer_python(venv: Path) -> Path:
    """The peer venv's python with a working cv2.linemod, created on first use."""
    python = venv / "bin" / "python"
    probe = [str(python), "-c", "import cv2; cv2.linemod.getDefaultLINE(); print(cv2.__version__)"]
    if python.exists() and subprocess.run(probe, env=CLEAN_ENV, capture_output=True).returncode == 0:
        return python
    print(f"creating the LINE-2D venv {venv} ({' '.join(PEER_PACKAGES)}) ...", flush=True)
    subprocess.run([sys.executable, "-m", "venv", str(venv)], env=CLEAN_ENV, check=True)
    subprocess.run([str(python), "-m", "pip", "install", "--quiet", *PEER_PACKAGES], env=CLEAN_ENV, check=True)
    check = subprocess.run(probe, env=CLEAN_ENV, capture_output=True, text=True)
    if check.returncode != 0:
        raise SystemExit(f"{venv}: cv2.linemod is not usable after installing {PEER_PACKAGES}:\n{check.stderr}")
    return python


def ensure_graph(step: Path, path: Path, step_deg: float, workers: int) -> tuple[object, float | None]:
    from brepose_ros.aspect_graph import AspectGraph, AspectGraphError
    from brepose_ros.offline.compiler import compile_aspect_graph

    try:
        graph = AspectGraph.load(path, step_path=step)
        if graph.params.get("step_deg") == step_deg:
            meta = path.with_suffix(".json")
            seconds = json.loads(meta.read_text())["seconds"] if meta.exists() else None
            return graph, seconds
    except (AspectGraphError, FileNotFoundError, OSError):
        pass
    started = time.perf_counter()
    compile_aspect_graph(step, step_deg=step_deg, workers=workers, progress=False).save(path)
    seconds = time.perf_counter() - started
    path.with_suffix(".json").write_text(json.dumps({"seconds": seconds}) + "\n")
    return AspectGraph.load(path, step_path=step), seconds


def ensure_scene(step: Path, folder: Path, n: int, seed: int, config) -> None:
    from brepose_ros.synthetic.scenes import generate_scene

    stamp = folder / "config.json"
    want = {"n": n, "seed": seed, "config": repr(config), "step_sha": _sha(step)}
    if stamp.exists() and json.loads(stamp.read_text()) == want:
        return
    if folder.exists():
        import shutil
        shutil.rmtree(folder)
    generate_scene(step, folder, n, seed=seed, config=config)
    stamp.write_text(json.dumps(want) + "\n")


def _sha(path: Path) -> str:
    from brepose_ros.aspect_graph import file_sha256
    return file_sha256(path)


def bench_main(args) -> int:
    """LINE-2D on bench/accuracy.py's scenes, its results in that script's layout."""
    sys.path.insert(0, str(ROOT))
    from bench import accuracy
    from brepose_ros.evaluation.metrics import pose_errors
    from brepose_ros.synthetic.scenes import SceneConfig

    python = peer_python(Path(args.peer_venv))
    cache = ROOT / "data" / "bench"
    distractors = accuracy.distractor_meshes(cache)
    images = range(args.start, args.start + args.n)
    rows = []
    for name, step in accuracy.bench_steps(args.bench_parts or list(accuracy.PARTS), cache).items():
        graph, model = accuracy.graph_and_model(step, cache)
        config = SceneConfig(span=accuracy.SPAN, look="varied")
        templates = Path(args.out) / "templates" / f"{name}-{args.peer_step:g}deg-{args.scales}scales-x{args.downscale}"
        render_templates(step, templates, args.peer_step, args.scales, config, args.downscale)
        scenes = {c: accuracy.scene(cache, name, step, c, images, distractors) for c in args.conditions}
        output = templates / f"matches-{args.start}-{args.n}.json"
        subprocess.run([str(python), str(Path(__file__).resolve()), "--role", "peer", "--templates", str(templates),
                        "--output", str(output), "--threshold", str(args.threshold),
                        "--inplane-step", str(args.inplane_step), "--top-k", "1", "--first", str(args.start),
                        "--count", str(args.n), "--scene", *(str(scenes[c].folder) for c in args.conditions)],
                       env=CLEAN_ENV, check=True)
        for condition, result in zip(args.conditions, json.loads(output.read_text())["results"]):
            truth = {e.image: e for e in scenes[condition].entries}
            records = []
            for p in result["predictions"]:
                record = {"image": p["image"], "found": p["R"] is not None, "score": p["score"],
                          "ms": 1000.0 * p["seconds"]}
                if p["R"] is not None:
                    e = truth[p["image"]]
                    record |= pose_errors(np.reshape(p["R"], (3, 3)), np.array(p["t"]), e.R, e.t, model, graph).to_dict()
                records.append(record)
            rows.append(accuracy.row_fields(name, condition) | {"images": records})
            hits = sum(r.get("success", False) for r in records)
            print(f"LINE-2D {name} {condition}: {hits} of {len(records)} right", flush=True)
    out = cache / "results" / f"accuracy_{args.label}.json"
    out.parent.mkdir(parents=True, exist_ok=True)
    out.write_text(json.dumps({"label": args.label, "look": "varied", "command": " ".join(sys.argv),
                               "method": "LINE-2D (cv2.linemod)", "rows": rows}, indent=1) + "\n")
    print(f"wrote {out}")
    return 0


def template_sizes(config, scales: int) -> np.ndarray:
    """Projected part diameters (pixels) of the template distances: log-even over the
    scene's range. The scene sets the largest side of the part's box to span x the smaller
    image side; the diameter is 1 to 1.4 times that side."""
    side = min(config.width, config.height)
    lo, hi = config.span[0] * side * 1.05, config.span[1] * side * 1.3
    if scales == 1:
        return np.array([np.sqrt(lo * hi)])
    ratio = (hi / lo) ** (1.0 / scales)
    return lo * ratio ** (np.arange(scales) + 0.5)


def working_camera(config, downscale: int):
    """Intrinsics of the scene images shrunk ``downscale`` times with cv2.INTER_AREA (a pixel
    j of the small image covers full-size pixels downscale*j ... downscale*j + downscale - 1)."""
    from brepose_ros.camera import Camera

    cam = config.camera()
    s = float(downscale)
    return Camera(cam.fx / s, cam.fy / s, (cam.cx - (s - 1) / 2) / s, (cam.cy - (s - 1) / 2) / s,
                  cam.width // downscale, cam.height // downscale)


def render_templates(step: Path, folder: Path, peer_step: float, scales: int, config, downscale: int) -> dict:
    """Base templates: one grey image + mask per (view, distance), part centred on the axis."""
    import cv2

    from brepose_ros.offline.cad import load_step, tessellate
    from brepose_ros.camera import Camera
    from brepose_ros.geometry import look_at_rotation
    from brepose_ros.synthetic.render import Placed, render
    from brepose_ros.viewsphere import fibonacci_directions, view_ups

    key = {"step_sha": _sha(step), "peer_step": peer_step, "scales": scales, "fx": config.fx,
           "span": list(config.span), "size": [config.width, config.height], "downscale": downscale,
           "version": 1}
    index_path = folder / "index.json"
    if index_path.exists():
        index = json.loads(index_path.read_text())
        if index.get("key") == key:
            return index
    started = time.perf_counter()
    folder.mkdir(parents=True, exist_ok=True)
    part = load_step(step)
    mesh = tessellate(part)
    center = np.asarray(part.center)
    scene_cam = working_camera(config, downscale)
    directions = fibonacci_directions(peer_step)
    ups = view_ups(directions)
    sizes = template_sizes(config, scales) / downscale
    rel = mesh.vertices - center
    bases = []
    for v, (direction, up) in enumerate(zip(directions, ups)):
        R = look_at_rotation(direction, up)
        for s, size in enumerate(sizes):
            p = rel @ R.T
            hull = cv2.convexHull(p[:, :2].astype(np.float32)).reshape(-1, 2)
            diameter = np.max(np.linalg.norm(hull[:, None] - hull[None], axis=2))
            distance = scene_cam.fx * diameter / size
            for _ in range(3):  # perspective: fixed-point on the projected diameter
                uv = (p[:, :2] / (p[:, 2:] + distance))
                hull = cv2.convexHull(uv.astype(np.float32)).reshape(-1, 2)
                projected = scene_cam.fx * np.max(np.linalg.norm(hull[:, None] - hull[None], axis=2))
                distance *= projected / size
            uv = scene_cam.fx * p[:, :2] / (p[:, 2:] + distance)
            radius = float(np.max(np.linalg.norm(uv, axis=1)))
            side = int(2 * np.ceil(radius + 12))
            c = (side - 1) / 2.0
            cam = Camera(scene_cam.fx, scene_cam.fy, c, c, side, side)
            t = np.array([0.0, 0.0, distance]) - R @ center
            rendering = render(cam, [Placed(mesh, R, t)], background=0.0)
            name = f"v{v:04d}_s{s}"
            cv2.imwrite(str(folder / f"{name}.png"), rendering.image)
            cv2.imwrite(str(folder / f"{name}_mask.png"), rendering.mask.astype(np.uint8) * 255)
            bases.append({"view": v, "scale": s, "image": f"{name}.png", "mask": f"{name}_mask.png",
                          "R_view": R.ravel().tolist(), "distance": float(distance), "center_px": [c, c],
                          "diameter_px": float(size)})
    index = {"key": key, "camera": scene_cam.to_dict(), "downscale": downscale, "model_center": center.tolist(),
             "views": len(directions), "sizes_px": sizes.tolist(), "bases": bases,
             "render_seconds": time.perf_counter() - started}
    index_path.write_text(json.dumps(index) + "\n")
    return index


def run_ours(graph, scene_folder: Path) -> list[dict]:
    import cv2

    from brepose_ros.online.estimator import Estimator
    from brepose_ros.evaluation.metrics import prediction_entry
    from brepose_ros.params import EstimatorParams
    from brepose_ros.scene_folder import load_scene

    scene = load_scene(scene_folder)
    estimator = Estimator(graph, EstimatorParams())
    predictions = []
    for entry in scene.entries:
        image = cv2.imread(str(entry.path), cv2.IMREAD_UNCHANGED)
        t0 = time.perf_counter()
        estimate = estimator.estimate(image, scene.camera)
        seconds = time.perf_counter() - t0
        predictions.append({**prediction_entry(entry.image, estimate), "seconds": seconds})
    estimator.close()
    return predictions


def score(scene_folder: Path, predictions: list[dict], model) -> dict:
    from brepose_ros.evaluation.metrics import pose_errors, summarise
    from brepose_ros.scene_folder import load_scene

    by_image = {p["image"]: p for p in predictions}
    errors = []
    for entry in load_scene(scene_folder).entries:
        p = by_image.get(entry.image)
        if p is None or p.get("R") is None:
            errors.append(None)
            continue
        errors.append(pose_errors(np.reshape(p["R"], (3, 3)), np.array(p["t"]), entry.R, entry.t, model))
    summary = summarise(errors)
    summary["median_seconds"] = float(np.median([p["seconds"] for p in predictions]))
    summary["errors"] = [e.to_dict() if e else None for e in errors]
    return summary


def best_candidates(scene_folder: Path, predictions: list[dict]) -> list[dict]:
    """Each image's LINE-2D candidate closest to the ground truth in rotation (oracle)."""
    from brepose_ros.geometry import rotation_angle_deg
    from brepose_ros.scene_folder import load_scene

    truth = {e.image: e for e in load_scene(scene_folder).entries}
    chosen = []
    for p in predictions:
        candidates = p.get("candidates") or []
        if not candidates:
            chosen.append(p)
            continue
        gt = truth[p["image"]]
        best = min(candidates, key=lambda c: rotation_angle_deg(np.reshape(c["R"], (3, 3)), gt.R))
        chosen.append({**p, "R": best["R"], "t": best["t"], "score": best["score"]})
    return chosen


def project_main(args) -> int:
    from brepose_ros.synthetic import shapes
    from brepose_ros.offline.cad import load_step, tessellate
    from brepose_ros.evaluation.metrics import ModelPoints, write_predictions
    from brepose_ros.synthetic.scenes import SceneConfig

    wall = time.perf_counter()
    out = Path(args.out)
    out.mkdir(parents=True, exist_ok=True)
    python = peer_python(Path(args.peer_venv))
    step = out / f"{args.part}.step"
    if not step.exists():
        shapes.export_step(args.part, step)
    configs = {"clean": SceneConfig()}
    if args.occluded:
        configs["occluded"] = SceneConfig(occlusion=0.3, clutter=3)
    scenes = {}
    for name, config in configs.items():
        folder = out / "scenes" / f"{args.part}-{name}-{args.images}-s{args.seed}"
        ensure_scene(step, folder, args.images, args.seed, config)
        scenes[name] = folder
    print(f"scenes: {', '.join(str(f) for f in scenes.values())}", flush=True)

    graph_path = out / f"{args.part}-{args.graph_step:g}deg.brepose.npz"
    graph, graph_seconds = ensure_graph(step, graph_path, args.graph_step, args.workers)
    print(f"aspect graph: {graph.n_views} views, {graph_seconds or float('nan'):.1f} s to compile", flush=True)
    templates = out / "templates" / f"{args.part}-{args.peer_step:g}deg-{args.scales}scales-x{args.downscale}"
    index = render_templates(step, templates, args.peer_step, args.scales, configs["clean"], args.downscale)
    print(f"templates: {len(index['bases'])} base renders ({index['views']} views x {args.scales} distances, "
          f"diameters {', '.join(f'{s:.0f}' for s in index['sizes_px'])} px) in {templates}, "
          f"{index['render_seconds']:.1f} s", flush=True)

    mesh = tessellate(load_step(step))
    model = ModelPoints.from_mesh(mesh.vertices, mesh.triangles)
    run_dir = out / "runs" / time.strftime("%Y%m%d-%H%M%S")
    run_dir.mkdir(parents=True, exist_ok=True)

    ours = {}
    for name, folder in scenes.items():
        predictions = run_ours(graph, folder)
        write_predictions(run_dir / f"ours-{name}.json", predictions)
        ours[name] = score(folder, predictions, model)
        print(f"ours: {name} done, median {ours[name]['median_seconds']:.2f} s/image", flush=True)

    peer_out = run_dir / "line2d.json"
    command = [str(python), str(Path(__file__).resolve()), "--role", "peer", "--templates", str(templates),
               "--output", str(peer_out), "--threshold", str(args.threshold),
               "--inplane-step", str(args.inplane_step), "--top-k", str(args.top_k), *(["--interior"] if args.interior else []),
               "--scene", *[str(f) for f in scenes.values()]]
    subprocess.run(command, env=CLEAN_ENV, check=True)
    peer = json.loads(peer_out.read_text())
    line2d, oracle = {}, {}
    for name, result in zip(scenes, peer["results"]):
        write_predictions(run_dir / f"line2d-{name}.json", result["predictions"])
        line2d[name] = score(scenes[name], result["predictions"], model)
        oracle[name] = score(scenes[name], best_candidates(scenes[name], result["predictions"]), model)

    rows = []
    for name in scenes:
        rows.append(("ours", name, ours[name], f"{graph.n_views} views", graph_seconds))
        label = "LINE-2D" + (" (interior)" if args.interior else "")
        rows.append((label, name, line2d[name], f"{peer['templates']} tpl", peer["train_seconds"]))
        rows.append((f"  top-{args.top_k} oracle", name, oracle[name], "", None))
    header = (f"{'method':<20} {'scene':<9} {'success':>7} {'er<0.01':>7} {'found':>5} {'med rot':>8} "
              f"{'med trans':>9} {'s/image':>7} {'views/templates':>16} {'train s':>7}")
    lines = [f"{args.part}, {args.images} images per scene, seed {args.seed}; ours: aspect graph "
             f"{args.graph_step:g} deg; LINE-2D: {args.peer_step:g} deg views x {len(np.arange(0, 360, args.inplane_step))} "
             f"in-plane x {args.scales} distances, images /{args.downscale}, threshold {args.threshold:g}, cv2 {peer['cv2_version']}",
             "success = rotation < 5 deg and translation < 5 % of the diameter "
             f"({model.diameter * 50:.1f} mm); rates over all images; medians over found ones",
             f"top-{args.top_k} oracle: of LINE-2D's {args.top_k} best-scoring templates, the one nearest the "
             "truth in rotation (needs the ground truth: an upper bound for a verification step, not a method)",
             f"ours: train s = aspect graph compile ({args.workers} processes); LINE-2D: train s = "
             f"addTemplate incl. in-plane warps (1 process), base renders {index['render_seconds']:.0f} s more",
             header,
             "-" * len(header)]
    for method, name, s, size, train in rows:
        lines.append(f"{method:<20} {name:<9} {s['success']:>7.0%} {s['er_below_0.01']:>7.0%} {s['found']:>5.0%} "
                     f"{s['median_rotation_deg']:>7.1f}° {s['median_translation_mm']:>7.1f}mm "
                     f"{s['median_seconds']:>7.2f} {size:>16} {'' if train is None else f'{train:.1f}':>7}")
    table = "\n".join(lines)
    (run_dir / "summary.json").write_text(json.dumps({
        "part": args.part, "args": vars(args), "graph_views": graph.n_views, "graph_seconds": graph_seconds,
        "line2d_templates": peer["templates"], "line2d_train_seconds": peer["train_seconds"],
        "template_render_seconds": index["render_seconds"], "cv2_contrib_version": peer["cv2_version"],
        "ours": ours, "line2d": line2d, "line2d_top_k_oracle": oracle, "table": table}, indent=1) + "\n")
    print("\n" + table)
    print(f"\nwall time {time.perf_counter() - wall:.0f} s; predictions and summary.json in {run_dir}")
    return 0


def main(argv=None) -> int:
    p = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    p.add_argument("--role", choices=("project", "peer"), default="project", help=argparse.SUPPRESS)
    p.add_argument("--part", default="sharp_bracket", help="built-in part (brepose_ros.synthetic.shapes)")
    p.add_argument("--images", type=int, default=12, help="images per scene")
    p.add_argument("--seed", type=int, default=1)
    p.add_argument("--occluded", action="store_true", help="also a scene with 30 %% occlusion and 3 clutter shapes")
    p.add_argument("--graph-step", type=float, default=5.0, help="our aspect graph's view spacing, degrees")
    p.add_argument("--peer-step", type=float, default=10.0, help="LINE-2D view spacing, degrees")
    p.add_argument("--inplane-step", type=float, default=15.0, help="LINE-2D in-plane rotation step, degrees")
    p.add_argument("--scales", type=int, default=4, help="LINE-2D template distances per view")
    p.add_argument("--downscale", type=int, default=2,
                   help="LINE-2D works on images (and templates) shrunk this many times")
    p.add_argument("--threshold", type=float, default=75.0, help="LINE-2D similarity threshold, percent")
    p.add_argument("--interior", action="store_true",
                   help="LINE-2D templates without mask: features on inner edges too, not only the silhouette")
    p.add_argument("--workers", type=int, default=2, help="processes compiling the aspect graph")
    p.add_argument("--out", default=str(ROOT / "data" / "peer"))
    p.add_argument("--peer-venv", default=str(ROOT / "data" / "peer-venv"))
    # peer role
    p.add_argument("--templates", help=argparse.SUPPRESS)
    p.add_argument("--scene", nargs="*", help=argparse.SUPPRESS)
    p.add_argument("--output", help=argparse.SUPPRESS)
    p.add_argument("--first", type=int, default=0, help=argparse.SUPPRESS)
    p.add_argument("--count", type=int, help=argparse.SUPPRESS)
    p.add_argument("--top-k", type=int, default=10, help="LINE-2D candidates kept per image (for the oracle row)")
    bench = p.add_argument_group("--bench: LINE-2D alone on bench/accuracy.py's scenes")
    bench.add_argument("--bench", action="store_true")
    bench.add_argument("--bench-parts", nargs="*", help="bench parts (default: all of bench/accuracy.py's)")
    bench.add_argument("--conditions", nargs="*", default=["clean", "clutter", "occl10+clutter", "occl20+clutter",
                                                            "occl30+clutter", "occl40+clutter", "occl50+clutter"])
    bench.add_argument("--n", type=int, default=16, help="images per part and condition")
    bench.add_argument("--start", type=int, default=64, help="first image index (64: the fresh images)")
    bench.add_argument("--label", default="line2d", help="names data/bench/results/accuracy_LABEL.json")
    args = p.parse_args(argv)
    if args.role == "peer":
        return peer_main(args)
    return bench_main(args) if args.bench else project_main(args)


if __name__ == "__main__":
    sys.exit(main())
