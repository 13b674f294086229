"""brepose-learn (the seed paper's learning mechanism) and the parameter files it writes."""
from __future__ import annotations

import zlib
from pathlib import Path

import numpy as np
import pytest

from brepose_ros.evaluation.learning import (HELD_OUT_MARGIN, SEARCH_SPACE, Score, choose, learn, search_space,
                                             symmetric_errors, symmetry_rotations, write_trials)
from brepose_ros.evaluation.metrics import ModelPoints, mean_error_rate, pose_errors
from brepose_ros.geometry import rot_z
from brepose_ros.params import EstimatorParams, field_ranges

CONFIG = Path(__file__).resolve().parents[1] / "config"
CUBE = ModelPoints(np.array([[x, y, z] for x in (-0.02, 0.02) for y in (-0.02, 0.02) for z in (-0.02, 0.02)]))


def test_every_searched_parameter_exists_and_its_range_is_allowed():
    ranges, defaults = field_ranges(), EstimatorParams().flat()
    assert search_space() == list(SEARCH_SPACE)
    for knob in SEARCH_SPACE:
        low, high = ranges[knob.name]
        assert low <= knob.low < knob.high <= high, knob
        assert knob.low <= defaults[knob.name] <= knob.high, f"{knob.name}: the default is the first trial"


def test_training_shapes_have_their_symmetries():
    assert len(symmetry_rotations("cube")) == 24 and len(symmetry_rotations("box")) == 4
    assert len(symmetry_rotations("sharp_bracket")) == 1
    for shape in ("cube", "box", "cylinder"):
        rotations = symmetry_rotations(shape)
        assert np.allclose(rotations @ rotations.transpose(0, 2, 1), np.eye(3)) and np.allclose(
            np.linalg.det(rotations), 1.0)


def test_a_cube_turned_by_a_quarter_turn_is_the_same_pose():
    t = np.array([0.0, 0.0, 0.4])
    R_gt = np.array([[1.0, 0, 0], [0, 0, -1], [0, 1, 0]])  # the camera sees the cube from its side
    turned = R_gt @ rot_z(np.pi / 2)
    assert pose_errors(turned, t, R_gt, t, CUBE).error_rate == pytest.approx(0.5)
    same = symmetric_errors(turned, t, R_gt, t, CUBE, symmetry_rotations("cube"))
    assert same.success and same.error_rate == pytest.approx(0.0, abs=1e-12)
    off = symmetric_errors(turned @ rot_z(np.radians(10.0)), t, R_gt, t, CUBE, symmetry_rotations("cube"))
    assert off.rotation_deg == pytest.approx(10.0) and not off.success


def test_mean_error_rate_counts_a_missed_part_as_a_guess():
    t = np.array([0.0, 0.0, 0.4])
    right = pose_errors(np.eye(3), t, np.eye(3), t, CUBE)
    assert mean_error_rate([right, None]) == pytest.approx(0.25)


def noisy_objective(effect: float):
    """A synthetic ``learn`` score: a sample is (seed, images); each image is wrong (er 0.8) with
    probability 0.4, less ``effect`` where the empty coefficient exceeds 0.4 (the defaults'
    is 0.25), else right (er 0.01), drawn anew for every parameter set and sample, as the
    estimator's luck on an image changes with any threshold."""
    def score(sample, params: EstimatorParams) -> Score:
        seed, images = sample
        flat = params.flat()  # the searched values only: a parameter added elsewhere changes no draw
        key = zlib.crc32(repr([flat[k.name] for k in SEARCH_SPACE]).encode())
        rng = np.random.default_rng([seed, key])
        wrong = 0.4 - (effect if params.matching.empty_coefficient > 0.4 else 0.0)
        return Score(np.where(rng.random(images) < wrong, 0.8, 0.01), 100.0)
    return score


#: runs of the synthetic search: enough that chance's share of fooled runs is measured, not guessed
RUNS = 60


def test_learning_keeps_the_defaults_when_no_trial_beats_them_on_the_held_out_images():
    pytest.importorskip("optuna")
    kept = looked_better = 0
    for seed in range(RUNS):  # no set is truly better: only chance can pass the held-out margin
        result = learn((seed, 120), (seed + 1000, 120), trials=30, timeout_s=60.0, seed=seed,
                       score=noisy_objective(0.0))
        looked_better += min(r["loss"] for r in result.trials[1:]) < result.trials[0]["loss"] - 0.03
        assert sum(r["held_out_loss"] is not None for r in result.trials) == 4  # the defaults and 3 finalists
        if result.verdict.winner is None:
            assert result.changed == {} and result.params == EstimatorParams()
            assert result.verdict.reason.startswith("defaults kept")
            kept += 1
    assert looked_better >= 0.75 * RUNS  # chosen on the training images alone, most runs would leave the defaults
    # 2 standard errors: about one run in 11 fooled; at 60 runs 48 kept is 3 binomial standard deviations below
    assert kept >= 0.8 * RUNS


def test_learning_chooses_a_clearly_better_set_and_logs_every_trial(tmp_path):
    pytest.importorskip("optuna")
    result = learn((0, 120), (1000, 120), trials=30, timeout_s=60.0, score=noisy_objective(0.3))
    assert result.verdict.winner is not None and result.verdict.reason.startswith("learned")
    assert result.changed["matching.empty_coefficient"] > 0.4
    assert result.chosen["held_out"].error_rate < result.default["held_out"].error_rate - 0.15
    assert len(result.trials) == 31 and [r["trial"] for r in result.trials] == list(range(31))
    log = tmp_path / "learned.trials.csv"
    write_trials(log, result.trials)
    rows = log.read_text().splitlines()
    assert len(rows) == 32 and "matching.empty_coefficient" in rows[0] and "held_out_loss" in rows[0]


def test_a_finalist_must_beat_the_defaults_by_the_margin_on_the_same_images():
    defaults = Score(np.array([0.8] * 20 + [0.0] * 80), 100.0)
    one_better = Score(np.array([0.8] * 19 + [0.0] * 81), 100.0)  # one image of 100 right instead of wrong
    assert choose(defaults, [one_better], budget_ms=150.0).winner is None
    ten_better = Score(np.array([0.8] * 10 + [0.0] * 90), 100.0)
    verdict = choose(defaults, [one_better, ten_better], budget_ms=150.0)
    assert verdict.winner == 1 and verdict.gain == pytest.approx(0.08)
    assert verdict.gain > HELD_OUT_MARGIN * verdict.standard_error
    too_slow = Score(ten_better.errors, 250.0)  # the same images right, but over the latency budget
    assert choose(defaults, [too_slow], budget_ms=150.0).winner is None
    assert choose(defaults, [], budget_ms=150.0).reason == "no trial besides the defaults"


def test_a_ros_parameter_file_loads_as_estimator_parameters(tmp_path):
    nested = tmp_path / "nested.yaml"
    nested.write_text("estimator:\n  ros__parameters:\n    matching:\n      empty_coefficient: 0.3\n"
                      "    edges.merge_gap: 9.0\n")
    params = EstimatorParams.load(nested)
    assert params.matching.empty_coefficient == 0.3 and params.edges.merge_gap == 9.0
    bad = tmp_path / "bad.yaml"
    bad.write_text("estimator:\n  ros__parameters:\n    matching:\n      empty_coefficient: 50.0\n")
    with pytest.raises(ValueError, match="empty_coefficient must be in"):
        EstimatorParams.load(bad)
    typo = tmp_path / "typo.yaml"
    typo.write_text("estimator:\n  ros__parameters:\n    graphs: [a.npz]\n")
    with pytest.raises(ValueError, match="unknown parameter group"):
        EstimatorParams.load(typo)


@pytest.mark.cad
@pytest.mark.slow
def test_brepose_learn_on_a_tiny_budget_writes_a_file_the_estimator_loads(tmp_path, capsys):
    pytest.importorskip("optuna")
    from brepose_ros.cli.learn import main

    out = tmp_path / "learned.yaml"
    assert main(["-o", str(out), "--trials", "2", "--n", "1", "--held-out-n", "1", "--finalists", "1",
                 "--step-deg", "30", "--cache", str(tmp_path / "cache")]) == 0
    text = out.read_text()
    assert "# shapes: cube, box, cylinder, l_block, wedge" in text and "held_out score of the paper's method" in text
    assert len((tmp_path / "learned.trials.csv").read_text().splitlines()) == 4  # header, defaults, 2 trials
    learned = EstimatorParams.load(out)
    searched = {k.name for k in SEARCH_SPACE}
    changed = {n for n, v in learned.flat().items() if v != EstimatorParams().flat()[n]}
    assert changed <= searched


def test_min_score_calibration_finds_the_known_threshold():
    from brepose_ros.evaluation.metrics import calibrate_min_score, precision_recall

    # highest first: 10 right poses at 0.9..0.81, a wrong one at 0.80, 9 right at 0.79..0.71, then
    # wrong ones from 0.70 down: down to 0.71 precision is 19 / 20 = 0.95, at 0.70 it is 19 / 21
    right = list(np.linspace(0.9, 0.81, 10)) + list(np.linspace(0.79, 0.71, 9))
    wrong = [0.80] + list(np.linspace(0.70, 0.3, 10))
    scores, correct = right + wrong, [True] * len(right) + [False] * len(wrong)
    assert calibrate_min_score(scores, correct, 0.95) == pytest.approx(0.71)
    assert calibrate_min_score(scores, correct, 0.96) == pytest.approx(0.81)  # 10 / 10 above the wrong 0.80
    assert calibrate_min_score([0.9, 0.5], [False, True], 0.95) is None  # the best score is wrong
    precision, recall, detections = precision_recall(scores, correct, 20, [0.71, 0.95])
    assert precision == pytest.approx([0.95, 1.0]) and recall == pytest.approx([0.95, 0.0])
    assert list(detections) == [20, 0]


def test_the_shipped_learned_file_passes_the_estimator_files_checks():
    import yaml

    from brepose_ros.params import ros_section

    EstimatorParams.load(CONFIG / "learned.yaml")  # the checks of config/estimator.yaml
    groups = ros_section(yaml.safe_load((CONFIG / "learned.yaml").read_text()))
    names = {f"{g}.{k}" for g, values in groups.items() for k in values}
    assert names and not any(n.startswith("pose.") for n in names)  # min_score's calibration holds
    assert "brepose-learn" in (CONFIG / "learned.yaml").read_text()


@pytest.mark.ros
def test_the_node_accepts_the_learned_file_as_a_parameter_file():
    from brepose_ros.ros.node import check_params_file

    check_params_file(CONFIG / "learned.yaml")  # raises StartupError on an unknown name
