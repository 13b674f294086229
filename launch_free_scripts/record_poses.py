"""Record the estimator node's poses into the predictions JSON of CONVENTIONS.md.

    python launch_free_scripts/record_poses.py -o predictions.json --bag out/demo/bag --scene out/demo/scene

Each image the node answers becomes an entry: R and t from its PoseStamped (null when the
part was not found), score and error ratio from its diagnostics. With ``--bag`` and
``--scene`` (a bag written from that scene by brepose-bag) entries are named by the scene's
image paths, ready for brepose-eval; otherwise by stamp (``stamp:<nanoseconds>``). Stops on
Ctrl-C, after ``--count`` images, or ``--idle`` seconds after the last answer, then writes.
Start it before play_bag.py; see there for the discovery setting across processes.
"""
import argparse
import signal
import sys
import threading
import time

from brepose_ros.evaluation.metrics import write_predictions
from brepose_ros.ros.replay import PoseRecorder, RosSession, scene_names

#: how long to wait for the node's topics before saying "recording" anyway, s
NODE_WAIT = 15.0


def answer_times(recorder: PoseRecorder) -> list[float]:
    """When the diagnostics of each answered image arrived; the node's input status, published
    once a second while no image arrives, answers none (else --idle would never run out)."""
    listener = recorder.diagnostics
    return [t for stamp, t in list(listener.arrived.items())
            if any(not status.name.endswith(": input") for status in listener.by_stamp[stamp].status)]


def main() -> int:
    parser = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    parser.add_argument("-o", "--output", required=True, help="predictions JSON to write")
    parser.add_argument("--part", help="part name when the node estimates several (topic ~/<part>/pose)")
    parser.add_argument("--node", default="estimator", help="the estimator node's name")
    parser.add_argument("--bag", help="the bag being played, to name images (with --scene)")
    parser.add_argument("--scene", help="the scene folder the bag was written from")
    parser.add_argument("--count", type=int, help="stop after this many answered images")
    parser.add_argument("--idle", type=float, default=30.0, help="stop this long after the last answer, s")
    args = parser.parse_args()
    if bool(args.bag) != bool(args.scene):
        parser.error("--bag and --scene go together")
    names = scene_names(args.bag, args.scene) if args.bag else None

    stop = threading.Event()
    signal.signal(signal.SIGTERM, lambda *_: stop.set())
    pose_topic = f"/{args.node}/{args.part}/pose" if args.part else f"/{args.node}/pose"
    with RosSession() as ros:
        recorder = PoseRecorder(ros.node("pose_recorder"), pose_topic,
                                f"{args.node}: {args.part}" if args.part else None)
        # "recording" is said once the node's publishers have matched ours, so that a bag
        # played after it is answered into this recorder too (a busy machine discovers slowly)
        seen = recorder.wait_for_node(NODE_WAIT)
        print(f"recording {pose_topic} and /diagnostics; Ctrl-C to stop"
              + ("" if seen else f" (no estimator seen within {NODE_WAIT:.0f} s: its answers are recorded once it is)"),
              file=sys.stderr)
        try:
            while not stop.wait(0.2):
                arrived = answer_times(recorder)
                if args.count and len(arrived) >= args.count:
                    break
                if arrived and time.perf_counter() - max(arrived) > args.idle:
                    break
        except KeyboardInterrupt:
            pass
        predictions = recorder.predictions(names)
    write_predictions(args.output, predictions)
    found = sum(p["R"] is not None for p in predictions)
    print(f"wrote {len(predictions)} predictions ({found} with a pose) to {args.output}")
    return 0


if __name__ == "__main__":
    sys.exit(main())
