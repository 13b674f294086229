"""One version number (brepose_ros.__version__) reported alike by the installed package,
package.xml, every command's --version, and the aspect graph files it writes; every
command's --help carries an example."""
from __future__ import annotations

import importlib
import json
import re
import xml.etree.ElementTree as ET
from importlib.metadata import version as installed_version
from pathlib import Path

import numpy as np
import pytest

from brepose_ros import __version__
from brepose_ros.aspect_graph import AspectGraph

REPO = Path(__file__).resolve().parents[1]
#: console scripts whose modules import the CAD stack at import time
CAD_COMMANDS = {"compile", "render", "evaluate", "threshold"}


def test_package_xml_and_the_installed_package_carry_the_package_version():
    assert re.fullmatch(r"\d+\.\d+\.\d+", __version__), "package.xml needs MAJOR.MINOR.PATCH"
    assert ET.parse(REPO / "package.xml").getroot().findtext("version") == __version__
    assert installed_version("brepose_ros") == __version__  # setup.py reads __init__.py


def test_the_changelog_has_a_section_for_the_version():
    assert re.search(rf"^## {re.escape(__version__)}\b", (REPO / "CHANGELOG.md").read_text(), re.MULTILINE)


@pytest.mark.parametrize("command", [
    pytest.param(name, marks=[pytest.mark.cad] if name in CAD_COMMANDS else [])
    for name in ("compile", "render", "bag", "estimate", "evaluate", "learn")])
def test_every_command_reports_the_version_and_shows_an_example(command, capsys):
    module = importlib.import_module(f"brepose_ros.cli.{command}")
    with pytest.raises(SystemExit) as stop:
        module.main(["--version"])
    assert stop.value.code == 0 and capsys.readouterr().out.strip().endswith(f"(brepose_ros) {__version__}")
    with pytest.raises(SystemExit):
        module.main(["--help"])
    help_text = capsys.readouterr().out
    assert re.search(r"^examples?:\n  brepose-", help_text, re.MULTILINE), help_text


@pytest.mark.ros
def test_the_node_reports_the_version(capsys):
    from brepose_ros.ros.node import parse_args

    with pytest.raises(SystemExit):
        parse_args(["estimator", "--version"])
    assert capsys.readouterr().out.strip() == f"estimator (brepose_ros) {__version__}"


def test_a_saved_aspect_graph_records_the_version(tmp_path):
    graph = AspectGraph(step_sha256="0" * 64, params={"units": "m"}, model_center=np.zeros(3), model_diameter=0.1,
                        n_faces=6, view_directions=np.array([[0.0, 0.0, 1.0]]), view_rotations=np.eye(3)[None],
                        seg_offsets=np.array([0, 1]), seg_xy=np.zeros((1, 2, 2), np.float32),
                        xy_origin=np.zeros((1, 2)), xy_scale=np.ones(1), seg_3d=np.zeros((1, 2, 3)),
                        seg_kind=np.zeros(1, np.uint8))
    path = graph.save(tmp_path / "part.brepose.npz")
    with np.load(path, allow_pickle=False) as npz:
        assert json.loads(str(npz["metadata"]))["brepose_ros_version"] == __version__
    assert AspectGraph.load(path).n_views == 1
