"""Start the estimator node with a parameter file: what ``ros2 run brepose_ros estimator
--ros-args --params-file config/node.yaml`` does in a ROS install (no ros2 CLI here).

    python launch_free_scripts/run_estimator.py                          # config/node.yaml
    python launch_free_scripts/run_estimator.py --params-file my.yaml --ros-args -r image_raw:=/cam/image

Ctrl-C or SIGTERM stop it cleanly. To talk to it from another process (play_bag.py,
record_poses.py) leave ROS_AUTOMATIC_DISCOVERY_RANGE unset or LOCALHOST in both shells: OFF
confines discovery to one process.
"""
import sys
from pathlib import Path

from brepose_ros.ros.node import main

DEFAULT_PARAMS = Path(__file__).resolve().parents[1] / "config" / "node.yaml"

if __name__ == "__main__":
    argv = sys.argv[1:]
    if "--params-file" not in argv:
        argv = ["--params-file", str(DEFAULT_PARAMS), *argv]
    sys.exit(main([sys.argv[0], *argv]))
