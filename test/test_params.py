"""Parameter groups and the shipped config files: one set of defaults, typos refused."""
from __future__ import annotations

import textwrap
from pathlib import Path

import pytest
import yaml

from brepose_ros.params import EstimatorParams, field_docs, field_ranges

CONFIG = Path(__file__).resolve().parents[1] / "config"
HEADER = """\
# Defaults of every estimator parameter, nested as EstimatorParams.to_dict(). Written by
# `python test/test_params.py` from brepose_ros/params.py, which stays the source of truth;
# test/test_params.py fails when the two differ. Load with EstimatorParams.load(path); in the
# ROS node the same names are parameters (edges.blur_size, matching.workers, ...) that
# config/node.yaml or a parameter change at run time can set.
"""


def write_estimator_yaml(path: Path = CONFIG / "estimator.yaml") -> None:
    """config/estimator.yaml from the defaults, each value under its documentation."""
    docs, ranges = field_docs(), field_ranges()
    lines = [HEADER]
    for group, values in EstimatorParams().to_dict().items():
        lines.append(f"{group}:")
        for key, value in values.items():
            text = docs[f"{group}.{key}"]
            if f"{group}.{key}" in ranges:
                text += " [range {:g} to {:g}]".format(*ranges[f"{group}.{key}"])
            lines += [f"  # {line}" for line in textwrap.wrap(text, 92)]
            lines.append(f"  {key}: {yaml.safe_dump(value).removesuffix(chr(10)).removesuffix('...').strip()}")
        lines.append("")
    path.write_text("\n".join(lines).rstrip() + "\n")


def test_estimator_yaml_holds_exactly_the_defaults():
    shipped = yaml.safe_load((CONFIG / "estimator.yaml").read_text())
    defaults = EstimatorParams().to_dict()
    assert shipped == defaults, "config/estimator.yaml is out of date: run python test/test_params.py"
    for group, values in defaults.items():
        for key, value in values.items():
            assert type(shipped[group][key]) is type(value), f"{group}.{key} has the wrong YAML type"
    assert EstimatorParams.load(CONFIG / "estimator.yaml") == EstimatorParams()


@pytest.mark.parametrize("data, message", [
    ({"matchng": {}}, "unknown parameter group"),
    ({"matching": {"empty_coeficient": 0.3}}, "unknown parameter.*empty_coeficient"),
    ({"pose": {"refine_iterations": "many"}}, "refine_iterations must be int"),
    ({"pose": 3}, "must be a mapping"),
])
def test_unknown_or_malformed_entries_are_refused(data, message):
    with pytest.raises(ValueError, match=message):
        EstimatorParams.from_dict(data)


def test_load_reports_missing_and_broken_files(tmp_path):
    with pytest.raises(ValueError, match="does not exist"):
        EstimatorParams.load(tmp_path / "none.yaml")
    broken = tmp_path / "broken.yaml"
    broken.write_text("matching: [unclosed\n")
    with pytest.raises(ValueError, match="not valid YAML"):
        EstimatorParams.load(broken)


def test_with_flat_changes_only_the_named_values():
    base = EstimatorParams()
    changed = base.with_flat({"matching.empty_coefficient": 0.3, "pose.refine_iterations": 2})
    assert changed.matching.empty_coefficient == 0.3 and changed.pose.refine_iterations == 2
    flat_before, flat_after = base.flat(), changed.flat()
    assert {k for k in flat_before if flat_before[k] != flat_after[k]} == {
        "matching.empty_coefficient", "pose.refine_iterations"}
    assert base.matching.empty_coefficient == 0.25, "with_flat must not modify the original"
    with pytest.raises(ValueError, match="unknown parameter group"):
        base.with_flat({"matchng.workers": 2})
    with pytest.raises(ValueError, match="blur_size"):
        base.with_flat({"edges.blur_size": 4})


def test_every_flat_parameter_is_documented():
    docs = field_docs()
    assert set(docs) == set(EstimatorParams().flat())
    assert all(docs.values())


if __name__ == "__main__":
    write_estimator_yaml()


def test_every_default_lies_in_its_range_and_the_bounds_are_enforced():
    defaults, ranges = EstimatorParams().flat(), field_ranges()
    assert ranges, "no ranges declared"
    for name, (low, high) in ranges.items():
        assert low <= defaults[name] <= high, name
        assert type(low) is type(defaults[name]) or isinstance(defaults[name], float), name
        for outside in (low - 1, high + 1):
            with pytest.raises(ValueError, match=name.split(".")[1]):
                EstimatorParams().with_flat({name: type(defaults[name])(outside)})
    with pytest.raises(ValueError, match="must be int, got 2.5"):
        EstimatorParams().with_flat({"matching.workers": 2.5})
    assert EstimatorParams().with_flat({"pose.min_score": "1e-3"}).pose.min_score == 0.001


@pytest.mark.parametrize("values, message", [
    ({"min_distance": 0.6, "max_distance": 0.4}, r"pose.min_distance \(0.6 m\) must not exceed max_distance \(0.4 m\)"),
    ({"min_distance": -0.1}, r"pose.min_distance must be in \[0, 1000\]"),
    ({"max_distance": -0.5, "min_distance": 0.2}, r"pose.max_distance must be in \[0, 1000\]"),
])
def test_a_hostile_working_range_is_refused_naming_it(values, message):
    with pytest.raises(ValueError, match=message):
        EstimatorParams.from_dict({"pose": values})


def test_a_working_range_end_left_at_zero_is_unknown():
    only_near = EstimatorParams.from_dict({"pose": {"min_distance": 0.5}}).pose
    assert only_near.within_distance(50.0) and not only_near.within_distance(0.4)
    only_far = EstimatorParams.from_dict({"pose": {"max_distance": 0.5}}).pose
    assert only_far.within_distance(0.01) and not only_far.within_distance(0.6)
    assert EstimatorParams().pose.within_distance(1e6)
