"""The larger-pose check: is the chosen pose a shrunken copy of the part sitting on its own edges?

Of the wrong poses the estimator reported on the bench's clean and clutter images, most were
turned by 100-180 degrees with the part's centre 1.25-3.4x as far as the truth's: the model,
turned and shrunk, lies on some of the real part's edges (docs/results/symmetry.md). This
check searches again about the chosen pose's place for larger poses only: the template
search (``search``) on the edge pixels within a box about the pose's projected centre, at
part sizes 1.25-3.8x its projected size (up to the search's largest), its best templates
matched by Kuhn-Munkres as seeds (``TetradHypotheses.at_seeds``, as the estimator's
``seeded`` generator does), the best of those refined also moved along their line of sight
(``depth_sweep``); those nearer than the chosen pose are climbed and polished, and the best
replaces it if it is still nearer and either scores more, or scores nearly as much and
carries more evidence against chance (``scoring.pose_surprises``). The score is a share, so
a shrunken copy that lies on the part's own edges can outscore the part's truth when an
occluder hides some of it; the truth then still explains more of the image in absolute
terms (docs/results/depth.md, session 24).
"""
from __future__ import annotations

import numpy as np

from ..aspect_graph import AspectGraph
from ..params import EstimatorParams
from .frame import Frame
from .hypotheses import TetradHypotheses, best_covered
from .refinement import Candidate, PoseRefiner, hypothesis_rounds
from .scoring import pose_surprises
from .search import TemplateSearch
from .workers import SERIAL, WorkerPool

#: part sizes searched, as multiples of the pose's projected size: the truth of the bench's
#: shrunken poses projected 1.3-3.4x as large
SIZE_RATIOS = 1.25 ** np.arange(1, 7)
#: the box searched reaches this many projected sizes from the pose's centre each way
BOX_HALF_WIDTH = 2.0
#: the best distinct templates matched as seeds
SEEDS = 48
#: the best verified rivals moved along their line of sight by these factors (``depth_sweep``)
SWEEP_STARTS = 16
DEPTH_FACTORS = (0.75, 0.87, 1.15)
#: a rival counts as larger when its centre is at most this share of the pose's distance
MAX_DEPTH_RATIO = 0.85
#: a larger rival scoring at least this share of the pose's score replaces it if it carries
#: more evidence; one scoring much less is another explanation, not a fuller one (a pose four
#: times as near covers much of the image with a low share and gathers evidence by its size)
EVIDENCE_SCORE_SHARE = 0.8


def depth_sweep(starts: list[Candidate], graph: AspectGraph, frame: Frame, p: EstimatorParams, refiner: PoseRefiner,
                pool: WorkerPool) -> list[Candidate]:
    """Each start moved along its line of sight by ``DEPTH_FACTORS`` and refined again: a start
    a few degrees off the truth often settles 10-30 % too far or too near, outside the
    refinement's reach of about 10 %."""
    if not starts:
        return []
    R = np.array([c.R for c in starts for _ in DEPTH_FACTORS])
    centres = np.array([f * (c.R @ graph.model_center + c.t) for c in starts for f in DEPTH_FACTORS])
    R, t, scores = refiner.refined_scores(R, centres - R @ graph.model_center, frame, p.pose,
                                          hypothesis_rounds(p.pose.refine_iterations), pool)
    return [Candidate(float(scores[j]), R[j], t[j], starts[j // len(DEPTH_FACTORS)].hypothesis)
            for j in range(len(R))]


def centre_distance(graph: AspectGraph, pose: Candidate) -> float:
    """How far the part's model centre lies from the camera at the pose, metres."""
    return float(np.linalg.norm(pose.R @ graph.model_center + pose.t))


def projected_place(graph: AspectGraph, R: np.ndarray, t: np.ndarray, frame: Frame) -> tuple[np.ndarray, float]:
    """The pose's model centre in pixels and the part's diameter there, in pixels."""
    depth = (R @ graph.model_center + t)[2]
    return (frame.camera.project_model(graph.model_center[None], R, t)[0],
            graph.model_diameter * frame.camera.focal / depth)


def larger_check_applies(best: Candidate, p: EstimatorParams, search: TemplateSearch | None) -> bool:
    """Whether the check runs on ``best``: it is on (``pose.larger_check``), there is a template
    search to run, and the pose scores below ``search.enough_score`` (a pose above it stopped
    the generators and is taken as clear)."""
    return p.pose.larger_check and search is not None and best.score < p.search.enough_score


def larger_pose(best: Candidate, graph: AspectGraph, frame: Frame, p: EstimatorParams, search: TemplateSearch,
                hypotheses: TetradHypotheses, refiner: PoseRefiner, pool: WorkerPool = SERIAL) -> Candidate:
    """``best``, or a larger pose about its place that the image prefers (module doc)."""
    rival = larger_rival(best, graph, frame, p, search, hypotheses, refiner, pool)
    return rival if rival is not None and prefers_rival(best, rival, graph, frame, p) else best


def larger_rival(best: Candidate, graph: AspectGraph, frame: Frame, p: EstimatorParams, search: TemplateSearch,
                 hypotheses: TetradHypotheses, refiner: PoseRefiner, pool: WorkerPool = SERIAL) -> Candidate | None:
    """The best larger pose about ``best``'s place, climbed and polished, still nearer than
    ``MAX_DEPTH_RATIO`` of its distance; None if the search finds none."""
    if (best.R @ graph.model_center + best.t)[2] <= 0:
        return None
    centre, size = projected_place(graph, best.R, best.t, frame)
    # no larger than the search's own largest size: a pose very near the camera (a not-found
    # image's best) would otherwise ask for templates, and maps padded for them, of many
    # thousands of pixels (one such image took 24 GB)
    sizes = size * SIZE_RATIOS
    sizes = sizes[sizes <= search.sizes(frame, p.search, p.pose.distances)[-1]]
    if not len(sizes):
        return None
    h, w = frame.evidence.shape
    x0, y0 = np.clip(np.floor(centre - BOX_HALF_WIDTH * size), 0, [w, h]).astype(int)
    x1, y1 = np.clip(np.ceil(centre + BOX_HALF_WIDTH * size), 0, [w, h]).astype(int)
    coarse = search.coarse(frame, p.search, pool, sizes=sizes, box=(x0, y0, x1, y1))
    seeds = search.best(coarse, frame, SEEDS, p.search)
    matched = hypotheses.at_seeds(seeds, frame, p.search.seed_window, p.matching, pool)
    distance = centre_distance(graph, best)
    verified = refiner.realign(refiner.verify(best_covered(matched, p.search.hypotheses), frame, p.pose, pool),
                               frame, p.pose, pool)
    verified += depth_sweep(sorted(verified, key=lambda c: -c.score)[:SWEEP_STARTS], graph, frame, p, refiner, pool)
    larger = [c for c in verified if centre_distance(graph, c) < MAX_DEPTH_RATIO * distance]
    if not larger:
        return None
    rival = refiner.best(larger, frame, p.pose, pool)
    # the climb and polish may carry a larger start back to the pose's own depth (a twin of it)
    return rival if centre_distance(graph, rival) < MAX_DEPTH_RATIO * distance else None


def prefers_rival(best: Candidate, rival: Candidate, graph: AspectGraph, frame: Frame, p: EstimatorParams) -> bool:
    """Whether the larger ``rival`` replaces ``best``: it scores more, or at least
    ``EVIDENCE_SCORE_SHARE`` as much and carries more evidence against chance (module doc)."""
    if rival.score > best.score:
        return True
    if rival.score < EVIDENCE_SCORE_SHARE * best.score:
        return False
    surprises = pose_surprises(graph, np.array([rival.R, best.R]), np.array([rival.t, best.t]), frame, p.pose)
    return bool(surprises[0] > surprises[1])
