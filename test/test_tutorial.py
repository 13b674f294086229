"""docs/tutorial.md and the README's commands, run as written, so that they cannot rot.

Every ```bash block of the tutorial runs, in order, as one bash script in one folder laid out
like the clone (launch_free_scripts/ and config/ linked in). What a user brings is made
from built-in parts: ``my_part.step`` (the sharp bracket), ``my_part.stl`` (a box in mm) and
``photos/`` (two renders of the part). A few numbers are changed (``SCALING``: coarse view
spheres and two images so that the walk stays short, patience for a loaded machine). The blocks
that start the node and the pose recorder run in the background, as in the tutorial's separate
shells, and the next block starts once they are listening. The README's commands
are the tutorial's (checked below), and ``make demo`` runs launch_free_scripts/demo.py, run here
with the same scaling.
"""
from __future__ import annotations

import json
import random
import re
import shutil
import subprocess
import sys
import time
from pathlib import Path

import pytest

from node_helpers import ros_env

REPO = Path(__file__).resolve().parents[1]
TUTORIAL = REPO / "docs" / "tutorial.md"
#: (as written, as run): each must occur in the tutorial, so that this table cannot go stale
SCALING = [
    ("brepose-compile ", "brepose-compile --step-deg 20 --workers 1 "),
    ("--n 8 ", "--n 2 "),
    ("--n 12 -o", "--n 2 --others builtin:box --precision 0 -o"),  # two images per scene decide nothing
    ("--idle 10", "--idle 3"),
    ("--reliability reliable", "--reliability reliable --timeout 60"),
]
#: blocks that run until stopped (the node) or until idle (the recorder): started in the background
BACKGROUND = ("estimator ", "python launch_free_scripts/record_poses.py")
IMAGES = 2
TIMEOUT = 300

pytestmark = [pytest.mark.cad, pytest.mark.ros, pytest.mark.slow]


def bash_blocks(markdown: str) -> list[str]:
    return re.findall(r"^```bash\n(.*?)^```$", markdown, re.MULTILINE | re.DOTALL)


def commands(block: str) -> list[str]:
    """The command lines of a block (continuation lines joined; heredoc bodies and comments left out)."""
    lines, in_heredoc = [], None
    for line in block.replace("\\\n", " ").splitlines():
        if in_heredoc:
            in_heredoc = None if line.strip() == in_heredoc else in_heredoc
            continue
        if heredoc := re.search(r"<<'?(\w+)'?", line):
            in_heredoc = heredoc.group(1)
        command = line.split("  #")[0].strip()
        if command and not command.startswith("#"):
            lines.append(command)
    return lines


@pytest.fixture(scope="module")
def user_folder(tmp_path_factory, builtin_step):
    """What a user has before the tutorial: the part as STEP and as a mesh, a few photos."""
    import trimesh

    from brepose_ros.synthetic.scenes import generate_scene

    folder = tmp_path_factory.mktemp("tutorial")
    for name in ("launch_free_scripts", "config"):
        (folder / name).symlink_to(REPO / name)
    shutil.copy(builtin_step("sharp_bracket"), folder / "my_part.step")
    trimesh.creation.box((60.0, 40.0, 25.0)).export(folder / "my_part.stl")
    scene = generate_scene(folder / "my_part.step", folder / "photo_scene", IMAGES, seed=7, progress=False)
    (folder / "photos").mkdir()
    for entry in scene.entries:
        shutil.copy(entry.path, folder / "photos" / entry.path.name)
    return folder


def test_every_tutorial_command_runs(user_folder):
    text = TUTORIAL.read_text()
    for written, _ in SCALING:
        assert written in text, f"SCALING names {written!r}, which the tutorial no longer has"
    env = ros_env(ROS_DOMAIN_ID=str(random.randint(100, 200)),
                  PATH=f"{Path(sys.executable).parent}:{ros_env()['PATH']}")
    background, outputs = [], {}
    try:
        for index, block in enumerate(bash_blocks(text)):
            script = block
            for written, run in SCALING:
                script = script.replace(written, run)
            if block.startswith(BACKGROUND):
                log = user_folder / f"block{index}.log"
                process = subprocess.Popen(["bash", "-euo", "pipefail", "-c", script], cwd=user_folder, env=env,
                                           stdout=log.open("w"), stderr=subprocess.STDOUT)
                background.append((process, log))
                deadline = time.monotonic() + TIMEOUT
                while not log.read_text():  # the node and the recorder each print a line once listening
                    assert process.poll() is None and time.monotonic() < deadline, f"block {index}:\n{block}"
                    time.sleep(0.2)
                continue
            result = subprocess.run(["bash", "-euo", "pipefail", "-c", script], cwd=user_folder, env=env,
                                    capture_output=True, text=True, timeout=TIMEOUT)
            logs = "".join(log.read_text() for _, log in background)
            assert result.returncode == 0, f"block {index}:\n{block}\n{result.stdout}{result.stderr}\n{logs}"
            outputs[commands(block)[0]] = result.stdout
        recorder, recorder_log = background[-1]
        assert recorder.wait(timeout=TIMEOUT) == 0, recorder_log.read_text()
    finally:
        for process, _ in background:
            process.terminate()
            process.wait(timeout=30)

    def output(prefix):
        return next(text for command, text in outputs.items() if command.startswith(prefix))

    assert re.search(rf"^\d of {IMAGES} found, \d correct \(\d+ %\)", output("brepose-render"), re.MULTILINE)
    assert len(list((user_folder / "renders_eval" / "overlays").glob("*.png"))) == IMAGES
    assert re.search(rf"^\d of {IMAGES} found \(\d+ %\); wrote poses.json and overlays in checks$",
                     output("brepose-estimate"), re.MULTILINE)
    assert len(list((user_folder / "checks").glob("*.png"))) == IMAGES
    assert "| 0.80 |" in output("brepose-threshold") and "min_score:" in (user_folder / "my_part.yaml").read_text()
    assert "| min_confidence | detections | precision | recall |" in output("brepose-threshold")
    assert f"the node answered {IMAGES}" in output("python launch_free_scripts/play_bag.py")
    recorded = json.loads((user_folder / "node_poses.json").read_text())
    assert sorted(p["image"] for p in recorded) == sorted(f"images/{i:06d}.png" for i in range(IMAGES))
    assert (user_folder / "my_part_mesh.brepose.npz").is_file()


def test_the_readme_commands_are_the_tutorials():
    readme = [c for block in bash_blocks((REPO / "README.md").read_text()) for c in commands(block)]
    tutorial = {c for block in bash_blocks(TUTORIAL.read_text()) for c in commands(block)}
    assert readme[:2] == ["make demo", "make test"]
    assert [c for c in readme[2:] if c not in tutorial] == []
    makefile = (REPO / "Makefile").read_text()
    assert "launch_free_scripts/demo.py --out out/demo" in makefile  # what test_demo runs
    assert "pytest -q test" in makefile and "make test" in (REPO / ".ci" / "run").read_text()


def test_demo(tmp_path):
    """``make demo``'s job on a coarse graph: the whole path and the summary a user reads."""
    result = subprocess.run([sys.executable, str(REPO / "launch_free_scripts" / "demo.py"), "--out", str(tmp_path),
                             "--images", str(IMAGES), "--step-deg", "20"],
                            capture_output=True, text=True, timeout=TIMEOUT, env=ros_env())
    assert result.returncode == 0, result.stdout + result.stderr
    assert re.search(rf"^\d of {IMAGES} found, \d correct \(\d+ %\); median error", result.stdout, re.MULTILINE)
    assert (tmp_path / "predictions.json").is_file()
