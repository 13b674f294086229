"""Start K estimator processes that share the parts (aspect graphs) of one camera: each
process gets every K-th graph and subscribes to the same image topic, so the parts are
estimated on K processes (and as many cores or machines) at once.

    python launch_free_scripts/run_partitioned.py --processes 2 --graphs a.brepose.npz b.brepose.npz
    python launch_free_scripts/run_partitioned.py --processes 2 --graphs *.brepose.npz \\
        --params-file config/node.yaml -- -r image_raw:=/camera/image_raw -r camera_info:=/camera/camera_info

Process k is the node ``estimator_<k>``: its poses are ``/estimator_<k>/pose`` (one part) or
``/estimator_<k>/<part>/pose``, and its diagnostics statuses ``estimator_<k>: <part>`` on
/diagnostics. ``--params-file`` (optional, e.g. config/node.yaml) gives every process the
same other parameters; its ``graphs`` and ``part_names`` are replaced by each process's
share. Arguments after ``--`` go to every process's ``--ros-args`` (remappings).

On several machines, start this script (or run_estimator.py with a partition of the graphs)
on each with the same ``ROS_DOMAIN_ID`` and discovery reaching the others (docs/ros.md,
"Parts on several processes or machines"); every process receives the full image stream.
Ctrl-C or SIGTERM stop every process. A bad option prints ``run_partitioned: error: ...``
and exits with status 2.
"""
from __future__ import annotations

import signal
import subprocess
import sys
import tempfile
import time
from pathlib import Path

import yaml

from brepose_ros.aspect_graph import SUFFIX as GRAPH_SUFFIX
from brepose_ros.cli.common import ArgumentParser, positive_int
from brepose_ros.ros.node import NODE_NAME, StartupError, check_params_file

#: seconds the processes get to stop after SIGTERM before they are killed
STOP_TIMEOUT = 10.0


def partition(graphs: list[str], names: list[str], processes: int) -> list[tuple[list[str], list[str]]]:
    """Every ``processes``-th graph (and its name) to each process, skipping empty shares."""
    shares = [(graphs[k::processes], names[k::processes]) for k in range(processes)]
    return [share for share in shares if share[0]]


def base_parameters(path: str | None) -> dict:
    """The node's ros__parameters of a params file (``estimator:`` or ``/**:`` section)."""
    if path is None:
        return {}
    check_params_file(path)
    data = yaml.safe_load(Path(path).read_text()) or {}
    merged = {}
    for key in ("/**", NODE_NAME):
        merged.update((data.get(key) or {}).get("ros__parameters") or {})
    return merged


def process_commands(args, folder: Path) -> list[list[str]]:
    """The command line of each process, its parameter file written into ``folder``."""
    names = args.part_names or [Path(g).name.removesuffix(GRAPH_SUFFIX) for g in args.graphs]
    if len(names) != len(args.graphs):
        raise StartupError(f"{len(args.graphs)} graphs but {len(names)} part names: give one name per graph")
    base = base_parameters(args.params_file)
    commands = []
    for k, (graphs, part_names) in enumerate(partition([str(Path(g).resolve()) for g in args.graphs], names,
                                                      args.processes)):
        params = folder / f"estimator_{k}.yaml"
        # "/**" applies to the renamed node; the renamed node ignores an "estimator:" section
        params.write_text(yaml.safe_dump({"/**": {"ros__parameters": {**base, "graphs": graphs,
                                                                      "part_names": part_names}}}))
        commands.append([sys.executable, "-m", "brepose_ros.ros.node", "--params-file", str(params),
                         "--ros-args", "-r", f"__node:={NODE_NAME}_{k}", *args.ros_args])
    return commands


def main(argv: list[str] | None = None) -> int:
    argv = sys.argv[1:] if argv is None else argv
    ours, ros_args = (argv[:argv.index("--")], argv[argv.index("--") + 1:]) if "--" in argv else (argv, [])
    parser = ArgumentParser(prog="run_partitioned", description=__doc__)
    parser.add_argument("--processes", type=positive_int, default=2, help="estimator processes (K)")
    parser.add_argument("--graphs", nargs="+", required=True, help="aspect graph files, one per part")
    parser.add_argument("--part-names", nargs="*", help="one name per graph (default: the file names)")
    parser.add_argument("--params-file", help="ROS parameter file shared by every process (config/node.yaml)")
    args = parser.parse_args(ours)
    args.ros_args = ros_args
    missing = [g for g in args.graphs if not Path(g).is_file()]
    if missing:
        parser.error(f"aspect graph file not found: {missing[0]}")
    with tempfile.TemporaryDirectory(prefix="brepose_partitioned_") as folder:
        try:
            commands = process_commands(args, Path(folder))
        except StartupError as exc:
            parser.error(str(exc))
        processes = [subprocess.Popen(command) for command in commands]
        stop = []
        for sig in (signal.SIGINT, signal.SIGTERM):
            signal.signal(sig, lambda *_: stop.append(True))
        try:
            while not stop and all(p.poll() is None for p in processes):
                time.sleep(0.2)
        finally:
            for p in processes:
                if p.poll() is None:
                    p.send_signal(signal.SIGINT)
            deadline = time.monotonic() + STOP_TIMEOUT
            for p in processes:
                try:
                    p.wait(timeout=max(deadline - time.monotonic(), 0.1))
                except subprocess.TimeoutExpired:
                    p.kill()
                    p.wait()
    failed = [p.returncode for p in processes if p.returncode not in (0, -signal.SIGINT)]
    return failed[0] if failed and not stop else 0


if __name__ == "__main__":
    sys.exit(main())
