"""brepose-threshold's parameter file: the chosen min_score and only what differs from the
defaults, loadable by every reader of estimator YAML (the whole run: test_tutorial.py)."""
from __future__ import annotations

import pytest
import yaml

from brepose_ros.params import EstimatorParams

pytestmark = pytest.mark.cad  # the command renders scenes


def test_the_written_file_holds_min_score_and_the_changed_parameters(tmp_path):
    from brepose_ros.cli.threshold import write_params

    params = EstimatorParams().with_flat({"pose.min_score": 0.812, "edges.blur_size": 7})
    write_params(tmp_path / "part.yaml", params, "brepose-threshold part.step --graph part.brepose.npz")
    text = (tmp_path / "part.yaml").read_text()
    assert text.startswith("# written by brepose-threshold part.step")
    assert EstimatorParams.load(tmp_path / "part.yaml") == params
    assert yaml.safe_load(text) == {"edges": {"blur_size": 7}, "pose": {"min_score": 0.812}}


def test_min_score_is_written_even_at_its_default(tmp_path):
    from brepose_ros.cli.threshold import write_params

    write_params(tmp_path / "part.yaml", EstimatorParams(), "brepose-threshold")
    assert EstimatorParams.load(tmp_path / "part.yaml") == EstimatorParams()
    assert f"min_score: {EstimatorParams().pose.min_score}" in (tmp_path / "part.yaml").read_text()
