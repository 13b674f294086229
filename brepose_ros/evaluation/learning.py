"""The seed paper's learning mechanism (section 6, Fig. 6): the estimator's thresholds tuned
on simple training shapes with known poses, then kept in a parameter file.

1. Training scenes (``training_parts``): the built-in training shapes (``TRAINING_SHAPES``)
   in the accuracy bench's conditions and look, with their aspect graphs; a training sample
   and a held-out sample (another seed) of images, read into memory once.
2. A trial (``evaluate``) runs every image through the paper's method alone
   (``Estimator.estimate(paper_only=True)``) with one set of parameters; errors are taken
   against the nearest symmetric equivalent of the true pose (a cube turned by 90 degrees
   looks the same).
3. The loss (``Score.loss``): the mean error rate ``er`` (CONVENTIONS.md; a missed part
   counts 0.5), plus the share by which the median time per image exceeds the latency budget.
4. The search (``learn``): optuna's TPE sampler over ``SEARCH_SPACE``, the defaults first.
5. The choice (``choose``): the best few trials and the defaults re-scored on the held-out
   images; the defaults stay unless a trial beats them there by ``HELD_OUT_MARGIN`` standard
   errors: the best of tens of noisy trials on the training images is partly their luck.

Only the parameters of ``SEARCH_SPACE`` are searched (those of the estimator that exist:
the others keep their defaults); ``write_learned`` writes the changed ones in the layout of
a ROS 2 parameter file, which ``EstimatorParams.load`` also reads, and ``write_trials`` the
log of every trial.
"""
from __future__ import annotations

import csv
import datetime
import itertools
import time
from dataclasses import dataclass, replace
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

#: the paper's cube, box and cylinder, and two shapes without rotational symmetry: a wrong view
#: of the first three is often one of their symmetries (forgiven), of the last two never, as
#: on the bench parts, where the paper's method errs most by a flipped view
TRAINING_SHAPES = ("cube", "box", "cylinder", "l_block", "wedge")
#: name -> scene generator settings (``synthetic.scenes.SceneConfig`` keywords): the
#: accuracy bench's conditions and look (bench/accuracy.py: random lights, backgrounds and
#: props, the part 15-70 % of the image), so the thresholds are learned on the images they
#: are judged on
TRAINING_CONDITIONS = {
    "clean": {"look": "varied", "span": (0.15, 0.70)},
    "clutter": {"look": "varied", "span": (0.15, 0.70), "offcenter": True, "clutter": 4},
    "occl30+clutter": {"look": "varied", "span": (0.15, 0.70), "offcenter": True, "clutter": 4, "occlusion": 0.3},
}
#: the held-out images' seed is the training seed plus this: other images of the same kind
HELD_OUT_SEED_OFFSET = 1000
#: a learned set replaces the defaults only when its held-out loss is lower by more than this
#: many standard errors of the per-image difference: where no set is truly better, the best
#: of three finalists passes 1 standard error by chance in 39 of 100 runs of a synthetic
#: objective, 2 in 9 (docs/results/learning.md)
HELD_OUT_MARGIN = 2.0


@dataclass(frozen=True)
class Knob:
    """One searched parameter (a flat name of ``EstimatorParams.flat``) and its range."""

    name: str
    low: float
    high: float
    log: bool = False


#: the searched parameters: the paper's (the empty-element coefficient, the nearest group's,
#: the thresholds of Canny and the gap of Hough, the merge distance) and the matcher's
#: coverage tolerance, in ranges around the defaults: tens of trials cannot explore more. The Canny
#: threshold stops at 7 noise levels: 9.5, learned on renders alone, lost a photograph's
#: faint edges (docs/results/learning.md). ``pose.*`` is left out: it changes what the score
#: means, on which ``pose.min_score`` is calibrated; ``matching.hypotheses`` too: the paper's
#: method, which the loss measures, takes the best hypothesis only
SEARCH_SPACE = (
    Knob("matching.empty_coefficient", 0.1, 0.6, log=True),
    Knob("matching.nearest_threshold", 0.3, 0.8),
    Knob("edges.canny_noise_factor", 3.0, 7.0, log=True),
    Knob("edges.canny_low_ratio", 0.25, 0.6),
    Knob("edges.hough_max_gap", 1.0, 6.0),
    Knob("edges.merge_distance", 1.0, 3.5),
    Knob("matching.coverage_tolerance", 0.025, 0.06),
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
                   conditions: dict | None = None,
                   held_out_n: int = 0) -> tuple[list[TrainingPart], list[TrainingPart]]:
    """Compile (once) the shapes' aspect graphs and render (once) ``n`` training images per
    shape and condition into ``cache``, and ``held_out_n`` held-out ones (seed ``seed +
    HELD_OUT_SEED_OFFSET``); the two lists share each shape's estimator. Needs the CAD stack."""
    from ..offline.cad import load_step, tessellate
    from ..offline.compiler import compile_aspect_graph
    from ..scene_folder import load_scene
    from ..synthetic.scenes import SceneConfig, generate_scene
    from ..synthetic.shapes import export_step

    def images(step: Path, shape: str, count: int, image_seed: int):
        loaded, camera = [], None
        for condition, config in (conditions or TRAINING_CONDITIONS).items():
            folder = cache / f"scene_{shape}_{condition}_{count}_{image_seed}"
            if not (folder / "gt.json").exists():
                generate_scene(step, folder, count, seed=image_seed, config=SceneConfig(**config))
            scene = load_scene(folder)
            camera = scene.camera
            loaded += [(cv2.imread(str(e.path), cv2.IMREAD_UNCHANGED), e.R, e.t) for e in scene.entries]
        return loaded, camera

    cache.mkdir(parents=True, exist_ok=True)
    train, held_out = [], []
    for shape in shapes:
        step = cache / f"{shape}.step"
        if not step.exists():
            export_step(shape, step)
        graph_path = cache / f"{shape}_{step_deg:g}deg.brepose.npz"
        if not graph_path.exists():
            compile_aspect_graph(step, step_deg=step_deg, progress=False).save(graph_path)
        mesh = tessellate(load_step(step))
        train_images, camera = images(step, shape, n, seed)
        part = TrainingPart(shape, Estimator(AspectGraph.load(graph_path)),
                            ModelPoints.from_mesh(mesh.vertices, mesh.triangles), symmetry_rotations(shape),
                            camera, train_images)
        train.append(part)
        if held_out_n:
            held_out.append(replace(part, images=images(step, shape, held_out_n, seed + HELD_OUT_SEED_OFFSET)[0]))
    return train, held_out


def standard_error(values: np.ndarray) -> float:
    """The standard error of the mean of ``values`` (0 for fewer than two)."""
    return float(np.std(values, ddof=1) / np.sqrt(len(values))) if len(values) > 1 else 0.0


@dataclass
class Score:
    """One parameter set on a sample of images: the paper's method alone."""

    errors: np.ndarray  # er per image (CONVENTIONS.md; a missed part counts 0.5)
    median_ms: float  # time per image

    @property
    def error_rate(self) -> float:
        return float(np.mean(self.errors))

    @property
    def standard_error(self) -> float:
        return standard_error(self.errors)

    def loss(self, budget_ms: float) -> float:
        """The mean er, plus the share by which the median time exceeds ``budget_ms``."""
        over = max(self.median_ms / budget_ms - 1.0, 0.0) if budget_ms > 0 else 0.0
        return self.error_rate + over

    def to_dict(self) -> dict:
        return {"error_rate": round(self.error_rate, 4), "standard_error": round(self.standard_error, 4),
                "median_ms": round(self.median_ms, 1), "images": len(self.errors)}


def evaluate(parts: list[TrainingPart], params: EstimatorParams) -> Score:
    """The paper's method alone (``Estimator.estimate(paper_only=True)``) over every image of
    ``parts`` with ``params``; errors modulo each shape's symmetries."""
    errors, times = [], []
    for part in parts:
        part.estimator.params = params
        for image, R_gt, t_gt in part.images:
            estimate = part.estimator.estimate(image, part.camera, paper_only=True)
            errors.append(symmetric_errors(estimate.R, estimate.t, R_gt, t_gt, part.model, part.symmetries).error_rate
                          if estimate.found else NOT_FOUND_ERROR_RATE)
            times.append(estimate.timings.get("total", 0.0) * 1000.0)
    return Score(np.asarray(errors, dtype=float), float(np.median(times)))


@dataclass(frozen=True)
class Verdict:
    """Which of the finalists replaces the defaults, if any, and why."""

    winner: int | None  # index into the finalists; None: the defaults stay
    gain: float  # the defaults' held-out loss minus the best finalist's
    standard_error: float  # of the per-image difference in er between the two
    reason: str


def choose(defaults: Score, finalists: list[Score], budget_ms: float, margin: float = HELD_OUT_MARGIN) -> Verdict:
    """The finalist of lowest held-out loss, if it beats the defaults' on the same images by more
    than ``margin`` standard errors of the paired per-image difference; else the defaults."""
    if not finalists:
        return Verdict(None, 0.0, 0.0, "no trial besides the defaults")
    best = min(range(len(finalists)), key=lambda i: finalists[i].loss(budget_ms))
    gain = defaults.loss(budget_ms) - finalists[best].loss(budget_ms)
    difference = finalists[best].errors - defaults.errors
    se = standard_error(difference)
    summary = (f"held-out loss {finalists[best].loss(budget_ms):.4f} against the defaults' "
               f"{defaults.loss(budget_ms):.4f} (difference {-gain:+.4f}, standard error {se:.4f})")
    if gain > 0 and gain > margin * se:
        return Verdict(best, gain, se, f"learned: {summary}")
    return Verdict(None, gain, se, f"defaults kept: the best finalist's {summary} is not lower by more than "
                                   f"{margin:g} standard error")


@dataclass
class LearnResult:
    params: EstimatorParams
    changed: dict  # flat name -> learned value (the searched knobs); empty when the defaults stay
    verdict: Verdict
    default: dict  # "train", "held_out": the defaults' Score on each sample
    chosen: dict  # the same for the set chosen (the defaults' when they stay)
    budget_ms: float
    trials: list[dict]  # one record per trial (``trial_record``), in order
    seconds: float


def trial_record(number: int, values: dict, train: Score, budget_ms: float, seconds: float) -> dict:
    """One row of the trial log: its parameters, training score and loss (held-out columns
    filled in for the finalists)."""
    return {"trial": number, "loss": round(train.loss(budget_ms), 4)} | {
        k: round(v, 4) for k, v in train.to_dict().items() if k != "images"} | {
        "seconds": round(seconds, 1), "held_out_loss": None, "held_out_error_rate": None} | values


def held_out_columns(held_out: Score, budget_ms: float) -> dict:
    """A trial log row's held-out columns (``trial_record``) for a set re-scored there."""
    return {"held_out_loss": round(held_out.loss(budget_ms), 4), "held_out_error_rate": round(held_out.error_rate, 4)}


def learn(train, held_out, trials: int, timeout_s: float, latency_factor: float = 1.5, seed: int = 0,
          finalists: int = 3, on_record: Callable[[dict, list[dict]], None] | None = None,
          score: Callable[[object, EstimatorParams], Score] = evaluate) -> LearnResult:
    """Search ``search_space()`` with optuna's TPE for the lowest training ``Score.loss``, then
    re-score the ``finalists`` best trials and the defaults on the held-out images and keep the
    defaults unless ``choose`` finds a finalist better there. The defaults are the first trial
    and set the latency budget (``latency_factor`` times their median time). The search stops
    after ``trials`` trials or when only the held-out re-scoring's time (measured on the
    defaults) is left of ``timeout_s``. ``on_record(record, records)`` after every trial and
    re-scoring (progress and the trial log). ``score(sample, params)`` scores a sample
    (``train`` or ``held_out``): by default ``evaluate`` on lists of ``TrainingPart``."""
    import optuna

    optuna.logging.set_verbosity(optuna.logging.WARNING)
    start = time.perf_counter()
    defaults = EstimatorParams()
    knobs = search_space(defaults)
    default_values = {k.name: defaults.flat()[k.name] for k in knobs}
    default_held_out = score(held_out, defaults)
    held_out_seconds = time.perf_counter() - start
    clock = time.perf_counter()
    default_train = score(train, defaults)
    budget = latency_factor * default_train.median_ms
    scores: dict[int, Score] = {0: default_train}
    records = [trial_record(0, default_values, default_train, budget, time.perf_counter() - clock)]
    records[0] |= held_out_columns(default_held_out, budget)
    if on_record is not None:
        on_record(records[0], records)

    def objective(trial) -> float:
        clock = time.perf_counter()
        values = {k.name: trial.suggest_float(k.name, k.low, k.high, log=k.log) for k in knobs}
        scores[trial.number] = score(train, defaults.with_flat(values))
        records.append(trial_record(trial.number, values, scores[trial.number], budget, time.perf_counter() - clock))
        if on_record is not None:
            on_record(records[-1], records)
        return scores[trial.number].loss(budget)

    study = optuna.create_study(direction="minimize", sampler=optuna.samplers.TPESampler(seed=seed, n_startup_trials=5))
    study.add_trial(optuna.trial.create_trial(
        params=default_values, value=default_train.loss(budget),
        distributions={k.name: optuna.distributions.FloatDistribution(k.low, k.high, log=k.log) for k in knobs}))
    remaining = timeout_s - (time.perf_counter() - start) - finalists * latency_factor * held_out_seconds
    if trials > 0 and remaining > 0:
        study.optimize(objective, n_trials=trials, timeout=remaining)
    ranked = sorted((t for t in study.trials if t.number > 0), key=lambda t: t.value)[:finalists]
    held_out_scores = []
    for t in ranked:
        held_out_scores.append(score(held_out, defaults.with_flat(t.params)))
        records[t.number] |= held_out_columns(held_out_scores[-1], budget)
        if on_record is not None:
            on_record(records[t.number], records)
    verdict = choose(default_held_out, held_out_scores, budget)
    default = {"train": default_train, "held_out": default_held_out}
    if verdict.winner is None:
        return LearnResult(defaults, {}, verdict, default, default, budget, records, time.perf_counter() - start)
    won = ranked[verdict.winner]
    changed = dict(won.params)
    return LearnResult(defaults.with_flat(changed), changed, verdict, default,
                       {"train": scores[won.number], "held_out": held_out_scores[verdict.winner], "trial": won.number},
                       budget, records, time.perf_counter() - start)


def write_trials(path: Path, records: list[dict]) -> None:
    """The trial log as CSV: one row per trial (parameters, training score and loss, held-out
    loss of the finalists and the defaults)."""
    path.parent.mkdir(parents=True, exist_ok=True)
    with path.open("w", newline="") as f:
        writer = csv.DictWriter(f, fieldnames=list(dict.fromkeys(k for r in records for k in r)))
        writer.writeheader()
        writer.writerows(records)


#: the node name of the parameter file (``ros.node.NODE_NAME``; not imported: no rclpy here)
NODE_NAME = "estimator"


def write_learned(path: Path, result: LearnResult, provenance: dict) -> None:
    """The learned parameters as a ROS 2 parameter file (``NODE: ros__parameters: group:``),
    the provenance, scores and the held-out verdict in its leading comments; when the defaults
    stay, a file that changes nothing (an empty ``ros__parameters``)."""
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
    lines += [f"# {result.verdict.reason}"]
    lines += [f"# {sample} score of the paper's method, defaults: {result.default[sample].to_dict()}"
              for sample in ("train", "held_out")]
    if result.changed:
        lines += [f"# {sample} score of the paper's method, learned (trial {result.chosen['trial']}): "
                  f"{result.chosen[sample].to_dict()}" for sample in ("train", "held_out")]
    lines += [f"# latency budget {result.budget_ms:.0f} ms (median, the paper's method), {len(result.trials) - 1} "
              f"trials in {result.seconds / 60:.1f} min", ""]
    body = yaml.safe_dump({NODE_NAME: {"ros__parameters": groups}}, sort_keys=False, default_flow_style=False)
    path.parent.mkdir(parents=True, exist_ok=True)
    path.write_text("\n".join(lines) + body)
