"""Real photographs: every BOP19 target in the 25 LM-O frames of ../shared/data/real/lmo_test_000002.

    python bench/real_lmo.py [--step-deg 5] [--objects 1 5 ...] [--params FILE.yaml] [--crop] [--overlays 4]
    python bench/real_lmo.py --report data/bench/real_lmo/results_LABEL.json [--appearance]  # a saved run's tables

Each of the 8 objects' scanned PLY meshes (mm) is compiled into an aspect graph (cached under
data/bench/real_lmo/graphs/, git-ignored), then every target of test_targets_bop19.json whose
frame is among the 25 is estimated in the 640 x 480 colour image as the node gets it (BGR).
As in the BOP protocol a target is known to be in the image, so the best pose is kept
whatever its score and confidence (``pose.min_score`` and ``pose.min_confidence`` 0); the
score is reported beside it. Only a pose outside a known working range (``--known-range``)
is not found, and counts as wrong.

A pose is correct when ADD(-S) < 0.1 of the object's diameter (models_info.json; ADD-S for
the objects with symmetries there: eggbox and glue). Recall is reported per object and
overall, split at a visible fraction of 0.8 (scene_gt_info.json), with the time per
estimate and per image (all its targets, one after the other), and the median seconds
of the estimator's stages (``Estimate.timings``: edges, search, refinement ...). Beside it the recall of
the 2D projection error below 5 px (``PROJECTION_PX``; the mean image distance of the
model's points under the two poses, to the nearest for eggbox and glue): on parts of
75-170 px, ADD < 0.1 d asks for the depth within about 1 %, a pixel of scale, which edges
rarely pin; the 2D figure tells a pose in the right place from one that is not.

Diagnostics of what real light does to the method, per target:

* ``truth``: the estimator's score (``scoring.pose_scores``: ``EdgeEvidence.shares`` on the
  Canny edge pixels, the F-measure of the share of the model confirmed beyond chance and
  the share of the seen image edges explained, times its significance) of the ground-truth
  pose, on the edges the estimator saw (``Estimator.part_frame``: within the part's colour
  regions, ``edges.colour_regions``, of the scanned meshes' vertex colours). When a wrong
  estimate scores higher, the score is fooled; when the truth scores higher, the search
  missed it. On the photos the ground truth lies 1-3 px off the image's
  edges (the truth's support at 2 px 0.43, at 4 px 0.68), so the truth scores far below the
  pose the refinement makes of it: ``near score`` is the score of the near-truth start after
  the polish (below), and ``near wins`` counts the wrong estimates it outscores (there the
  search missed a better pose; elsewhere the score prefers the wrong one).
* ``support grey / colour``: the share of the projected model edges at the true pose that
  the grey image's Canny edges confirm, and that the colour edges (``edges.colour``: the
  luminance's or an opponent-colour plane's gradient, ``image_edges.colour_gradients``) do.
* ``size``: the diagonal of the projected part's bounding box, pixels.
* ``from near truth``: recall (ADD(-S) / 2D projection) when the estimator's refinement
  (hypothesis rounds as ``PoseRefiner.verify`` runs them, view climb, polish) starts from
  the truth turned by ``NEAR_DEG`` about a random axis through the part's centre and
  shifted by ``NEAR_SHIFT`` of its diameter: what a search that landed on the right view
  and place would give, on the same image and score.

``--light`` adds what the photos themselves show, from the true poses of all 8 objects
rendered into a label image (``synthetic.render.rasterize``): per object the share of
saturated pixels (a highlight: a channel at 250 or more) inside its visible silhouette,
and the contrast across that silhouette (mean inside minus mean outside, in a 3 px band)
in grey and in the colour channel where it is largest; per image the Canny high threshold
the edge stage chose from the image's own gradient statistics.

``--render`` replaces every photo by a rendering of the 8 objects at their true poses
(``synthetic.render``: grey metal, two lights, a flat dark background): the same poses,
sizes and mutual occlusions without real light, clutter or sensor, as the control.

``--crop`` hands the estimator the ground-truth region instead (the visible bounding box
grown to twice its size, at least 160 px): an oracle for detection, measuring matching
and pose alone. ``--min-margin-px`` sets ``pose.min_margin_pixels`` for the run: the floor
of the margin around a pose inside which the score counts unexplained edge pixels.
``--known-range RATIO`` gives the estimator a known working distance
(``pose.min_distance`` / ``max_distance``): the median distance of the frame's objects'
model origins (BOP models are centred) divided and multiplied by RATIO, as a camera that knows
its distance to the table within -20 / +25 % for 1.25 (a robot's camera pose, a fixed cell);
the same range for every object of the frame, not any target's own depth. Targets whose own
distance lies outside it are counted (``targets outside it``): the estimator cannot find them.
``--overlays N`` writes N successes and N failures per object as PNGs to
data/bench/real_lmo/overlays/ (estimate green or red, truth blue); every target's figures
go to data/bench/real_lmo/results*.json.
"""
from __future__ import annotations

import argparse
import dataclasses
import json
import sys
import time
from dataclasses import dataclass
from pathlib import Path

import cv2
import numpy as np
from scipy.spatial import cKDTree

REPO = Path(__file__).resolve().parents[1]
sys.path.insert(0, str(REPO))

from brepose_ros.aspect_graph import FORMAT_VERSION, SUFFIX, AspectGraph  # noqa: E402
from brepose_ros.camera import Camera  # noqa: E402
from brepose_ros.evaluation.metrics import ModelPoints  # noqa: E402
from brepose_ros.geometry import normalize  # noqa: E402
from brepose_ros.evaluation.overlay import draw_overlay, draw_segments  # noqa: E402
from brepose_ros.offline.cad import Mesh  # noqa: E402
from brepose_ros.offline.compiler import compile_aspect_graph, surface_mesh, with_surface  # noqa: E402
from brepose_ros.offline.mesh import load_mesh  # noqa: E402
from brepose_ros.online.estimator import Estimator  # noqa: E402
from brepose_ros.online.frame import Frame  # noqa: E402
from brepose_ros.online.image_edges import canny_thresholds, detect_edges, to_gray  # noqa: E402
from brepose_ros.online.refinement import Candidate, PoseRefiner, hypothesis_rounds  # noqa: E402
from brepose_ros.online.scoring import EdgeEvidence, pose_scores  # noqa: E402
from brepose_ros.online.workers import SERIAL  # noqa: E402
from brepose_ros.params import EstimatorParams  # noqa: E402
from brepose_ros.synthetic.render import Placed, rasterize, render  # noqa: E402

LMO = REPO.parent / "shared" / "data" / "real" / "lmo_test_000002"
OUT = REPO / "data" / "bench" / "real_lmo"
NAMES = {1: "ape", 5: "can", 6: "cat", 8: "driller", 9: "duck", 10: "eggbox", 11: "glue", 12: "holepuncher"}
#: targets at least this visible count as well visible (the issue's split)
WELL_VISIBLE = 0.8
#: BOP's correctness threshold, a fraction of the diameter
ADD_THRESHOLD = 0.1
#: the 2D projection threshold of the LINEMOD papers, pixels
PROJECTION_PX = 5.0
#: the oracle crop: the visible box grown by this factor about its centre, at least this wide
CROP_GROWTH, CROP_MIN_PX = 2.0, 160
#: the refinement oracle's start: the truth turned by this many degrees and moved by this
#: share of the diameter, about where a hypothesis from the right view of a 5-degree graph lands
NEAR_DEG, NEAR_SHIFT = 5.0, 0.02
#: the refinement's stages in the near-truth probe: the hypothesis rounds, the view climb, the polish
NEAR_STAGES = ("rounds", "climb", "polish")
#: the bands inside and outside the silhouette compared by ``--appearance``, pixels
APPEARANCE_BAND_PX = 4.0
#: the floors of pose.min_shading_fit ``--appearance`` counts the estimates at
SHADING_FLOORS = (0.5, 0.6, 0.7, 0.8)
#: confidence levels whose estimates ``print_confidence`` counts: the default rule's floor, the
#: trusted rule's, and between
CONFIDENCE_LEVELS = (0.09, 0.3, 0.55)
#: grey level behind the rendered objects (``--render``)
RENDER_BACKGROUND = 40.0
#: overlay colours (BGR): the true pose's edges, the estimate's when correct and when not
TRUTH_COLOUR, CORRECT_COLOUR, WRONG_COLOUR = (255, 128, 0), (0, 220, 0), (0, 0, 255)
#: published RGB-only results on the whole LM-O test set (the issue's comparison)
PUBLISHED = [("PVNet (trained on LM), ADD(-S) recall", "40.8 %"),
             ("DPOD (trained on LM), ADD(-S) recall", "47.3 %"),
             ("FoundPose coarse stage (unseen objects), BOP AR", "34.0")]


@dataclass
class Target:
    frame: int
    obj: int
    R: np.ndarray
    t: np.ndarray  # metres
    visible: float
    box: tuple[int, int, int, int]  # visible bounding box x, y, w, h


def load_targets(folder: Path) -> list[Target]:
    """The BOP19 targets whose frame is among the images in rgb/ (LM-O has one instance each)."""
    ground_truth = json.loads((folder / "scene_gt.json").read_text())
    info = json.loads((folder / "scene_gt_info.json").read_text())
    out = []
    for target in json.loads((folder / "test_targets_bop19.json").read_text()):
        frame = str(target["im_id"])
        if not (folder / "rgb" / f"{int(frame):06d}.png").exists():
            continue
        k = next(i for i, g in enumerate(ground_truth[frame]) if g["obj_id"] == target["obj_id"])
        g = ground_truth[frame][k]
        out.append(Target(int(frame), target["obj_id"], np.array(g["cam_R_m2c"], float).reshape(3, 3),
                          np.array(g["cam_t_m2c"], float) / 1000.0, float(info[frame][k]["visib_fract"]),
                          tuple(info[frame][k]["bbox_visib"])))
    return out


def graph_of(obj: int, step_deg: float) -> AspectGraph:
    path = OUT / "graphs" / f"obj_{obj:06d}_{step_deg:g}deg_v{FORMAT_VERSION}{SUFFIX}"
    mesh = LMO / "models" / f"obj_{obj:06d}.ply"
    if not path.exists():
        path.parent.mkdir(parents=True, exist_ok=True)
        compile_aspect_graph(mesh, step_deg=step_deg, units="mm", workers=2).save(path)
    graph = AspectGraph.load(path, step_path=mesh)
    if graph.colour_histogram is None:  # cached before graphs kept a mesh's colour: the mesh has it
        graph = dataclasses.replace(graph, colour_histogram=load_mesh(mesh, "mm").colour_histogram)
    if graph.surface is None:  # cached before graphs held the part's surface
        graph = with_surface(graph, surface_mesh(load_mesh(mesh, "mm")))
        graph.save(path)
    return graph


def crop(image: np.ndarray, camera: Camera, box) -> tuple[np.ndarray, Camera]:
    """The image inside the grown box and the camera that sees just that."""
    x, y, w, h = box
    center, half = np.array([x + w / 2, y + h / 2]), max(CROP_GROWTH * max(w, h), CROP_MIN_PX) / 2
    x0, y0 = np.clip(np.floor(center - half).astype(int), 0, [camera.width - 1, camera.height - 1])
    x1, y1 = np.clip(np.ceil(center + half).astype(int), [x0 + 1, y0 + 1], [camera.width, camera.height])
    inner = Camera(camera.fx, camera.fy, camera.cx - x0, camera.cy - y0, int(x1 - x0), int(y1 - y0),
                   camera.distortion)
    return np.ascontiguousarray(image[y0:y1, x0:x1]), inner


def edge_evidence(image: np.ndarray, params, colour: bool) -> EdgeEvidence:
    """The score's evidence of an image with grey or colour edges (``edges.colour``)."""
    edges = detect_edges(image, dataclasses.replace(params, colour=colour))
    return EdgeEvidence(edges.edge_map, edges.gradient_x, edges.gradient_y)


def refined_from_near_truth(refiner: PoseRefiner, target: Target, frame: Frame, params: EstimatorParams,
                            rng: np.random.Generator) -> list[tuple[np.ndarray, np.ndarray]]:
    """The estimator's refinement of one start near the truth (``from near truth``): the
    pose after each of ``NEAR_STAGES`` (``PoseRefiner.best`` of one candidate, step by step)."""
    graph = refiner.graph
    turn = cv2.Rodrigues(np.deg2rad(NEAR_DEG) * normalize(rng.normal(size=3)))[0]
    center = target.R @ graph.model_center + target.t + NEAR_SHIFT * graph.model_diameter * normalize(
        rng.normal(size=3))
    R = turn @ target.R
    R, t, scores = refiner.refined_scores(R[None], (center - R @ graph.model_center)[None], frame, params.pose,
                                          hypothesis_rounds(params.pose.refine_iterations), SERIAL, align=True)
    climbed = refiner.climb(Candidate(float(scores[0]), R[0], t[0], None), frame, params.pose)
    polished = refiner.polish(climbed, frame, params.pose)
    return [(R[0], t[0]), (climbed.R, climbed.t), (polished.R, polished.t)]


def known_range(targets: list[Target], frame: int, ratio: float | None) -> tuple[float, float]:
    """The working range (``pose.min_distance``, ``max_distance``) of ``--known-range`` in
    one frame, metres: the median distance of its objects divided and multiplied by ``ratio``
    (0, 0: unknown, without the option)."""
    if ratio is None:
        return 0.0, 0.0
    median = float(np.median([np.linalg.norm(t.t) for t in targets if t.frame == frame]))
    return median / ratio, median * ratio


def projection_px(model: ModelPoints, camera: Camera, R, t, target: Target, symmetric: bool) -> float:
    """Mean image distance of the model's points under (R, t) and the true pose, pixels (to
    the nearest true one for a symmetric object, as ADD-S)."""
    estimated = camera.project_model(model.points, R, t)
    true = camera.project_model(model.points, target.R, target.t)
    if symmetric:
        return float(np.mean(cKDTree(true).query(estimated)[0]))
    return float(np.mean(np.linalg.norm(estimated - true, axis=1)))


def support(evidence: EdgeEvidence, model_px: np.ndarray, tolerance: float) -> float:
    """Share of one pose's projected model edges (K, 2, 2) that edge pixels confirm."""
    return float(evidence.supports(model_px, np.array([0, len(model_px)]), tolerance)[0])


def main(argv=None) -> int:
    parser = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    parser.add_argument("--step-deg", type=float, default=5.0, help="aspect graph view spacing")
    parser.add_argument("--objects", type=int, nargs="*", default=list(NAMES), choices=list(NAMES))
    parser.add_argument("--params", type=Path, help="estimator parameter YAML (config/estimator.yaml layout)")
    parser.add_argument("--crop", action="store_true", help="oracle: estimate in the ground-truth region only")
    parser.add_argument("--overlays", type=int, default=3, help="successes and failures saved per object")
    parser.add_argument("--frames", type=int, help="only the first N frames (quick runs)")
    parser.add_argument("--label", help="appended to the results file's name, so that runs of other code with the "
                                        "same options keep their own file")
    parser.add_argument("--min-margin-px", type=float, help="the score's margin floor (default: the estimator's)")
    parser.add_argument("--light", action="store_true", help="also highlights, contrast and Canny thresholds")
    parser.add_argument("--render", action="store_true", help="renderings of the true poses instead of the photos")
    parser.add_argument("--known-range", type=float, metavar="RATIO",
                        help="known working distance: the frame's median object distance / and x RATIO (> 1)")
    parser.add_argument("--report", type=Path, metavar="RESULTS",
                        help="print the tables of a saved results file (data/bench/real_lmo/results*.json) "
                             "instead of running")
    parser.add_argument("--appearance", action="store_true",
                        help="with --report: also the look at the truth against the wrong estimates "
                             "(bench/silhouette_contrast.py's cues on the photos)")
    args = parser.parse_args(argv)
    if args.report:
        rows = json.loads(args.report.read_text())
        args.objects = [obj for obj in NAMES if any(r["obj"] == obj for r in rows)]
        report(rows, args, EstimatorParams.load(args.params) if args.params else EstimatorParams())
        if args.appearance:
            appearance_report(rows, args.objects)
        return 0
    if args.known_range is not None and args.known_range <= 1:
        parser.error("--known-range must be above 1")
    if not LMO.is_dir():
        print(f"error: {LMO} is not there (../shared beside the clone)", file=sys.stderr)
        return 2
    params = EstimatorParams.load(args.params) if args.params else EstimatorParams()
    params = params.with_flat({"pose.min_score": 0.0, "pose.min_confidence": 0.0} | (
        {"pose.min_margin_pixels": args.min_margin_px} if args.min_margin_px is not None else {}))
    camera = Camera.load(LMO / "camera.json")
    info = json.loads((LMO / "models" / "models_info.json").read_text())
    targets = load_targets(LMO)
    frames = sorted({t.frame for t in targets})[: args.frames]
    images = {f: cv2.imread(str(LMO / "rgb" / f"{f:06d}.png"), cv2.IMREAD_COLOR) for f in frames}
    meshes = scene_meshes()
    if args.render:
        images = {f: render(camera, [Placed(meshes[t.obj], t.R, t.t) for t in targets if t.frame == f],
                            background=RENDER_BACKGROUND, color=True).image for f in frames}
    working_range = {f: known_range(targets, f, args.known_range) for f in frames}
    tolerance = params.pose.inlier_pixels
    overlays = OUT / ("overlays" + ("_render" if args.render else "") + ("_crop" if args.crop else ""))
    overlays.mkdir(parents=True, exist_ok=True)
    rows = []
    for obj in args.objects:
        graph = graph_of(obj, args.step_deg)
        mesh = load_mesh(LMO / "models" / f"obj_{obj:06d}.ply", "mm")
        model = ModelPoints.from_mesh(mesh.vertices, mesh.triangles)
        diameter = info[str(obj)]["diameter"] / 1000.0
        symmetric = "symmetries_discrete" in info[str(obj)] or "symmetries_continuous" in info[str(obj)]
        estimator, refiner, rng = Estimator(graph, params), PoseRefiner(graph), np.random.default_rng(obj)
        saved = {True: 0, False: 0}
        for target in (t for t in targets if t.obj == obj and t.frame in images):
            image, cam = images[target.frame], camera
            if args.crop:
                image, cam = crop(image, camera, target.box)
            near_end, far_end = working_range[target.frame]
            if args.known_range:
                estimator.params = params.with_flat({"pose.min_distance": near_end, "pose.max_distance": far_end})
            started = time.perf_counter()
            estimate = estimator.estimate(image, cam)
            seconds = time.perf_counter() - started
            found = estimate.R is not None  # not found only outside a known working range
            distance = (model.add_s if symmetric else model.add)(estimate.R, estimate.t, target.R, target.t) \
                if found else np.inf
            error = distance * model.diameter / diameter
            # the truth scored on what the estimator saw: the whole image or the crop, within
            # the part's colour regions where they apply
            seen = estimator.part_frame(image, cam)
            truth_px = cam.project_model(graph.seg_3d[graph.visible_segments(target.R, target.t)], target.R, target.t)
            truth = float(pose_scores(graph, target.R[None], target.t[None], seen, params.pose)[0])
            size = float(np.hypot(*np.ptp(truth_px.reshape(-1, 2), axis=0)))
            stages = refined_from_near_truth(refiner, target, seen, params, rng)
            near_add = [(model.add_s if symmetric else model.add)(R, t, target.R, target.t) * model.diameter / diameter
                        for R, t in stages]
            near_px = [projection_px(model, cam, R, t, target, symmetric) for R, t in stages]
            near_score = float(pose_scores(graph, stages[-1][0][None], stages[-1][1][None], seen, params.pose)[0])
            near, near_projected = near_add[-1], near_px[-1]
            projected = projection_px(model, cam, estimate.R, estimate.t, target, symmetric) if found else np.inf
            rows.append(dict(obj=obj, frame=target.frame, visible=target.visible, error=error,
                             R=estimate.R.ravel().tolist() if found else None, t=estimate.t.tolist() if found else None,
                             correct=error < ADD_THRESHOLD, score=estimate.score, truth=truth,
                             projected=projected, projected_correct=projected < PROJECTION_PX,
                             near_correct=near < ADD_THRESHOLD, near_projected_correct=near_projected < PROJECTION_PX,
                             near_add=near_add, near_px=near_px, near_score=near_score, timings=estimate.timings,
                             support=support(edge_evidence(image, params.edges, False), truth_px, tolerance),
                             explained=seen.evidence.shares(truth_px, tolerance, params.pose.min_margin_pixels,
                                                            seen_tolerance_px=params.pose.seen_pixels).explained,
                             size=size, seconds=seconds, confidence=float(estimate.confidence),
                             shading_fit=estimate.shading_fit, in_range=bool(
                                 near_end <= np.linalg.norm(target.t) <= far_end or far_end == 0),
                             colour_support=support(edge_evidence(image, params.edges, True), truth_px, tolerance)))
            correct = rows[-1]["correct"]
            if saved[correct] < args.overlays:
                saved[correct] += 1
                picture = draw_overlay(image, estimate, f"{NAMES[obj]} {target.frame}")
                draw_segments(picture, truth_px, TRUTH_COLOUR, 1)
                if found:
                    estimated_px = cam.project_model(graph.seg_3d[graph.visible_segments(estimate.R, estimate.t)],
                                                     estimate.R, estimate.t)
                    draw_segments(picture, estimated_px, CORRECT_COLOUR if correct else WRONG_COLOUR, 1)
                name = f"{NAMES[obj]}_{target.frame:06d}_{'ok' if correct else 'fail'}.png"
                cv2.imwrite(str(overlays / name), picture)
            print(f"{NAMES[obj]:12s} {target.frame:5d} vis {target.visible:.2f} size {size:4.0f} px  "
                  f"ADD(-S) {error:6.2f} d {projected:6.1f} px  score {estimate.score:.2f} truth {truth:.2f} "
                  f"near {near_score:.2f}  "
                  f"from near truth {near:5.2f} d {near_projected:6.1f} px  "
                  f"{seconds:.2f} s",
                  file=sys.stderr, flush=True)
        estimator.close()
    report(rows, args, params)
    if args.light:
        light_report(targets, images, meshes, camera, params, args.objects)
    run = "".join([f"_{args.params.stem}" if args.params else "", "_crop" if args.crop else "",
                   "_render" if args.render else "",
                   f"_range{args.known_range:g}" if args.known_range else "",
                   f"_margin{args.min_margin_px:g}" if args.min_margin_px is not None else "",
                   f"_{args.label}" if args.label else ""])
    (OUT / f"results{run}.json").write_text(json.dumps(rows, indent=1))
    return 0


def report(rows: list[dict], args, params: EstimatorParams) -> None:
    def recall(selected, key="correct"):
        return f"{100 * np.mean([r[key] for r in selected]):.1f} % ({len(selected)})" if selected else "-"

    def median(selected, key, scale=1.0, digits=2):
        return f"{scale * np.median([r[key] for r in selected]):.{digits}f}" if selected else "-"

    mode = ("renderings" if args.render else "photos") + (", oracle crop" if args.crop else ", whole image")
    mode += f", params {args.params}" if args.params else ""
    if args.known_range:
        mode += (f", known range x/{args.known_range:g} about the frame's median distance "
                 f"({sum(not r['in_range'] for r in rows)} targets outside it, "
                 f"{sum(r['R'] is None for r in rows)} not found: no pose in it)")
    mode += f", margin floor {params.pose.min_margin_pixels:g} px, {'colour' if params.edges.colour else 'grey'} edges"
    print(f"\nLM-O test scene 2, {len(rows)} BOP19 targets in {len({r['frame'] for r in rows})} frames, "
          f"{mode}, {args.step_deg:g} deg views")
    print("| object | ADD(-S) recall | visible >= 0.8 | visible < 0.8 | 2D proj < 5 px | median size px "
          "| median score | median truth score | median near score | truth support grey / colour | truth explained "
          "| score fooled | near wins | from near truth ADD(-S) / 2D | median s |")
    print("|---|---|---|---|---|---|---|---|---|---|---|---|---|---|---|")
    for obj in [*args.objects, None]:
        mine = [r for r in rows if obj is None or r["obj"] == obj]
        well = [r for r in mine if r["visible"] >= WELL_VISIBLE]
        poor = [r for r in mine if r["visible"] < WELL_VISIBLE]
        wrong = [r for r in mine if not r["correct"]]
        fooled = sum(r["score"] >= r["truth"] for r in wrong)
        near_wins = sum(r["near_score"] > r["score"] for r in wrong)
        print(f"| {NAMES[obj] if obj else '**all**'} | {recall(mine)} | {recall(well)} | {recall(poor)} | "
              f"{recall(mine, 'projected_correct')} | {median(mine, 'size', digits=0)} | {median(mine, 'score')} | "
              f"{median(mine, 'truth')} | {median(mine, 'near_score')} | {median(mine, 'support')} / "
              f"{median(mine, 'colour_support')} | {median(mine, 'explained')} | {fooled} of {len(wrong)} | "
              f"{near_wins} of {len(wrong)} | "
              f"{recall(mine, 'near_correct')} / {recall(mine, 'near_projected_correct')} | "
              f"{median(mine, 'seconds')} |")
    print(f"\nFrom near truth, stage by stage: ADD(-S) < {ADD_THRESHOLD:g} d / 2D projection < {PROJECTION_PX:g} px "
          "after each stage")
    print("| object | " + " | ".join(NEAR_STAGES) + " |")
    print("|---|" + "---|" * len(NEAR_STAGES))
    for obj in [*args.objects, None]:
        mine = [r for r in rows if obj is None or r["obj"] == obj]
        cells = [f"{100 * np.mean([r['near_add'][k] < ADD_THRESHOLD for r in mine]):.1f} / "
                 f"{100 * np.mean([r['near_px'][k] < PROJECTION_PX for r in mine]):.1f} %"
                 for k in range(len(NEAR_STAGES))]
        print(f"| {NAMES[obj] if obj else '**all**'} | " + " | ".join(cells) + " |")
    print_ceilings(rows, args.objects)
    print_confidence(rows)
    per_image = [sum(r["seconds"] for r in rows if r["frame"] == f) for f in sorted({r["frame"] for r in rows})]
    print(f"\ntime per image (all its targets): median {np.median(per_image):.1f} s; "
          f"per estimate: median {np.median([r['seconds'] for r in rows]):.2f} s")
    stages = sorted({name for r in rows for name in r["timings"]} - {"total"})
    print("per estimate, median s by stage: " + ", ".join(
        f"{name} {np.median([r['timings'].get(name, 0.0) for r in rows]):.2f}" for name in stages))
    print("published RGB-only figures on the whole LM-O test set: " +
          "; ".join(f"{name} {value}" for name, value in PUBLISHED))


def print_confidence(rows: list[dict]) -> None:
    """Does the confidence tell the right estimates from the wrong ones on the photos? The AUC
    of right against wrong estimates by the confidence and by the score, and how many
    estimates at a few confidence levels are right (runs recorded since session 28)."""
    from bench.silhouette_contrast import auc

    rows = [r for r in rows if "confidence" in r and r["R"] is not None]
    right = np.array([r["correct"] for r in rows], bool)
    if not right.any() or right.all():
        return
    print(f"\nThe confidence on the photos ({len(rows)} estimates, {right.sum()} right; pose.prior as run)")
    for name in ("confidence", "score"):
        print(f"- AUC right vs wrong by the {name}: {auc(np.array([r[name] for r in rows]), right):.2f}")
    for level in CONFIDENCE_LEVELS:
        kept = np.array([r["confidence"] >= level for r in rows])
        print(f"- confidence >= {level:g}: {int((kept & right).sum())} right of {int(kept.sum())}")


def print_ceilings(rows: list[dict], objects) -> None:
    """What a perfect search, and a perfect search and choice, would give on these edges.

    A perfect search puts the near-truth start, refined and polished (``near``), among the
    candidates: the score then keeps it where it outscores the estimate. A perfect choice
    keeps it wherever it is right as well. Neither can exceed what the refinement makes of a
    start beside the truth, so the second is the ceiling of the edge score's evidence.
    """
    def searched(r):
        return r["correct"] or (r["near_correct"] and r["near_score"] > r["score"])

    def chosen(r):
        return r["correct"] or r["near_correct"]

    def share(selected, rule):
        return f"{100 * np.mean([rule(r) for r in selected]):.1f}" if selected else "-"

    print("\nCeilings, ADD(-S) recall % (all / visible >= 0.8 / < 0.8): today | a perfect search (the near-truth "
          "start among the candidates, the score choosing) | a perfect search and choice")
    print("| object | today | perfect search | perfect search and choice |")
    print("|---|---|---|---|")
    for obj in [*objects, None]:
        mine = [r for r in rows if obj is None or r["obj"] == obj]
        well = [r for r in mine if r["visible"] >= WELL_VISIBLE]
        splits = (mine, well, [r for r in mine if r["visible"] < WELL_VISIBLE])
        cells = [" / ".join(share(s, rule) for s in splits) for rule in (lambda r: r["correct"], searched, chosen)]
        print(f"| {NAMES[obj] if obj else '**all**'} | " + " | ".join(cells) + " |")


def scene_meshes() -> dict[int, Mesh]:
    """The 8 objects' meshes in metres with smooth vertex normals, for rendering."""
    meshes = {}
    for obj in NAMES:
        meshes[obj] = surface_mesh(load_mesh(LMO / "models" / f"obj_{obj:06d}.ply", "mm"))
    return meshes


def appearance_report(rows: list[dict], objects) -> None:
    """Where the estimate is wrong, does the look of the image over the part's silhouette prefer
    the true pose, where the edge score does not? Per object: the wrong estimates, and how many
    of them the truth beats by the shading fit (how much of the grey level over the silhouette
    the mesh's normals explain under some light), by the contrast across the silhouette, and by
    the edge score of the truth refined from beside it (``near score``). Then how many right and
    wrong estimates ``pose.min_shading_fit`` would keep at a few floors."""
    from bench.silhouette_contrast import band_contrast, mesh_silhouette, quantised
    from brepose_ros.online.appearance import shading_fit

    camera, meshes = Camera.load(LMO / "camera.json"), scene_meshes()
    targets = {(t.frame, t.obj): t for t in load_targets(LMO)}
    beats, fits = {}, []
    for r in (r for r in rows if r["R"] is not None):
        image = cv2.imread(str(LMO / "rgb" / f"{r['frame']:06d}.png"), cv2.IMREAD_COLOR)
        grey, (bins, n_bins) = cv2.cvtColor(image, cv2.COLOR_BGR2GRAY), quantised(image)
        mesh, truth = meshes[r["obj"]], targets[(r["frame"], r["obj"])]
        estimate = np.array(r["R"]).reshape(3, 3), np.array(r["t"])
        fits.append((r["correct"], shading_fit(grey, mesh, *estimate, camera)))
        if r["correct"]:
            continue
        poses = [estimate, (truth.R, truth.t)]
        shading = [fits[-1][1], shading_fit(grey, mesh, truth.R, truth.t, camera)]
        contrast = [band_contrast(bins, n_bins, mesh_silhouette(mesh, R, t, camera), APPEARANCE_BAND_PX)
                    for R, t in poses]
        beats[(r["obj"], r["frame"])] = (shading[1] > shading[0], contrast[1] > contrast[0],
                                         r["near_score"] > r["score"])
    print("\nWrong estimates the truth beats, by the shading fit / the contrast across the silhouette / "
          "the edge score (near truth)")
    print("| object | wrong | shading fit | contrast | edge score |")
    print("|---|---|---|---|---|")
    for obj in [*objects, None]:
        mine = [b for (o, _), b in beats.items() if obj is None or o == obj]
        print(f"| {NAMES[obj] if obj else '**all**'} | {len(mine)} | "
              + " | ".join(str(sum(b[k] for b in mine)) for k in range(3)) + " |")
    right = [f for ok, f in fits if ok]
    wrong = [f for ok, f in fits if not ok]
    print(f"\nEstimates whose shading fit reaches a floor (pose.min_shading_fit): right of {len(right)}, "
          f"wrong of {len(wrong)}")
    for floor in SHADING_FLOORS:
        print(f"- {floor:g}: {sum(f >= floor for f in right)} right, {sum(f >= floor for f in wrong)} wrong")


def light_report(targets: list[Target], images: dict, meshes: dict, camera: Camera, params, objects) -> None:
    """Highlights and silhouette contrast per object, Canny thresholds per image (``--light``)."""
    band = np.ones((7, 7), np.uint8)  # 3 px either side of the silhouette
    stats = {obj: [] for obj in objects}
    for frame, image in images.items():
        here = [t for t in targets if t.frame == frame]
        labels = rasterize(camera, [Placed(meshes[t.obj], t.R, t.t) for t in here]).labels
        grey = to_gray(image)
        for k, target in enumerate(here):
            mask = (labels == k).astype(np.uint8)
            if target.obj not in stats or mask.sum() < 20:
                continue
            inside = (mask > 0) & (cv2.erode(mask, band) == 0)
            outside = (cv2.dilate(mask, band) > 0) & (mask == 0)
            colour = np.abs(image[inside].mean(axis=0) - image[outside].mean(axis=0))
            stats[target.obj].append((np.mean(image[mask > 0].max(axis=1) >= 250),
                                      abs(grey[inside].mean() - grey[outside].mean()), colour.max()))
    print("\n| object | saturated share in silhouette (median / max) | silhouette contrast grey "
          "| colour (best channel) |")
    print("|---|---|---|---|")
    for obj, values in stats.items():
        v = np.array(values)
        print(f"| {NAMES[obj]} | {np.median(v[:, 0]):.3f} / {v[:, 0].max():.3f} | {np.median(v[:, 1]):.1f} | "
              f"{np.median(v[:, 2]):.1f} |")
    highs = []
    for image in images.values():
        grey = cv2.GaussianBlur(to_gray(image), (params.edges.blur_size,) * 2, params.edges.blur_sigma)
        magnitude = cv2.magnitude(cv2.Sobel(grey, cv2.CV_32F, 1, 0), cv2.Sobel(grey, cv2.CV_32F, 0, 1))
        highs.append(canny_thresholds(magnitude, params.edges)[1])
    print(f"\nCanny high threshold (Sobel magnitude, 0..255 grey): median {np.median(highs):.1f}, "
          f"range {min(highs):.1f}-{max(highs):.1f}; the floor for noise-free renders is "
          f"{params.edges.canny_min_high:g}")


if __name__ == "__main__":
    sys.exit(main())
