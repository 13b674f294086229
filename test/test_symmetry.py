"""Symmetries: found at compile time on parts with known answers, stored and checked in the
graph file, decided at run time between twins, and equal in the evaluation."""
from __future__ import annotations

import dataclasses
import json
import zipfile

import cv2
import numpy as np
import pytest

from brepose_ros.aspect_graph import EXACT_SYMMETRY_SHARE, AspectGraph, AspectGraphError
from brepose_ros.evaluation.metrics import ModelPoints, pose_errors
from brepose_ros.geometry import look_at_rotation, rotation_about, rotation_angle_deg
from brepose_ros.offline.hidden_lines import OUTLINE, SHARP
from brepose_ros.offline.symmetry import detect_symmetries

# ----------------------------------------------------------------------------- parts as arrays


def prism(outline: np.ndarray, height: float, views: int = 3, smooth: bool = False):
    """Edges (S, 2, 3) and surface (vertices, triangles) of a prism over a 2D polygon whose
    caps the fan from its first corner triangulates (convex, or an L from its inner corner);
    each edge repeated ``views`` times, as the views of a graph repeat them. A ``smooth``
    side (a cylinder's) has no edges along it."""
    n = len(outline)
    low = np.column_stack([outline, np.full(n, -height / 2)])
    high = np.column_stack([outline, np.full(n, height / 2)])
    ring = np.arange(n)
    edges = np.concatenate([np.stack([low, np.roll(low, -1, axis=0)], axis=1),
                            np.stack([high, np.roll(high, -1, axis=0)], axis=1),
                            np.stack([low, high], axis=1)[:0 if smooth else n]])
    vertices = np.concatenate([low, high])
    nxt = np.roll(ring, -1)
    sides = np.concatenate([np.stack([ring, nxt, n + nxt], axis=1), np.stack([ring, n + nxt, n + ring], axis=1)])
    fan = np.stack([np.zeros(n - 2, int), ring[1:-1], ring[2:]], axis=1)
    triangles = np.concatenate([sides, fan[:, ::-1], n + fan])
    return np.tile(edges, (views, 1, 1)), (vertices, triangles)


def rectangle(dx: float, dy: float) -> np.ndarray:
    return np.array([[-dx, -dy], [dx, -dy], [dx, dy], [-dx, dy]]) / 2


def circle(radius: float, sides: int = 72) -> np.ndarray:
    angles = np.linspace(0, 2 * np.pi, sides, endpoint=False)
    return radius * np.column_stack([np.cos(angles), np.sin(angles)])


def detect(edges, surface, diameter=None):
    diameter = diameter or float(np.ptp(surface[0], axis=0) @ np.ptp(surface[0], axis=0)) ** 0.5
    kinds = np.full(len(edges), SHARP, np.uint8)
    return detect_symmetries(edges, kinds, diameter, surface)


def exact(symmetries):
    return symmetries.shares >= EXACT_SYMMETRY_SHARE


def angle_of(S):
    return rotation_angle_deg(S, np.eye(3))


# ----------------------------------------------------------------------------- compile time

def test_a_cube_has_its_23_rotations_besides_the_identity():
    found = detect(*prism(rectangle(0.04, 0.04), 0.04))
    assert exact(found).sum() == 23
    angles = sorted(round(angle_of(S)) for S in found.rotations)
    assert angles == [90] * 6 + [120] * 8 + [180] * 9
    for S, b in zip(found.rotations, found.translations):  # about the cube's centre
        assert np.allclose(b, 0, atol=1e-4)


def test_a_box_with_three_different_sides_has_three_half_turns():
    found = detect(*prism(rectangle(0.06, 0.04), 0.025))
    assert exact(found).sum() == 3 and len(found.shares) == 3
    axes = sorted(int(np.argmax(np.diag(S))) for S in found.rotations)
    assert all(round(angle_of(S)) == 180 for S in found.rotations)
    assert axes == [0, 1, 2]  # each half turn keeps one axis


def test_a_cylinder_turns_continuously_about_its_axis():
    found = detect(*prism(circle(0.02), 0.05, smooth=True))
    assert len(found.axis_shares) == 1 and found.axis_shares[0] >= EXACT_SYMMETRY_SHARE
    point, axis = found.axes[0]
    assert abs(axis[2]) > 0.999 and np.linalg.norm(point[:2]) < 1e-4
    # its half turns about the diameters are one symmetry up to the turn about the axis
    assert len(found.shares) == 1 and exact(found).all() and round(angle_of(found.rotations[0])) == 180


def test_an_l_bracket_has_no_exact_symmetry():
    outline = np.array([[0.0, 0.0], [0.0, 0.05], [-0.008, 0.05], [-0.008, -0.008], [0.08, -0.008], [0.08, 0.0]])
    found = detect(*prism(outline, 0.05))
    assert not exact(found).any() and len(found.axis_shares) == 0


def test_a_box_with_one_notch_is_near_symmetric_about_the_half_turn_that_moves_the_notch():
    edges, surface = prism(rectangle(0.06, 0.04), 0.025)
    notch, _ = prism(rectangle(0.008, 0.008) + [0.02, 0.0], 0.025)  # a square hole through one end
    found = detect(np.concatenate([edges, notch]), surface)
    near = found.shares < EXACT_SYMMETRY_SHARE
    assert near.sum() >= 1 and (~near).sum() == 1  # the half turn about the long axis keeps the hole
    assert np.all(found.shares[near] >= 0.6)
    for S in found.rotations[near]:
        assert S @ [0.02, 0, 0] == pytest.approx([-0.02, 0, 0], abs=2e-3)  # the twin has the hole at the other end


def test_a_disc_with_a_bolt_circle_turns_exactly_by_its_holes():
    """Six holes make the disc's axis a near continuous symmetry, and its turns by 60
    degrees exact ones (a flange: the estimator's poses turned so are right)."""
    parts = [prism(circle(0.045), 0.01, smooth=True)]
    for k in range(6):
        angle = k * np.pi / 3
        parts.append(prism(circle(0.004, 24) + 0.034 * np.array([np.cos(angle), np.sin(angle)]), 0.01, smooth=True))
    edges = np.concatenate([e for e, _ in parts])
    offsets = np.cumsum([0] + [len(v) for _, (v, _) in parts])
    surface = (np.concatenate([v for _, (v, _) in parts]),
               np.concatenate([tri + offset for (_, (_, tri)), offset in zip(parts, offsets)]))
    found = detect(edges, surface)
    assert len(found.axis_shares) == 1 and found.axis_shares[0] < EXACT_SYMMETRY_SHARE
    turns = sorted(round(angle_of(S)) for S in found.rotations[exact(found)] if abs(S[2, 2]) > 0.999)
    assert {60, 120, 180} <= set(turns)


def test_near_turns_that_an_exact_turn_makes_one_map_are_kept_once():
    """A square plate with two holes on one line turns exactly by a half turn about its
    normal and nearly by a quarter turn (the holes move): the quarter turns either way are
    one map of the part under the half turn (the screw's rolls), so only one is kept, and no
    two near symmetries kept differ by an exact one."""
    parts = [prism(rectangle(0.06, 0.06), 0.01)]
    parts += [prism(rectangle(0.008, 0.008) + [x, 0.0], 0.01) for x in (-0.02, 0.02)]
    edges = np.concatenate([e for e, _ in parts])
    offsets = np.cumsum([0] + [len(v) for _, (v, _) in parts])
    surface = (np.concatenate([v for _, (v, _) in parts]),
               np.concatenate([tri + offset for (_, (_, tri)), offset in zip(parts, offsets)]))
    found = detect(edges, surface)
    exact_turns = [np.eye(3), *found.rotations[exact(found)]]
    about_normal = [S for S in found.rotations[~exact(found)] if abs(S[2, 2]) > 0.999]
    assert any(abs(angle_of(S) - 180) < 3 and abs(S[2, 2]) > 0.999 for S in exact_turns[1:])
    assert sum(abs(angle_of(S) - 90) < 3 for S in about_normal) == 1
    near = found.rotations[~exact(found)]
    for a in range(len(near)):
        for b in range(a + 1, len(near)):
            assert min(rotation_angle_deg(E @ near[a], near[b]) for E in exact_turns) > 3.0


def test_outlines_do_not_count_and_a_part_without_edges_or_surface_has_none():
    edges, _ = prism(rectangle(0.06, 0.04), 0.025)
    found = detect_symmetries(edges, np.full(len(edges), OUTLINE, np.uint8), 0.08, None)
    assert len(found.shares) == 0 and len(found.axis_shares) == 0


# ----------------------------------------------------------------------------- the graph file

def graph_with(symmetries=None, **arrays) -> AspectGraph:
    """A one-view graph of a box 60 x 40 x 25 mm with the box's half turns (or the given ones)."""
    edges, _ = prism(rectangle(0.06, 0.04), 0.025, views=1)
    rotation = look_at_rotation(np.array([0.0, 0.0, -1.0]))
    xy = np.einsum("ij,skj->ski", rotation[:2], edges)
    turns = np.array([rotation_about(np.eye(3)[i], np.pi) for i in range(3)])
    fields = dict(symmetry_rotations=turns, symmetry_translations=np.zeros((3, 3)),
                  symmetry_shares=np.ones(3), symmetry_axes=np.zeros((0, 2, 3)), symmetry_axis_shares=np.zeros(0))
    fields.update(symmetries or {})
    fields.update(arrays)
    return AspectGraph(step_sha256="0" * 64, params={}, model_center=np.zeros(3), model_diameter=0.0763, n_faces=6,
                       view_directions=np.array([[0.0, 0.0, -1.0]]), view_rotations=rotation[None],
                       seg_offsets=np.array([0, len(edges)]), seg_xy=xy.astype(np.float32),
                       xy_origin=np.zeros((1, 2)), xy_scale=np.ones(1), seg_3d=edges,
                       seg_kind=np.zeros(len(edges), np.uint8), **fields)


def test_symmetries_survive_the_file(tmp_path):
    graph = graph_with()
    loaded = AspectGraph.load(graph.save(tmp_path / "box.brepose.npz"))
    assert np.array_equal(loaded.symmetry_rotations, graph.symmetry_rotations)
    assert loaded.exact_symmetries.all()


@pytest.mark.parametrize("arrays, message", [
    (dict(symmetry_rotations=np.tile(2 * np.eye(3), (3, 1, 1))), "not a rotation"),
    (dict(symmetry_rotations=np.tile(np.diag([1.0, 1.0, -1.0]), (3, 1, 1))), "not a rotation"),
    (dict(symmetry_shares=np.array([1.0, 1.0, 1.5])), "share outside"),
    (dict(symmetry_axes=np.array([[[0, 0, 0], [0, 0, 2.0]]]), symmetry_axis_shares=np.ones(1)), "not a unit"),
    (dict(symmetry_shares=np.ones(2)), "symmetry_rotations has dtype"),
    (dict(symmetry_translations=np.full((3, 3), np.nan)), "NaN"),
], ids=["scaled", "mirror", "share", "axis", "shape", "nan"])
def test_tampered_symmetries_are_refused(tmp_path, arrays, message):
    path = graph_with(**arrays).save(tmp_path / "bad.brepose.npz")  # a consistent digest: only the checks
    with pytest.raises(AspectGraphError, match=message):
        AspectGraph.load(path)


def test_a_format_2_file_is_refused_with_a_recompile_message(tmp_path):
    path = graph_with().save(tmp_path / "box.brepose.npz")
    with zipfile.ZipFile(path) as archive:
        entries = {name: archive.read(name) for name in archive.namelist()}
    metadata = np.load(path)["metadata"]
    meta = json.loads(str(metadata))
    meta["format_version"] = 2
    old = tmp_path / "old.brepose.npz"
    np.savez(old, **{k[:-4]: np.load(path)[k[:-4]] for k in entries if k != "metadata.npy"},
             metadata=np.array(json.dumps(meta)))
    with pytest.raises(AspectGraphError, match="older.*recompile"):
        AspectGraph.load(old)


# ----------------------------------------------------------------------------- evaluation

def test_a_pose_turned_by_an_exact_symmetry_has_no_symmetric_error():
    graph = graph_with()
    model = ModelPoints(np.array([[x, y, z] for x in (-0.03, 0.03) for y in (-0.02, 0.02) for z in (-0.0125, 0.0125)]))
    R, t = look_at_rotation(np.array([0.3, -0.2, -1.0])), np.array([0.01, 0.0, 0.4])
    R_twin, t_twin = graph.symmetric_poses(R, t, [1])
    errors = pose_errors(R_twin[0], t_twin[0], R, t, model, graph)
    assert errors.rotation_deg == pytest.approx(180) and not errors.success
    assert errors.rotation_sym_deg < 1e-6 and errors.translation_sym_mm < 1e-6 and errors.success_sym
    assert errors.add_s < 1e-9
    plain = pose_errors(R_twin[0], t_twin[0], R, t, model)
    assert plain.rotation_sym_deg == pytest.approx(180)  # without the graph: no symmetry


def test_a_turn_about_a_continuous_axis_off_the_origin_costs_nothing():
    point = np.array([0.01, 0.02, 0.0])
    graph = graph_with(symmetry_rotations=np.zeros((0, 3, 3)), symmetry_translations=np.zeros((0, 3)),
                       symmetry_shares=np.zeros(0), symmetry_axes=np.array([[point, [0.0, 0.0, 1.0]]]),
                       symmetry_axis_shares=np.ones(1))
    model = ModelPoints(point + np.random.default_rng(0).normal(size=(50, 3)) * [0.02, 0.02, 0.05])
    R, t = look_at_rotation(np.array([0.5, 0.2, -1.0])), np.array([0.0, 0.01, 0.3])
    turn = rotation_about(np.array([0.0, 0.0, 1.0]), np.radians(37))
    R_est, t_est = R @ turn, t + R @ (point - turn @ point)  # the part turned 37 degrees about the axis
    errors = pose_errors(R_est, t_est, R, t, model, graph)
    assert errors.rotation_deg == pytest.approx(37)
    assert errors.rotation_sym_deg < 1e-6 and errors.translation_sym_mm < 1e-6
    tilted = R_est @ rotation_about(np.array([1.0, 0.0, 0.0]), np.radians(4))
    assert pose_errors(tilted, t_est, R, t, model, graph).rotation_sym_deg == pytest.approx(4, abs=1e-6)


def test_a_nearly_rotational_part_is_checked_against_its_end_over_end_twins():
    """``end_over_end``: a shaft of radius 10 and length 70 mm whose axis is a near continuous
    symmetry through a point off the origin (a flat or a chamfer at one end breaks it). Seen
    from the side, each twin turns the part half round about an axis across its own, through
    that point: the point projects where it did, each end's ring is drawn on the other's (the
    outline of a body of revolution, to 0.05 px), and what was at one end (the chamfer) is now
    at the other. The first turns about the axis square to the line of sight, the others every
    180 / ``ACROSS_DIRECTIONS`` degrees on. Seen along the axis, or with the axis an exact
    symmetry (a plain cylinder), there is no twin."""
    from brepose_ros.camera import Camera
    from brepose_ros.online.symmetry import ACROSS_DIRECTIONS, end_over_end

    point, axis = np.array([0.002, -0.001, 0.003]), np.array([0.0, 0.0, 1.0])

    def ring(n):
        return np.array([[10 * np.cos(a), 10 * np.sin(a), 0.0] for a in np.linspace(0, 2 * np.pi, n)]) / 1000

    ends = [ring(73) + point + [0, 0, z] for z in (-0.035, 0.035)]
    dense = [ring(7201) + point + [0, 0, z] for z in (-0.035, 0.035)]  # the rings as curves, to 0.01 mm
    graph = graph_with(no_turns(), symmetry_axes=np.array([[point, axis]]), symmetry_axis_shares=np.array([0.63]))
    camera = Camera(fx=600.0, fy=600.0, cx=320.0, cy=240.0, width=640, height=480)
    R, t = look_at_rotation(np.array([1.0, 0.4, -0.3])), np.array([0.01, -0.005, 0.25])
    R_twins, t_twins, axis_of, keeps_outline = end_over_end(graph, R, t)
    assert len(R_twins) == ACROSS_DIRECTIONS and (axis_of == 0).all()
    assert np.flatnonzero(keeps_outline).tolist() == [0, ACROSS_DIRECTIONS // 2]
    sight = R.T @ (R @ graph.model_center + t)
    for R_twin, t_twin in zip(R_twins, t_twins):
        assert rotation_angle_deg(R_twin, R) == pytest.approx(180.0)
        turn_axis = np.linalg.eigh(R.T @ R_twin + R_twin.T @ R)[1][:, -1]  # the half turn's axis, model frame
        assert abs(turn_axis @ axis) < 1e-9
        assert np.allclose(R_twin @ point + t_twin, R @ point + t)
        shown = [camera.project_model(ring_points, R_twin, t_twin) for ring_points in ends]
        seen = [camera.project_model(ring_points, R, t) for ring_points in dense]
        for end, other in ((0, 1), (1, 0)):  # each end's ring drawn on the other's
            gaps = np.linalg.norm(shown[end][:, None] - seen[other][None], axis=2).min(axis=1)
            assert gaps.max() < 0.05
        # the chamfer's centre now where the other end's is
        assert np.allclose(R_twin @ (point + [0, 0, 0.035]) + t_twin, R @ (point - [0, 0, 0.035]) + t)
    across = np.array([np.linalg.eigh(R.T @ R_k + R_k.T @ R)[1][:, -1] for R_k in R_twins])
    assert abs(across[0] @ sight) < 1e-9 * np.linalg.norm(sight)  # square to the line of sight
    steps = np.degrees(np.arccos(np.clip(np.abs(np.sum(across[1:] * across[:-1], axis=1)), 0, 1)))
    assert steps == pytest.approx(np.full(ACROSS_DIRECTIONS - 1, 180.0 / ACROSS_DIRECTIONS), abs=1e-6)
    along = look_at_rotation(-axis)  # the camera looks down the axis at the part's centre
    assert len(end_over_end(graph, along, np.array([0.0, 0.0, 0.25]))[0]) == 0
    exact = graph_with(symmetry_axes=np.array([[point, axis]]), symmetry_axis_shares=np.ones(1))
    assert len(end_over_end(exact, R, t)[0]) == 0



def test_a_climbed_end_over_end_twin_is_rolled_to_the_best_scoring_of_a_few_turns_about_the_axis(monkeypatch):
    """``rolled``: the twin turned about the near axis through its point (off the origin) by
    each of ``ROLL_STEPS_DEG``; the best-scoring one replaces the twin only if it scores more.
    A score that peaks at the roll 4 degrees back brings the twin there, the axis's point
    staying where the twin shows it; a score that peaks at the twin itself keeps it."""
    from brepose_ros.online import symmetry
    from brepose_ros.online.refinement import Candidate

    point, axis = np.array([0.002, -0.001, 0.003]), np.array([0.0, 0.6, 0.8])
    R_true, t = look_at_rotation(np.array([1.0, 0.4, -0.3])), np.array([0.01, -0.005, 0.25])
    off = rotation_about(axis, np.radians(4.0))  # the twin's part turned 4 degrees too far about the axis
    R_twin = R_true @ off.T
    twin = Candidate(0.5, R_twin, t - R_twin @ (point - off @ point), None)

    def peaked(graph, R, t, frame, p):  # the score falls off with the angle from the true rotation
        return np.array([0.7 - 0.01 * rotation_angle_deg(R_k, R_true) for R_k in R])

    monkeypatch.setattr(symmetry, "pose_scores", peaked)
    kept = symmetry.rolled(twin, point, axis, graph_with(), None, None)
    assert rotation_angle_deg(kept.R, R_true) < 1e-4 and kept.score == pytest.approx(0.7)
    assert np.allclose(kept.R @ point + kept.t, twin.R @ point + twin.t)  # turned about the axis's line
    assert np.allclose(kept.t, t)
    assert symmetry.rolled(Candidate(0.75, R_twin, twin.t, None), point, axis, graph_with(), None, None).score == 0.75



def test_the_end_over_end_twins_that_climb_are_the_best_two_still_turned_and_the_outline_keepers(monkeypatch):
    """``check_twins``: of the refined end-over-end twins, the two best-scoring ones whose axis
    still points against the pose's climb, besides the two that keep the outline (square to
    the line of sight and nearest it); one refined back to the pose's end (its axis pointing
    the pose's way) takes no climb however well it scores."""
    from brepose_ros.online import symmetry
    from brepose_ros.online.refinement import Candidate
    from brepose_ros.params import EstimatorParams

    point, axis = np.array([0.002, -0.001, 0.003]), np.array([0.0, 0.0, 1.0])
    graph = graph_with(no_turns(), symmetry_axes=np.array([[point, axis]]), symmetry_axis_shares=np.array([0.63]))
    best = Candidate(0.7, look_at_rotation(np.array([1.0, 0.4, -0.3])), np.array([0.01, -0.005, 0.25]), None)
    scores = np.full(symmetry.ACROSS_DIRECTIONS, 0.1)
    scores[[3, 5, 8]] = 0.9, 0.8, 0.7

    class Refiner:  # each twin refined where it started, but twin 3 back onto the pose
        def refined_scores(self, R, t, frame, p, rounds, pool, align):
            R, t = R.copy(), t.copy()
            R[3], t[3] = best.R, best.t
            return R, t, scores

        def climb_together(self, starts, frame, p, pool, each_alone):
            return list(starts)

        def polished(self, chosen, frame, p, pool):
            return chosen

        def refine(self, R, t, frame, p, rounds):
            return R, t

    compared = []

    def pick(pose, twins, *rest):  # the poses the check compares, the pose kept
        compared.extend(twins)
        return symmetry.Verdict(pose, 1.0)

    monkeypatch.setattr(symmetry, "pose_scores", lambda graph, R, t, frame, p: np.zeros(len(R)))
    monkeypatch.setattr(symmetry, "pick_by_evidence", pick)
    assert symmetry.check_twins(best, graph, Refiner(), None, EstimatorParams().pose) == (best, 1.0, False)
    R_twins, _, _, _ = symmetry.end_over_end(graph, best.R, best.t)
    climbed = [int(np.argmin([rotation_angle_deg(c.R, R_k) for R_k in R_twins])) for c in compared]
    assert sorted(climbed) == [0, 5, symmetry.ACROSS_DIRECTIONS // 2, 8]


def no_turns() -> dict:
    """``graph_with``'s symmetries for a part without discrete ones."""
    return dict(symmetry_rotations=np.zeros((0, 3, 3)), symmetry_translations=np.zeros((0, 3)),
                symmetry_shares=np.zeros(0))


@pytest.mark.parametrize("order, distinct", [(6, 2), (2, 6), (4, 3), (5, 12)])
def test_end_over_end_twins_that_an_exact_turn_makes_one_pose_are_tried_once(order, distinct):
    """Two half turns across an axis differ by a turn about it of twice the angle between
    them: where that turn is an exact symmetry (a flange's bolt circle turned by a sixth, a
    slotted screw's half turn), the two twins are one pose of the part and only the first is
    refined. With exact turns by 1/``order`` about the axis, the 15-degree directions give
    2 twins (six-fold: directions 30 degrees apart differ by a sixth), 6 (a half turn), 3
    (four-fold) or, for a five-fold turn that no multiple of 30 degrees reaches, all 12. No
    exact turn maps one kept twin onto another (the five-fold turns come within 6 degrees
    of some); the twin square to the line of sight keeps the outline, and so does the one
    nearest it, for even orders the same pose as the first."""
    from brepose_ros.online.symmetry import ACROSS_DIRECTIONS, end_over_end

    point, axis = np.array([0.002, -0.001, 0.003]), np.array([0.0, 0.0, 1.0])
    turns = np.array([rotation_about(axis, 2 * np.pi * k / order) for k in range(1, order)])
    graph = graph_with(symmetry_rotations=turns, symmetry_translations=point - turns @ point,
                       symmetry_shares=np.full(order - 1, 0.98), symmetry_axes=np.array([[point, axis]]),
                       symmetry_axis_shares=np.array([0.6]))
    R, t = look_at_rotation(np.array([1.0, 0.4, -0.3])), np.array([0.01, -0.005, 0.25])
    R_twins, t_twins, axis_of, keeps_outline = end_over_end(graph, R, t)
    assert len(R_twins) == distinct
    everything = end_over_end(graph_with(no_turns(), symmetry_axes=graph.symmetry_axes,
                                         symmetry_axis_shares=graph.symmetry_axis_shares), R, t)
    assert len(everything[0]) == ACROSS_DIRECTIONS
    assert np.allclose(R_twins[0], everything[0][0]) and np.allclose(t_twins[0], everything[1][0])
    for a in range(len(R_twins)):  # model frame: what turns twin a's part into twin b's
        for b in range(a + 1, len(R_twins)):
            between = R_twins[a].T @ R_twins[b]
            assert min(rotation_angle_deg(between, S) for S in [np.eye(3), *turns]) > 5.0
    assert keeps_outline[0] and keeps_outline.sum() == (1 if order % 2 == 0 else 2)


# ----------------------------------------------------------------------------- run time

def test_a_pose_that_loses_on_evidence_to_one_twin_does_not_win_on_noise_over_another(monkeypatch):
    """``pick_by_evidence``: the pose (a few degrees off) shows clearly less than twin A on
    the edges that tell them apart; A and twin B tie there, and the pose and B cannot be told
    apart (B scores 0.005 below the pose). The pose stands down, and of A and B the better
    whole score, B, is kept, as ambiguous and tied with the pose: the pose's lead of pixel
    noise over B must not let A win (the notched plate's clutter 6 on the bench)."""
    from brepose_ros.online import symmetry
    from brepose_ros.online.refinement import Candidate
    from brepose_ros.params import PoseParams

    near_box = graph_with(symmetry_shares=np.full(3, 0.7))  # its half turns near, not exact
    R = look_at_rotation(np.array([0.3, -0.2, -1.0]))
    pose = Candidate(0.719, R, np.array([0.0, 0.0, 0.4]), None)
    twin_a = Candidate(0.668, R @ rotation_about(np.array([1.0, 0.0, 0.0]), np.pi), pose.t, None)
    twin_b = Candidate(0.714, R @ rotation_about(np.array([0.0, 1.0, 0.0]), np.pi), pose.t, None)
    evidence = {(0.719, 0.668): (0.425, True), (0.719, 0.714): (-0.005, False), (0.668, 0.714): (0.0, True)}
    monkeypatch.setattr(symmetry, "twin_evidence", lambda graph, a, b, frame, p: evidence[(a.score, b.score)])
    kept, margin, tied = symmetry.pick_by_evidence(pose, [twin_a, twin_b], near_box, None, PoseParams())
    assert kept is twin_b and margin == 0.0 and tied
    # where A also shows more than B, A is kept, its smallest gain the margin; nothing ties with it
    evidence[(0.668, 0.714)] = (-0.3, True)
    kept, margin, tied = symmetry.pick_by_evidence(pose, [twin_a, twin_b], near_box, None, PoseParams())
    assert kept is twin_a and margin == pytest.approx(0.3) and not tied
    # where the image tells none apart, a rival displaces the pose only by a clear whole score
    evidence.update({key: (0.0, False) for key in evidence})
    assert symmetry.pick_by_evidence(pose, [twin_a, twin_b], near_box, None, PoseParams())[0] is pose
    higher = Candidate(0.719 + 2.5 * symmetry.MIN_GAIN, twin_b.R, twin_b.t, None)
    evidence[(0.719, higher.score)] = (0.0, False)
    evidence[(0.668, higher.score)] = (0.0, False)
    assert symmetry.pick_by_evidence(pose, [twin_a, higher], near_box, None, PoseParams())[0] is higher


def test_a_twin_below_the_found_floor_still_makes_the_pose_ambiguous(monkeypatch):
    """``pick_by_evidence``: a twin scoring under ``pose.min_score`` but from ``RIVAL_FLOOR`` on
    is a rival (the confidence's twin features were recorded so); the image cannot tell it
    from the pose, so the pose is kept with margin 0 (ambiguous), but the whole scores chose
    clearly: no tie. Below the rival floor a twin is none: margin 1."""
    from brepose_ros.online import symmetry
    from brepose_ros.online.refinement import Candidate
    from brepose_ros.params import PoseParams

    p = PoseParams()
    near_box = graph_with(symmetry_shares=np.full(3, 0.7))
    R = look_at_rotation(np.array([0.3, -0.2, -1.0]))
    pose = Candidate(0.7, R, np.array([0.0, 0.0, 0.4]), None)
    flip = R @ rotation_about(np.array([1.0, 0.0, 0.0]), np.pi)
    monkeypatch.setattr(symmetry, "twin_evidence", lambda graph, a, b, frame, p: (0.0, False))
    below_found = Candidate((symmetry.RIVAL_FLOOR + p.min_score) / 2, flip, pose.t, None)
    assert symmetry.RIVAL_FLOOR < below_found.score < p.min_score
    assert symmetry.pick_by_evidence(pose, [below_found], near_box, None, p) == (pose, 0.0, False)
    below_rivals = Candidate(symmetry.RIVAL_FLOOR - 0.01, flip, pose.t, None)
    assert symmetry.pick_by_evidence(pose, [below_rivals], near_box, None, p) == (pose, 1.0, False)

def test_twins_that_an_exact_symmetry_makes_one_pose_are_one_rival(monkeypatch):
    """``pick_by_evidence``: a part turning exactly by a half turn about z and nearly by a
    quarter turn has the quarter turns either way as one twin (the screw's rolls, the flange's
    under its sixths). Both refined, the second is the first's copy, not a rival: the image
    cannot tell them apart, and as a rival it would zero the winner's margin. The pose's own
    exact twin is no rival either."""
    from brepose_ros.online import symmetry
    from brepose_ros.online.refinement import Candidate
    from brepose_ros.params import PoseParams

    z = np.array([0.0, 0.0, 1.0])
    turns = np.array([rotation_about(z, angle) for angle in (np.pi, np.pi / 2, -np.pi / 2)])
    graph = graph_with(symmetry_rotations=turns, symmetry_translations=np.zeros((3, 3)),
                       symmetry_shares=np.array([0.99, 0.7, 0.7]))
    R, t = look_at_rotation(np.array([0.3, -0.2, -1.0])), np.array([0.0, 0.0, 0.4])
    pose = Candidate(0.75, R, t, None)
    (R_plus, R_minus, R_half), (t_plus, t_minus, t_half) = graph.symmetric_poses(R, t, [1, 2, 0])
    plus, minus = Candidate(0.70, R_plus, t_plus, None), Candidate(0.70, R_minus, t_minus, None)
    assert symmetry.same_pose(graph, R_plus, t_plus, R_minus, t_minus)
    assert symmetry.same_pose(graph, R, t, R_half, t_half)
    assert not symmetry.same_pose(graph, R, t, R_plus, t_plus)
    asked = []

    def evidence(graph, a, b, frame, p):
        asked.append((a.score, b.score))
        return -0.4, True  # the twin shows clearly less than the pose

    monkeypatch.setattr(symmetry, "twin_evidence", evidence)
    kept, margin, tied = symmetry.pick_by_evidence(pose, [plus, minus, Candidate(0.74, R_half, t_half, None)],
                                                   graph, None, PoseParams())
    assert kept is pose and margin == pytest.approx(0.4) and not tied and len(asked) == 1
    # where the graph holds the half turn as a near symmetry too, the three are rivals
    near = graph_with(symmetry_rotations=turns, symmetry_translations=np.zeros((3, 3)),
                      symmetry_shares=np.full(3, 0.7))
    assert not symmetry.same_pose(near, R_plus, t_plus, R_minus, t_minus)


def test_poses_turned_about_an_exact_axis_off_the_origin_are_one_pose():
    """``same_pose`` on a part turning exactly about an axis through (0.01, 0, 0) along z (a
    plain cylinder): the pose turned about that line by any angle is the same pose; turned
    about a parallel line through the origin, or tilted, it is not."""
    from brepose_ros.geometry import turned_poses
    from brepose_ros.online.symmetry import same_pose

    point, axis = np.array([0.01, 0.0, 0.0]), np.array([0.0, 0.0, 1.0])
    graph = graph_with(no_turns(), symmetry_axes=np.array([[point, axis]]), symmetry_axis_shares=np.array([0.99]))
    R, t = look_at_rotation(np.array([0.3, -0.2, -1.0])), np.array([0.0, 0.0, 0.4])
    for angle in (0.3, 2.0, np.pi):
        turn = rotation_about(axis, angle)[None]
        (R_line,), (t_line,) = turned_poses(R, t, turn, (point - turn @ point))
        assert same_pose(graph, R, t, R_line, t_line)
        (R_origin,), (t_origin,) = turned_poses(R, t, turn, np.zeros((1, 3)))
        assert not same_pose(graph, R, t, R_origin, t_origin)  # the axis line lands elsewhere
    tilt = R @ rotation_about(np.array([1.0, 0.0, 0.0]), np.radians(10.0)).T
    assert not same_pose(graph, R, t, tilt, t)


def test_a_pose_whose_small_rolls_score_alike_is_tied(monkeypatch):
    """``roll_tied``: about a near continuous axis the pose is scored turned by
    ``ROLL_TIE_DEG`` about the axis line; a roll scoring within both scores' noise of the pose
    (``2 * MIN_GAIN``) or above ties it (its confidence then a coin toss), a clear drop at every
    roll does not; a part with an exact axis or none is never tied so."""
    from brepose_ros.geometry import rotation_about
    from brepose_ros.online import symmetry
    from brepose_ros.online.refinement import Candidate

    point, axis = np.array([0.01, 0.0, 0.0]), np.array([0.0, 0.0, 1.0])
    near = graph_with(no_turns(), symmetry_axes=np.array([[point, axis]]), symmetry_axis_shares=np.array([0.6]))
    pose = Candidate(0.8, look_at_rotation(np.array([0.3, -0.2, -1.0])), np.array([0.0, 0.0, 0.4]), None)
    drop = {"by": 0.1}

    def scores(graph, R, t, frame, p):
        for R_k, t_k, angle in zip(R, t, symmetry.ROLL_TIE_DEG):  # turned about the axis line
            turn = rotation_about(axis, np.radians(angle))
            assert np.allclose(R_k, pose.R @ turn.T) and np.allclose(R_k @ point + t_k, pose.R @ point + pose.t)
        return np.full(len(R), pose.score - drop["by"])

    monkeypatch.setattr(symmetry, "pose_scores", scores)
    assert not symmetry.roll_tied(pose, near, None, None)
    drop["by"] = 1.9 * symmetry.MIN_GAIN
    assert symmetry.roll_tied(pose, near, None, None)
    exact = graph_with(no_turns(), symmetry_axes=near.symmetry_axes, symmetry_axis_shares=np.array([0.99]))
    assert not symmetry.roll_tied(pose, exact, None, None)
    assert not symmetry.roll_tied(pose, graph_with(no_turns()), None, None)


@pytest.fixture(scope="module")
def plate_graph(builtin_step):
    """The notched plate's graph at 15 degrees, and its STEP file."""
    from brepose_ros.offline.compiler import compile_aspect_graph

    step = builtin_step("notched_plate")
    return compile_aspect_graph(step, step_deg=15.0, workers=2, progress=False), step


def plate_image(step, hide_features: bool = False):
    """The notched plate seen from above its notched face, 230 mm away (the notch about
    20 x 15 px), and its pose; with ``hide_features`` the notch and the three places where a
    twin would have it are painted over with the plate's own grey."""
    from brepose_ros.camera import Camera
    from brepose_ros.offline.cad import load_step, tessellate
    from brepose_ros.synthetic.render import Placed, render

    camera = Camera(fx=600.0, fy=600.0, cx=320.0, cy=240.0, width=640, height=480)
    R = look_at_rotation(np.array([0.25, 0.35, -1.0]))
    t = np.array([0.005, -0.01, 0.23])
    image = render(camera, [Placed(tessellate(load_step(step)), R, t)], background=40.0).image
    if hide_features:
        plate = float(np.median(image[image > 60]))
        for x, y in ((0.020, 0.030), (-0.020, -0.030), (0.020, -0.030), (-0.020, 0.030)):
            u, v = camera.project_model(np.array([x, y, 0.004]), R, t)
            cv2.circle(image, (int(round(u)), int(round(v))), 24, plate, -1)
    return image, camera, R, t


def twin_check(graph, image, camera, R, t):
    """``check_twins`` from pose R, t on the image: the pose kept, its margin, and whether
    the estimator would call it ambiguous."""
    from brepose_ros.online.frame import Frame
    from brepose_ros.online.image_edges import detect_edges
    from brepose_ros.online.refinement import Candidate, PoseRefiner
    from brepose_ros.online.scoring import pose_scores
    from brepose_ros.online.symmetry import check_twins
    from brepose_ros.params import EstimatorParams

    p = EstimatorParams()
    frame = Frame.of(detect_edges(image, p.edges), camera)
    score = float(pose_scores(graph, R[None], t[None], frame, p.pose)[0])
    kept, margin, _ = check_twins(Candidate(score, R, t, None), graph, PoseRefiner(graph), frame, p.pose)
    return kept, margin, margin < p.pose.twin_margin


@pytest.mark.slow
def test_the_notched_plate_comes_out_the_right_way_round_when_its_notch_shows(plate_graph):
    graph, step = plate_graph
    near = np.nonzero(~graph.exact_symmetries)[0]
    assert len(near) >= 1 and graph.exact_symmetries.sum() == 0  # the notch breaks all three half turns
    image, camera, R, t = plate_image(step)
    kept, margin, ambiguous = twin_check(graph, image, camera, R, t)
    assert rotation_angle_deg(kept.R, R) < 3.0 and not ambiguous
    for R_twin, t_twin in zip(*graph.symmetric_poses(R, t, near)):  # each flipped start turns back
        kept, margin, ambiguous = twin_check(graph, image, camera, R_twin, t_twin)
        assert rotation_angle_deg(kept.R, R) < 3.0 and not ambiguous


@pytest.mark.slow
def test_the_notched_plate_is_reported_ambiguous_when_its_notch_is_hidden(plate_graph):
    graph, step = plate_graph
    image, camera, R, t = plate_image(step, hide_features=True)
    kept, margin, ambiguous = twin_check(graph, image, camera, R, t)
    assert ambiguous and margin < 0.1


@pytest.mark.slow
def test_a_near_tie_between_finalists_goes_to_the_pose_its_distinguishing_edges_show(plate_graph):
    """``check_rivals``: each twin of the notched plate (its notch where the plate has none),
    given a score a little above the truth's, loses to the truth on the notch, and never
    displaces a truth that scores a little above it; a twin scoring more than
    ``RIVAL_SCORE_GAP`` above the truth is not compared and stays first, and neither is a
    pose at another place (``RIVAL_PLACE``), however little the image shows of it."""
    from brepose_ros.online.frame import Frame
    from brepose_ros.online.image_edges import detect_edges
    from brepose_ros.online.refinement import Candidate
    from brepose_ros.online.scoring import pose_scores
    from brepose_ros.online.symmetry import RIVAL_SCORE_GAP, check_rivals
    from brepose_ros.params import EstimatorParams

    graph, step = plate_graph
    image, camera, R, t = plate_image(step)
    p = EstimatorParams()
    frame = Frame.of(detect_edges(image, p.edges), camera)
    score = float(pose_scores(graph, R[None], t[None], frame, p.pose)[0])
    assert score >= p.pose.min_score + 0.05
    near = np.nonzero(~graph.exact_symmetries)[0]
    for R_twin, t_twin in zip(*graph.symmetric_poses(R, t, near)):
        truth, twin = Candidate(score, R, t, None), Candidate(score + 0.02, R_twin, t_twin, None)
        assert check_rivals([twin, truth], graph, frame, p.pose) is truth
        ahead = Candidate(score + 0.02, R, t, None)
        assert check_rivals([ahead, Candidate(score, R_twin, t_twin, None)], graph, frame, p.pose) is ahead
        far = Candidate(score + RIVAL_SCORE_GAP + 0.01, R_twin, t_twin, None)
        assert check_rivals([far, truth], graph, frame, p.pose) is far
    elsewhere = Candidate(score + 0.02, R, t + np.array([0.1, 0.0, 0.0]), None)  # about 260 px aside, off the plate
    assert check_rivals([elsewhere, Candidate(score, R, t, None)], graph, frame, p.pose) is elsewhere


@pytest.mark.slow
def test_a_pose_too_far_anchored_at_a_corner_of_the_rendered_plate_runs_on_and_the_truth_does_not(plate_graph):
    """The score's run-on (``Shares.run_on``) on the rendered notched plate: the model 1.5x as
    far, placed so that an outer corner of the plate projects where it truly is (its edges
    from there lie on pieces of the plate's), finds the plate's edges running on past its
    model edges' ends; the truth finds none, and neither does the model 1.5x as near there
    (too large: its edges run past the plate's, which the confirmed share sees)."""
    from brepose_ros.online.frame import Frame
    from brepose_ros.online.image_edges import detect_edges
    from brepose_ros.online.scoring import pose_shares
    from brepose_ros.params import EstimatorParams

    graph, step = plate_graph
    image, camera, R, t = plate_image(step)
    p = EstimatorParams()
    frame = Frame.of(detect_edges(image, p.edges), camera)
    truth = pose_shares(graph, R, t, frame, p.pose)[0]
    assert truth.run_on < 0.01 and truth.score > 0.9
    ends = graph.seg_3d[graph.visible_segments(R, t)].reshape(-1, 3)
    centre = camera.project_model(graph.model_center[None], R, t)[0]
    corner = ends[np.argmax(np.linalg.norm(camera.project_model(ends, R, t) - centre, axis=1))]
    far, near = (pose_shares(graph, R, f * (R @ corner + t) - R @ corner, frame, p.pose)[0] for f in (1.5, 1 / 1.5))
    assert far.run_on > 0.08 and far.score < truth.score - 0.5
    assert near.run_on < 0.01


def test_an_ambiguous_pose_says_so_in_the_overlay_caption():
    from brepose_ros.evaluation.overlay import caption
    from brepose_ros.online.estimator import Estimate

    estimate = Estimate(found=True, R=np.eye(3), t=np.array([0.0, 0.0, 0.3]), score=0.9, error_ratio=0.1,
                        view_index=0, n_image_segments=10, n_matched=5, n_nearest=4, symmetry_margin=0.05,
                        ambiguous=True)
    assert "ambiguous (twin margin 0.05)" in caption(estimate)
    assert "ambiguous" not in caption(dataclasses.replace(estimate, symmetry_margin=0.6, ambiguous=False))
