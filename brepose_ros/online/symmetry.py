"""The twin check: the final pose against its twins under the part's near symmetries.

A near-symmetric part (``offline.symmetry``) looks almost the same in a pose and in its twin,
the pose turned by the symmetry: the score of both is high, and the estimator may settle on
either. Here each twin of the final pose (``AspectGraph.symmetric_poses``, and for a nearly
rotational part its end-over-end turns, ``end_over_end``, and their rolls, ``rolled``) is
refined, climbed and polished on the image like the pose was, and the two are compared on the
only edges that tell them apart: the projected model edges of each that lie farther than
``DISTINCT_REACH`` inlier distances from every projected edge of the other (a hole on one
side, a chamfer, a tab). The share of those edges that like image edges confirm beyond
chance, counted as the score counts it (the local density of like edges is what chance
confirms; ``scoring.EdgeEvidence``), is each pose's evidence: the common edges would only
drown the small distinguishing feature, and clutter where a feature would be must not
confirm it.

The pose with more evidence is kept, and the difference of the two shares is its *margin*
(0 to 1): near 0 the image cannot decide (the feature is hidden, or absent from both), and
the estimate says so (``Estimate.ambiguous``). Where the feature is too small at this
distance to leave ``MIN_DISTINCT_PIXELS`` of distinguishing edge, the difference of the
whole scores chooses, and the margin is 0: a guess is no evidence. With several twins, a
pose that another shows less of stands down, and the best whole score among those left
wins. Exact symmetries need no check: their twins are the same pose of the part.

About a near continuous axis (a shaft with a flat, a screw) the stored twins are a few turns
only, and a pose rolled between them is compared with none: where the pose turned by
``ROLL_TIE_DEG`` either way about the axis scores within the scores' noise of it
(``roll_tied``), the image does not pin its roll, and the pose is tied as with a twin (the
shaft's trusted wrong poses were rolled 16-78 degrees or end over end, four of five with a
roll scoring within 0.012 of them or above; docs/results/confidence.md).

A twin that wins is checked once more against its own twins: the pose entering the check
may sit a few degrees off (its distinguishing edges then confirm little), while its twins
were refined onto the image; the winner's twins bring the pose's side back as well fitted.

The same comparison decides between the refinement's finalists (``check_rivals``): the
best few distinct poses, climbed and polished, of which a wrong one may score a little
above a right one (a part turned over at another depth, its outline lying on the real
part's edges); a finalist at the same place scoring no more than ``RIVAL_SCORE_GAP`` below
the best climbed one replaces it when the edges that tell the two apart show it clearly more
(by ``pose.twin_margin``; docs/results/choice.md).
"""
from __future__ import annotations

from typing import NamedTuple

import numpy as np

from ..aspect_graph import AspectGraph
from ..geometry import rotation_about, turned_poses
from ..params import PoseParams
from .frame import Frame
from .larger import projected_place
from .lines2d import point_segment_distance, samples_along
from .refinement import (CLIMB_ROUNDS, SAME_POSE_DEG, SAME_POSE_DIAMETERS, Candidate, PoseRefiner,
                         hypothesis_rounds)
from .scoring import pose_scores
from .workers import SERIAL, WorkerPool

#: an edge of one pose distinguishes it from its twin when farther than this many inlier
#: distances from every edge of the twin: the polished twin sits on the common edges within
#: a pixel or two, and a feature nearer than this would be confused with them
DISTINCT_REACH = 2.0
#: pieces the projected edges are cut into to find the distinguishing ones, pixels
PIECE_PIXELS = 2.0
#: fewer distinguishing pixels than this in both poses are too few to count on their own
#: (the notched plate's 8 x 6 mm notch at 2.5 px/mm leaves 0-20)
MIN_DISTINCT_PIXELS = 10.0

#: one pose shows more than another on the edges that tell them apart only by more than this,
#: and where those do not decide, a rival displaces the pose on the whole score only by more
#: than twice this: two poses that show nearly the same edges differ by pixel noise of up to
#: 0.015 (the notched plate's truth and flip scored 0.681 and 0.696)
MIN_GAIN = 0.0175
#: axes across a near continuous axis about which the end-over-end twins turn (every 15
#: degrees: the refinement closes the rest; ``end_over_end``)
ACROSS_DIRECTIONS = 12
#: of those, the best-scoring this many still end over end climb (besides the two that keep the
#: outline): the best alone was the shaft truth's end rolled half round (clutter 4), the
#: second 4 degrees off the truth
ACROSS_CLIMBED = 2
#: turns about the near axis a climbed end-over-end twin is scored at (``rolled``): the
#: climbed twins of the flange's clean 13 stood 6-8 degrees off the truth's roll (its bolt
#: holes), the shaft's clutter 4 3-4 degrees
ROLL_STEPS_DEG = (-8.0, -4.0, 4.0, 8.0)
#: turns about a near continuous axis, degrees, at which the final pose is scored for a roll
#: the image does not tell from it (``roll_tied``): within the stored twins' spacing (60-90
#: degrees on the shaft), beyond the refinement's reach of a few degrees
ROLL_TIE_DEG = (-30.0, -20.0, -10.0, 10.0, 20.0, 30.0)

#: a twin scoring this or more is a rival of the pose, whatever ``pose.min_score``: the
#: confidence's twin features (``twin_margin``, ``ambiguous``) were recorded with rivals from
#: this score on (bench/confidence.py's RECORD_FLOOR), and a twin a little below the found
#: floor still shows that the image may hold the part turned so
RIVAL_FLOOR = 0.3

#: a finalist of the refinement scoring at most this much below the best is compared with it
#: on the edges that tell them apart (``check_rivals``): where a right finalist lost to a wrong
#: one on the bench's clean images, it was by 0.006-0.035 (4 images); a wider gap would let the
#: evidence of a few distinguishing pixels overrule a clearly higher score
RIVAL_SCORE_GAP = 0.03
#: ... and lies at the same place: its projected centre less than this share of the best's
#: projected diameter from the best's. Two poses at different places share no edge, and their
#: evidence, the confirmed share of all their edges, leaves out the score's explained share
#: (a guard by that reasoning; no bench image changed by it)
RIVAL_PLACE = 0.5


class Verdict(NamedTuple):
    """What the twin check (or the rival check's comparison) kept: the ``pose``, its ``margin``
    over its strongest rival (``pick_by_evidence``), and whether it is ``tied``: a rival that
    the edges telling the two apart do not show less of scores within both scores' noise of
    the pose (``2 * MIN_GAIN``), so the image cannot choose between them at all (the notched
    plate and its half turn with the notch unseen, 0.910 against 0.902), or, from the twin
    check, the pose rolled a little about a near continuous axis does (``roll_tied``)."""

    pose: Candidate
    margin: float
    tied: bool = False


def check_twins(best: Candidate, graph: AspectGraph, refiner: PoseRefiner, frame: Frame,
                p: PoseParams, pool: WorkerPool = SERIAL, compared: list[Candidate] | None = None
                ) -> Verdict:
    """The pose (``best`` or one of its twins) with the most evidence on the edges that tell
    them apart, its margin over its strongest rival and whether a twin ties with it (module
    doc, ``Verdict``); margin None when the
    part has no near symmetry nor a near continuous axis (``end_over_end``), 1 when no twin
    holds on the image (each refines back onto the pose or scores below ``RIVAL_FLOOR``).
    The twins climb and polish on the ``pool``'s threads, in step, each as it would alone.
    When a twin wins, the check runs once more from it, its twins compared with all the poses
    ``compared`` already: a pose a few degrees off is compared with twins refined from it onto
    the image, so its own side is judged by its misfit; the winner's twins bring that side
    back as well fitted as the winner, and a pose the image could not tell from the winner
    still makes it ambiguous."""
    near = np.nonzero(~graph.exact_symmetries)[0]
    R_flip, t_flip, axis_of, keeps_outline = end_over_end(graph, best.R, best.t)
    if len(near) == 0 and len(R_flip) == 0:
        return Verdict(best, None)
    R, t = graph.symmetric_poses(best.R, best.t, near)
    R, t = refiner.refine(R, t, frame, p, CLIMB_ROUNDS)
    starts = [Candidate(float(score), R_k, t_k, best.hypothesis)
              for R_k, t_k, score in zip(R, t, pose_scores(graph, R, t, frame, p))]
    flip_axes = []  # the near axis (point, direction) each end-over-end start turned across
    if len(R_flip):
        # an end-over-end start lies up to half a direction step off, its roll and centre only
        # near: refined as a hypothesis is, aligned on the edge pixels first (from the climb
        # rounds alone the start nearest the shaft's truth scored below wrong ones). Of each
        # axis's ``ACROSS_DIRECTIONS`` the ``ACROSS_CLIMBED`` best still end over end go on,
        # and the two that keep the outline (square to the line of sight and nearest it): where
        # the image cannot tell the ends apart, one of them says so
        R_flip, t_flip, scores = refiner.refined_scores(R_flip, t_flip, frame, p,
                                                        hypothesis_rounds(p.refine_iterations), pool, align=True)
        # a twin refined back to the pose's end (its axis pointing the pose's way again, at
        # whatever roll) is no twin and takes no climb from one that is
        near_axes = graph.symmetry_axes[~graph.exact_axes]
        directions = near_axes[axis_of, 1]
        turned = np.sum(np.einsum("kij,kj->ki", R_flip, directions) * (directions @ best.R.T), axis=1) < 0
        for axis in np.unique(axis_of):
            members = np.flatnonzero(axis_of == axis)
            chosen = set(members[keeps_outline[members]].tolist())
            across = members[turned[members]]
            for k in across[np.argsort(-scores[across], kind="stable")][:ACROSS_CLIMBED]:
                chosen.add(int(k))
            for k in sorted(chosen):
                starts.append(Candidate(float(scores[k]), R_flip[k], t_flip[k], best.hypothesis))
                flip_axes.append(near_axes[axis])
    # climbed over neighbouring views like the pose was: a near symmetry's twin starts a
    # few degrees off, and a twin left in a worse optimum would lose for that alone; an
    # end-over-end twin's roll is then scored a few degrees either way (``rolled``)
    climbed = refiner.climb_together(starts, frame, p, pool, each_alone=True)
    climbed[len(near):] = [rolled(c, *axis, graph, frame, p) for c, axis in zip(climbed[len(near):], flip_axes)]
    twins = refiner.polished(climbed, frame, p, pool)
    verdict = pick_by_evidence(best, twins + (compared or []), graph, frame, p)
    if compared is None and verdict.pose is not best:
        return check_twins(verdict.pose, graph, refiner, frame, p, pool, compared=[best] + twins)
    return verdict._replace(tied=verdict.tied or roll_tied(verdict.pose, graph, frame, p))


def roll_tied(pose: Candidate, graph: AspectGraph, frame: Frame, p: PoseParams) -> bool:
    """Whether the pose turned by one of ``ROLL_TIE_DEG`` about a near (not exact) continuous
    axis of the part scores within both scores' noise of it (``2 * MIN_GAIN``), or more: the
    image does not pin the pose's roll (module doc)."""
    for point, axis in graph.symmetry_axes[~graph.exact_axes]:
        R, t = _rolls(pose, point, axis, ROLL_TIE_DEG)
        if np.any(pose_scores(graph, R, t, frame, p) >= pose.score - 2 * MIN_GAIN):
            return True
    return False


def _rolls(pose: Candidate, point: np.ndarray, axis: np.ndarray, angles_deg) -> tuple[np.ndarray, np.ndarray]:
    """The pose turned by each of ``angles_deg`` about the part's axis through ``point``."""
    turns = np.array([rotation_about(axis, np.radians(angle)) for angle in angles_deg])
    return turned_poses(pose.R, pose.t, turns, point - turns @ point)  # about the line through ``point``


def end_over_end(graph: AspectGraph, R: np.ndarray, t: np.ndarray
                 ) -> tuple[np.ndarray, np.ndarray, np.ndarray, np.ndarray]:
    """The twins (K, 3, 3), (K, 3) of pose R, t turned end over end about each near (not
    exact) continuous axis of the part, the index of that axis (K,), and whether each keeps the
    outline (K,): half turns about ``ACROSS_DIRECTIONS`` axes across it through its point,
    evenly over a half circle from the one square to the line of sight (that one and the
    ``ACROSS_DIRECTIONS // 2``-th, the one nearest the line of sight, keep the outline). A
    nearly rotational part (a shaft with a flat, a screw) shows almost the same outline turned
    so (the silhouette of a body of revolution is symmetric about its axis's middle), and its
    stored near symmetries are turns about the axis, which do not reach that twin. Which axis
    across maps the part's odd features (a flat, a cross hole) onto the image is the roll
    about its axis, which the image tells least: the pose's own roll may be off by any angle,
    so every direction is tried, but once: two half turns across differ by a turn about the
    axis of twice the angle between them, and where that turn is an exact symmetry (a
    flange's bolt circle turned by a sixth) the two twins are one pose of the part
    (``distinct_poses``)."""
    near_axes = graph.symmetry_axes[~graph.exact_axes]
    R_twins, t_twins, axis_of, keeps_outline = [], [], [], []
    sight = R.T @ (R @ graph.model_center + t)  # camera to the part's centre, in the model frame
    for index, (point, axis) in enumerate(near_axes):
        across = np.cross(axis, sight)
        if np.linalg.norm(across) < 1e-9 * np.linalg.norm(sight):
            continue  # seen along the axis: the outline is a circle, no end is in view
        across /= np.linalg.norm(across)
        turns = np.array([rotation_about(rotation_about(axis, angle) @ across, np.pi)
                          for angle in np.pi * np.arange(ACROSS_DIRECTIONS) / ACROSS_DIRECTIONS])
        # each turn about the line through ``point``: X -> turn X + (point - turn point)
        R_axis, t_axis = turned_poses(R, t, turns, point - turns @ point)
        first = distinct_poses(graph, R_axis, t_axis)
        kept = np.unique(first)
        R_twins.extend(R_axis[kept])
        t_twins.extend(t_axis[kept])
        axis_of.extend([index] * len(kept))
        keeps_outline.extend(np.isin(kept, first[[0, ACROSS_DIRECTIONS // 2]]).tolist())
    return (np.array(R_twins).reshape(-1, 3, 3), np.array(t_twins).reshape(-1, 3),
            np.array(axis_of, dtype=np.int64), np.array(keeps_outline, dtype=bool))


def rolled(twin: Candidate, point: np.ndarray, axis: np.ndarray, graph: AspectGraph, frame: Frame,
           p: PoseParams) -> Candidate:
    """The end-over-end ``twin`` turned about the near continuous axis through ``point`` by
    the one of ``ROLL_STEPS_DEG`` that scores best, if it scores more than the twin: what
    tells the roll of a nearly rotational part is its small odd features (a flange's bolt
    holes), which the line rounds hardly move, while its outline stays put at any roll."""
    R, t = _rolls(twin, point, axis, ROLL_STEPS_DEG)
    scores = pose_scores(graph, R, t, frame, p)
    k = int(np.argmax(scores))
    return Candidate(float(scores[k]), R[k], t[k], twin.hypothesis) if scores[k] > twin.score else twin


def distinct_poses(graph: AspectGraph, R: np.ndarray, t: np.ndarray) -> np.ndarray:
    """(K,) for each of the poses (K, 3, 3), (K, 3), the first of them that shows the part
    alike (``same_pose``)."""
    first = np.arange(len(R))
    for k in range(1, len(R)):
        for j in range(k):
            if first[j] == j and same_pose(graph, R[j], t[j], R[k], t[k]):
                first[k] = j
                break
    return first


def check_rivals(finalists: list[Candidate], graph: AspectGraph, frame: Frame, p: PoseParams) -> Candidate:
    """Of the refinement's finalists (``PoseRefiner.finalists``: the best climbed pose first),
    the first, or a rival at its place (``RIVAL_PLACE``) scoring no more than
    ``RIVAL_SCORE_GAP`` below it that the edges telling the two apart show by at least
    ``pose.twin_margin`` more (``pick_by_evidence``, module doc)."""
    best = finalists[0]
    if (best.R @ graph.model_center + best.t)[2] <= 0:
        return best
    centre, size = projected_place(graph, best.R, best.t, frame)
    rivals = [c for c in finalists[1:] if c.score >= best.score - RIVAL_SCORE_GAP
              and np.hypot(*(frame.camera.project_model(graph.model_center[None], c.R, c.t)[0] - centre))
              < RIVAL_PLACE * size]
    if not rivals:
        return best
    winner, margin, _ = pick_by_evidence(best, rivals, graph, frame, p)
    # a lower score is overruled only where the image tells the two apart (the margin below
    # which a pose is called ambiguous against its twin): a right pose lost to a pose on the
    # part's rim at a 0.06 margin, a 176-degree turn lost to the right pose at 0.74
    return winner if margin >= p.twin_margin else best


def pick_by_evidence(best: Candidate, twins: list[Candidate], graph: AspectGraph, frame: Frame,
                     p: PoseParams) -> Verdict:
    """Of the pose and its refined ``twins``, the one with the most evidence on the edges
    that tell them apart, its margin over its strongest rival, and whether a rival ties with
    it (``Verdict``; ``check_twins``, ``check_rivals``; also bench/flips.py's generic
    alternates)."""
    # a twin is a rival when it scores like a pose the image could hold and did not refine
    # back onto the pose (or onto another rival)
    rivals: list[Candidate] = []
    for twin in twins:
        if twin.score >= RIVAL_FLOOR and not any(same_pose(graph, twin.R, twin.t, c.R, c.t) for c in [best] + rivals):
            rivals.append(twin)
    if not rivals:
        return Verdict(best, 1.0)  # no twin holds on this image
    # with several near symmetries the rivals are twins of each other too: each pose's margin
    # is its smallest gain over any other
    poses = [best] + rivals
    gains = np.zeros((len(poses), len(poses)))  # gains[i, j]: how much more pose j shows than pose i
    seen = np.ones((len(poses), len(poses)), bool)  # whether the image can tell poses i and j apart
    for i, j in zip(*np.triu_indices(len(poses), 1)):
        gains[i, j], seen[i, j] = twin_evidence(graph, poses[i], poses[j], frame, p)
        gains[j, i], seen[j, i] = -gains[i, j], seen[i, j]
    # a pose stands unless another shows more of the edges that tell the two apart; among the
    # standing ones the image does not decide, and the whole score does: a pose that loses on
    # its evidence to one twin (it sits a few degrees off it) must not win over another by a
    # whole score that differs by noise
    beaten = ((gains > MIN_GAIN) & seen).any(axis=1)
    standing = np.flatnonzero(~beaten)
    np.fill_diagonal(gains, np.inf)
    margins = gains.min(axis=0)
    scores = np.array([c.score for c in poses])
    if len(standing) == 0:  # a cycle of gains: the pose with the largest smallest gain
        winner = int(np.argmax(margins))
        if margins[winner] <= margins[0] + 2 * MIN_GAIN:
            winner = 0
    else:
        winner = int(standing[np.argmax(scores[standing])])
        if not beaten[0] and scores[winner] <= scores[0] + 2 * MIN_GAIN:
            # the pose won on the whole score already: a rival the image does not tell from
            # it displaces it only by more than both scores' noise (the screw's clutter 4 lost
            # its right pose to a flip 0.018 above it)
            winner = 0
    # the poses the winner does not show more of than they show (or the image cannot tell
    # from it): where one of them scores within the scores' noise, nothing chose
    undecided = (~seen[:, winner]) | (gains[:, winner] <= 0.0)
    undecided[winner] = False
    tied = bool(np.any(undecided & (scores >= scores[winner] - 2 * MIN_GAIN)))
    # where the distinguishing feature shows too little, the whole scores chose: no margin
    return Verdict(poses[winner], float(max(margins[winner], 0.0)) if seen[:, winner].all() else 0.0, tied)


def same_pose(graph: AspectGraph, R_a: np.ndarray, t_a: np.ndarray, R_b: np.ndarray, t_b: np.ndarray) -> bool:
    """Whether two poses show the part alike: pose b lies within ``refinement.SAME_POSE_DEG``
    and ``SAME_POSE_DIAMETERS`` of pose a or of one of its twins under the part's exact discrete
    symmetries, or turned about an exact continuous axis (the axis line maps alike). Two
    stored near twins that an exact symmetry makes one (the flange's quarter turns either way
    under its sixths) are otherwise two rivals the image can never tell apart, and zero the
    winner's margin."""
    R, t = graph.symmetric_poses(R_a, t_a, graph.exact_symmetries)
    R, t = np.concatenate([R_a[None], R]), np.concatenate([t_a[None], t])
    near = SAME_POSE_DIAMETERS * graph.model_diameter
    cos = (np.einsum("kji,ji->k", R, R_b) - 1.0) / 2.0  # trace(R_k^T R_b)
    if np.any((cos > np.cos(np.radians(SAME_POSE_DEG))) & (np.linalg.norm(t - t_b, axis=1) < near)):
        return True
    for point, axis in graph.symmetry_axes[graph.exact_axes]:
        along = (R @ axis) @ (R_b @ axis) > np.cos(np.radians(SAME_POSE_DEG))
        at = np.linalg.norm(R @ point + t - (R_b @ point + t_b), axis=1) < near
        if np.any(along & at):
            return True
    return False


def twin_evidence(graph: AspectGraph, pose: Candidate, twin: Candidate, frame: Frame,
                  p: PoseParams) -> tuple[float, bool]:
    """How much more the image shows of the twin than of the pose, and whether it can tell:
    the twin's share of its distinguishing edges that the image confirms beyond chance minus
    the pose's share of its own (``EdgeEvidence.confirmed_beyond_chance``). When neither shows ``MIN_DISTINCT_PIXELS``
    of distinguishing edge (a small feature on a small image, or one seen edge-on), the image
    cannot tell (False), and the difference of the whole scores, which the feature still
    moves a little, is all there is to choose by."""
    drawn = [frame.camera.project_model(graph.seg_3d[graph.visible_segments(c.R, c.t)], c.R, c.t)
             for c in (pose, twin)]
    reach = DISTINCT_REACH * p.inlier_pixels
    pieces = [distinct_pieces(drawn[0], drawn[1], reach), distinct_pieces(drawn[1], drawn[0], reach)]
    if max(len(piece) for piece in pieces) * PIECE_PIXELS < MIN_DISTINCT_PIXELS:
        return twin.score - pose.score, False
    shares = [frame.evidence.confirmed_beyond_chance(piece, p.inlier_pixels) for piece in pieces]
    return float(shares[1] - shares[0]), True


def distinct_pieces(segments: np.ndarray, others: np.ndarray, reach: float) -> np.ndarray:
    """Pieces (N, 2, 2) about ``PIECE_PIXELS`` long of the segments (pixels) that lie farther
    than ``reach`` from every one of ``others``."""
    if len(segments) == 0:
        return np.zeros((0, 2, 2))
    delta = segments[:, 1] - segments[:, 0]
    counts = np.maximum(np.ceil(np.hypot(delta[:, 0], delta[:, 1]) / PIECE_PIXELS).astype(int), 1)
    segment, frac = samples_along(counts)
    half = (delta / (2.0 * counts[:, None]))[segment]
    centers = segments[segment, 0] + frac[:, None] * delta[segment]
    if len(others):
        far = point_segment_distance(centers[:, None], others[None]).min(axis=1) > reach
        centers, half = centers[far], half[far]
    return np.stack([centers - half, centers + half], axis=1)
