"""The seed paper's learning mechanism (section 6, Fig. 6): the estimator's thresholds tuned
on simple training shapes with known poses, then kept in a parameter file.

1. Training scenes (``training_parts``): the built-in cube, box and cylinder
   (``synthetic.shapes``), each clean and occluded among clutter (``synthetic.scenes``),
   with their aspect graphs; the images are read into memory once.
2. A trial (``evaluate``) runs every image through the paper's method alone
   (``Estimator.estimate(paper_only=True)``) and through the full pipeline with one set of
   parameters; errors are taken against the nearest symmetric equivalent of the true pose
   (the training shapes are symmetric: a cube turned by 90 degrees looks the same).
3. The loss (``Score.loss``): the full pipeline's failure rate plus the mean error rate
   ``er`` of both methods (CONVENTIONS.md; a missed part counts 0.5), and a penalty when the
   full pipeline's median time per image exceeds the latency budget.
4. The search (``learn``): optuna's TPE sampler over ``SEARCH_SPACE``, the defaults tried
   first, so the result is never worse than the defaults on the training scenes.

Only the parameters of ``SEARCH_SPACE`` are searched (those of the estimator that exist:
the others keep their defaults); ``write_learned`` writes the changed ones in the layout of
a ROS 2 parameter file, which ``EstimatorParams.load`` also reads.
"""
from __future__ import annotations

import datetime
import itertools
import time
from dataclasses import dataclass
from pathlib import Path
from typing import Callable

import cv2
import numpy as np
import yaml

from .. import __version__
from ..aspect_graph import AspectGraph
from ..camera import Camera
from ..online.estimator import Estimator
from ..params import EstimatorParams
from .metrics import NOT_FOUND_ERROR_RATE, ModelPoints, PoseErrors, pose_errors

TRAINING_SHAPES = ("cube", "box", "cylinder")
#: name -> scene generator settings (``synthetic.scenes.SceneConfig`` keywords): the paper's
#: training images are clean; occluded ones among clutter, under random lights and
#: backgrounds (the varied look), teach the occlusion and edge thresholds
TRAINING_CONDITIONS = {"clean": {}, "occluded_varied": {"occlusion": 0.25, "clutter": 3, "look": "varied"}}


@dataclass(frozen=True)
class Knob:
    """One searched parameter (a flat name of ``EstimatorParams.flat``) and its range."""

    name: str
    low: float
    high: float
    log: bool = False


#: the searched parameters: the paper's (the empty-element coefficient, the nearest group's,
#: the thresholds of Canny and the gap of Hough, the merge distance) and two of the matcher's
#: own, in ranges around the defaults: tens of trials cannot explore more. The Canny
#: threshold stops at 7 noise levels: 9.5, learned on renders alone, lost a photograph's
#: faint edges (docs/results/learning.md). ``pose.*`` is left out: it changes what the score
#: means, on which ``pose.min_score`` is calibrated
SEARCH_SPACE = (
    Knob("matching.empty_coefficient", 0.1, 0.6, log=True),
    Knob("matching.nearest_threshold", 0.3, 0.8),
    Knob("edges.canny_noise_factor", 3.0, 7.0, log=True),
    Knob("edges.canny_low_ratio", 0.25, 0.6),
    Knob("edges.hough_max_gap", 1.0, 6.0),
    Knob("edges.merge_distance", 1.0, 3.5),
    Knob("matching.coverage_tolerance", 0.025, 0.06),
    Knob("matching.hypotheses", 4, 10),
)


def search_space(defaults: EstimatorParams | None = None) -> list[Knob]:
    """The knobs of ``SEARCH_SPACE`` that the estimator has."""
    names = (defaults or EstimatorParams()).flat()
    return [k for k in SEARCH_SPACE if k.name in names]


def symmetry_rotations(shape: str) -> np.ndarray:
    """(S, 3, 3) rotations about the model origin that map a training shape onto itself:
    the cube's 24, the box's 4, the cylinder's turns about z (1 degree apart) and their
    flips; the identity alone for any other part."""
    if shape == "cube":
        signed = [np.diag(s)[list(p)] for p in itertools.permutations(range(3))
                  for s in itertools.product((1, -1), repeat=3)]
        return np.array([m for m in signed if np.linalg.det(m) > 0], dtype=float)
    if shape == "box":
        return np.array([np.diag(s) for s in itertools.product((1, -1), repeat=3) if np.prod(s) > 0], dtype=float)
    if shape == "cylinder":
        a = np.radians(np.arange(360.0))
        c, s, z, o = np.cos(a), np.sin(a), np.zeros_like(a), np.ones_like(a)
        turns = np.stack([np.stack([c, -s, z], -1), np.stack([s, c, z], -1), np.stack([z, z, o], -1)], axis=1)
        return np.concatenate([turns, turns @ np.diag([1.0, -1.0, -1.0])])
    return np.eye(3)[None]


def symmetric_errors(R, t, R_gt, t_gt, model: ModelPoints, symmetries: np.ndarray) -> PoseErrors:
    """``pose_errors`` against the symmetric equivalent of the truth nearest in rotation."""
    gaps = np.einsum("ij,sik->sjk", np.asarray(R), R_gt @ symmetries)  # R^T R_gt S
    nearest = int(np.argmax(np.trace(gaps, axis1=1, axis2=2)))
    return pose_errors(R, t, R_gt @ symmetries[nearest], t_gt, model)


@dataclass
class TrainingPart:
    """One training shape: its estimator, surface points, symmetries and images in memory."""

    name: str
    estimator: Estimator
    model: ModelPoints
    symmetries: np.ndarray
    camera: Camera
    images: list[tuple[np.ndarray, np.ndarray, np.ndarray]]  # (image, R_gt, t_gt)


def training_parts(cache: Path, shapes=TRAINING_SHAPES, n: int = 4, seed: int = 0, step_deg: float = 10.0,
                   conditions: dict | None = None) -> list[TrainingPart]:
    """Compile (once) the shapes' aspect graphs and render (once) ``n`` images per shape and
    condition into ``cache``; needs the CAD stack."""
    from ..offline.cad import load_step, tessellate
    from ..offline.compiler import compile_aspect_graph
    from ..scene_folder import load_scene
    from ..synthetic.scenes import SceneConfig, generate_scene
    from ..synthetic.shapes import export_step

    cache.mkdir(parents=True, exist_ok=True)
    parts = []
    for shape in shapes:
        step = cache / f"{shape}.step"
        if not step.exists():
            export_step(shape, step)
        graph_path = cache / f"{shape}_{step_deg:g}deg.brepose.npz"
        if not graph_path.exists():
            compile_aspect_graph(step, step_deg=step_deg, progress=False).save(graph_path)
        mesh = tessellate(load_step(step))
        images, camera = [], None
        for condition, config in (conditions or TRAINING_CONDITIONS).items():
            folder = cache / f"scene_{shape}_{condition}_{n}_{seed}"
            if not (folder / "gt.json").exists():
                generate_scene(step, folder, n, seed=seed, config=SceneConfig(**config))
            scene = load_scene(folder)
            camera = scene.camera
            images += [(cv2.imread(str(e.path), cv2.IMREAD_UNCHANGED), e.R, e.t) for e in scene.entries]
        parts.append(TrainingPart(shape, Estimator(AspectGraph.load(graph_path)),
                                  ModelPoints.from_mesh(mesh.vertices, mesh.triangles), symmetry_rotations(shape),
                                  camera, images))
    return parts


@dataclass
class Score:
    """One parameter set on the training images."""

    paper_error_rate: float  # mean er of the paper's method alone
    full_error_rate: float  # mean er of the full pipeline
    full_success: float  # share of images the full pipeline gets right
    median_ms: float  # full pipeline, per image

    def loss(self, budget_ms: float) -> float:
        over = max(self.median_ms / budget_ms - 1.0, 0.0) if budget_ms > 0 else 0.0
        return (1.0 - self.full_success) + self.paper_error_rate + self.full_error_rate + over

    def to_dict(self) -> dict:
        return {k: round(float(v), 4) for k, v in self.__dict__.items()}


def evaluate(parts: list[TrainingPart], params: EstimatorParams) -> Score:
    """Both methods over every training image with ``params``."""
    paper, full, success, times = [], [], [], []
    for part in parts:
        part.estimator.params = params
        for image, R_gt, t_gt in part.images:
            for paper_only, rates in ((True, paper), (False, full)):
                estimate = part.estimator.estimate(image, part.camera, paper_only=paper_only)
                errors = (symmetric_errors(estimate.R, estimate.t, R_gt, t_gt, part.model, part.symmetries)
                          if estimate.found else None)
                rates.append(errors.error_rate if errors else NOT_FOUND_ERROR_RATE)
                if not paper_only:
                    success.append(bool(errors and errors.success))
                    times.append(estimate.timings.get("total", 0.0) * 1000.0)
    return Score(float(np.mean(paper)), float(np.mean(full)), float(np.mean(success)), float(np.median(times)))


@dataclass
class LearnResult:
    params: EstimatorParams
    changed: dict  # flat name -> learned value (the searched knobs)
    default: Score
    best: Score
    budget_ms: float
    trials: int
    seconds: float


def learn(parts: list[TrainingPart], trials: int, timeout_s: float, latency_factor: float = 1.5, seed: int = 0,
          on_trial: Callable[[int, float, float, Score], None] | None = None) -> LearnResult:
    """Search ``search_space()`` with optuna's TPE for the lowest ``Score.loss``; the
    defaults are the first trial and set the latency budget (``latency_factor`` times their
    median time). Stops after ``trials`` trials or once ``timeout_s`` has passed.
    ``on_trial(number, loss, best_loss, score)`` after each trial (progress)."""
    import optuna

    optuna.logging.set_verbosity(optuna.logging.WARNING)
    start = time.perf_counter()
    defaults = EstimatorParams()
    knobs = search_space(defaults)
    kinds = {k.name: type(defaults.flat()[k.name]) for k in knobs}
    default_score = evaluate(parts, defaults)
    budget = latency_factor * default_score.median_ms
    scores: dict[int, Score] = {}

    def objective(trial) -> float:
        values = {}
        for k in knobs:
            if kinds[k.name] is int:
                values[k.name] = trial.suggest_int(k.name, int(k.low), int(k.high), log=k.log)
            else:
                values[k.name] = trial.suggest_float(k.name, k.low, k.high, log=k.log)
        scores[trial.number] = evaluate(parts, defaults.with_flat(values))
        return scores[trial.number].loss(budget)

    def progress(study, trial):
        if on_trial is not None:
            on_trial(trial.number, trial.value, study.best_value, scores[trial.number])

    study = optuna.create_study(direction="minimize", sampler=optuna.samplers.TPESampler(seed=seed, n_startup_trials=5))
    study.add_trial(optuna.trial.create_trial(
        params={k.name: defaults.flat()[k.name] for k in knobs}, value=default_score.loss(budget),
        distributions={k.name: (optuna.distributions.IntDistribution(int(k.low), int(k.high), log=k.log)
                                if kinds[k.name] is int else optuna.distributions.FloatDistribution(k.low, k.high,
                                                                                                   log=k.log))
                       for k in knobs}))
    scores[0] = default_score
    remaining = timeout_s - (time.perf_counter() - start)
    if trials > 0 and remaining > 0:
        study.optimize(objective, n_trials=trials, timeout=remaining, callbacks=[progress])
    best = study.best_trial
    changed = {name: kinds[name](value) for name, value in best.params.items()}
    return LearnResult(defaults.with_flat(changed), changed, default_score, scores[best.number], budget,
                       len(study.trials) - 1, time.perf_counter() - start)


#: the node name of the parameter file (``ros.node.NODE_NAME``; not imported: no rclpy here)
NODE_NAME = "estimator"


def write_learned(path: Path, result: LearnResult, provenance: dict) -> None:
    """The learned parameters as a ROS 2 parameter file (``NODE: ros__parameters: group:``),
    the provenance and scores in its leading comments."""
    groups: dict[str, dict] = {}
    for name, value in sorted(result.changed.items()):
        group, _, key = name.partition(".")
        groups.setdefault(group, {})[key] = round(value, 6) if isinstance(value, float) else value
    lines = ["# Estimator parameters learned by brepose-learn (the seed paper's section 6) on the",
             "# training shapes; the other parameters keep their defaults (config/estimator.yaml).",
             "# Use: brepose-estimate --params config/learned.yaml ..., or for the node",
             "#   estimator --params-file config/node.yaml --params-file config/learned.yaml",
             f"# version {__version__}, {datetime.datetime.now(datetime.timezone.utc):%Y-%m-%d %H:%M} UTC"]
    lines += [f"# {key}: {value}" for key, value in provenance.items()]
    lines += [f"# training score, defaults: {result.default.to_dict()}",
              f"# training score, learned:  {result.best.to_dict()}",
              f"# latency budget {result.budget_ms:.0f} ms (median, full pipeline), {result.trials} trials in "
              f"{result.seconds / 60:.1f} min", ""]
    body = yaml.safe_dump({NODE_NAME: {"ros__parameters": groups}}, sort_keys=False, default_flow_style=False)
    path.parent.mkdir(parents=True, exist_ok=True)
    path.write_text("\n".join(lines) + body)
