"""The evaluation metrics of ../shared/CONVENTIONS.md, each on one case with a known answer."""
import numpy as np
import pytest

from brepose_ros.evaluation.metrics import (ModelPoints, format_summary, found_correct, pose_error_rate, pose_errors,
                                           summarise, translation_error_mm)
from brepose_ros.geometry import rot_z, rotation_angle_deg


def rot_x(angle):
    c, s = np.cos(angle), np.sin(angle)
    return np.array([[1.0, 0.0, 0.0], [0.0, c, -s], [0.0, s, c]])


#: the eight corners of a 2 cm cube centred on the origin: diameter 2 sqrt(3) cm
CUBE = ModelPoints(np.array([[x, y, z] for x in (-0.01, 0.01) for y in (-0.01, 0.01) for z in (-0.01, 0.01)]))


def test_rotation_error_is_the_geodesic_angle():
    assert rotation_angle_deg(rot_z(np.radians(30.0)), np.eye(3)) == pytest.approx(30.0)
    assert rotation_angle_deg(rot_x(np.radians(30.0)) @ rot_z(0.7), rot_z(0.7)) == pytest.approx(30.0)


def test_translation_error_is_the_distance_in_millimetres():
    assert translation_error_mm([0.003, 0.004, 0.5], [0.0, 0.0, 0.5]) == pytest.approx(5.0)


def test_error_rate_compares_viewing_directions_only():
    """(1 - cos of the angle between the viewing directions) / 2: blind to a turn about the
    optical axis, 1/2 for a quarter turn of the view, 1 for the part seen from behind."""
    R = rot_x(0.3)
    assert pose_error_rate(rot_z(1.0) @ R, R) == pytest.approx(0.0, abs=1e-15)
    assert pose_error_rate(R @ rot_x(np.pi / 2), R) == pytest.approx(0.5)
    assert pose_error_rate(R @ rot_x(np.pi), R) == pytest.approx(1.0)


def test_cube_diameter_is_its_space_diagonal():
    assert CUBE.diameter == pytest.approx(0.02 * np.sqrt(3.0))


def test_add_is_the_mean_point_distance_in_diameters():
    t = np.array([0.0, 0.0, 0.4])
    assert CUBE.add(np.eye(3), t + [0.002, 0.0, 0.0], np.eye(3), t) == pytest.approx(0.002 / CUBE.diameter)
    # a quarter turn about z moves every corner by the side of the cube, 2 cm
    assert CUBE.add(rot_z(np.pi / 2), t, np.eye(3), t) == pytest.approx(0.02 / CUBE.diameter)


def test_add_s_forgives_a_symmetry_and_nothing_else():
    t = np.array([0.0, 0.0, 0.4])
    assert CUBE.add_s(rot_z(np.pi / 2), t, np.eye(3), t) == pytest.approx(0.0, abs=1e-12)
    assert CUBE.add_s(np.eye(3), t + [0.002, 0.0, 0.0], np.eye(3), t) == pytest.approx(0.002 / CUBE.diameter)


def test_success_needs_5_degrees_and_5_percent_of_the_diameter():
    t = np.array([0.0, 0.0, 0.4])
    bound = 0.05 * CUBE.diameter
    assert pose_errors(rot_z(np.radians(4.9)), t + [0.99 * bound, 0, 0], np.eye(3), t, CUBE).success
    assert not pose_errors(rot_z(np.radians(5.1)), t, np.eye(3), t, CUBE).success
    assert not pose_errors(np.eye(3), t + [1.01 * bound, 0, 0], np.eye(3), t, CUBE).success


def test_summary_counts_images_without_a_pose_as_failures():
    t = np.array([0.0, 0.0, 0.4])
    right = pose_errors(np.eye(3), t, np.eye(3), t, CUBE)
    wrong = pose_errors(rot_z(np.radians(20.0)), t, np.eye(3), t, CUBE)
    summary = summarise([right, wrong, None, None])
    assert summary["images"] == 4 and summary["found"] == 0.5 and summary["success"] == 0.25
    assert summary["median_rotation_deg"] == pytest.approx(10.0)


def test_summaries_for_people_count_images():
    t = np.array([0.0, 0.0, 0.4])
    right = pose_errors(np.eye(3), t, np.eye(3), t, CUBE)
    wrong = pose_errors(rot_z(np.radians(20.0)), t, np.eye(3), t, CUBE)
    errors = [right, right, right, wrong, None, None, None, None]
    assert found_correct(errors) == "4 of 8 found, 3 correct (38 %)"
    assert found_correct([]) == "0 of 0 found, 0 correct (0 %)"
    lines = format_summary(summarise(errors)).splitlines()
    assert "found" in lines[1] and lines[1].endswith("4 of 8 (50 %)")
    assert "success" in lines[2] and lines[2].endswith("3 of 8 (38 %)")


def test_a_prediction_names_the_steps_a_time_budget_left_out_and_only_then():
    from brepose_ros.evaluation.metrics import prediction_entry
    from brepose_ros.online.estimator import Estimate

    hurried = Estimate(True, np.eye(3), np.array([0.0, 0.0, 0.5]), score=0.8, error_ratio=0.2, view_index=3,
                       n_image_segments=12, n_matched=8, n_nearest=6, skipped=("seeded", "larger"))
    entry = prediction_entry("images/000000.png", hurried)
    assert entry["skipped"] == ["seeded", "larger"] and entry["t"] == [0.0, 0.0, 0.5]
    hurried.skipped = ()
    assert "skipped" not in prediction_entry("images/000000.png", hurried)
