"""Play a rosbag2 of Image + CameraInfo (written by brepose-bag or any camera recording) into
the estimator node's topics, and report how the node kept up.

    python launch_free_scripts/play_bag.py out/demo/bag                       # lock-step
    python launch_free_scripts/play_bag.py camera.bag --mode rate --speed 0.5  # recorded rate

``lockstep`` publishes the next image only when the node has published the diagnostics of
the previous one (every frame is answered, as fast as the node can); ``rate`` keeps the
recorded spacing like ``ros2 bag play`` and the node skips what it cannot keep up with.
The node runs in another process (run_estimator.py): leave ROS_AUTOMATIC_DISCOVERY_RANGE
unset or LOCALHOST in both shells, OFF confines discovery to one process. ``--reliability
reliable`` offers reliable delivery, which frames over about 0.5 MB need between processes
under Fast DDS defaults (docs/ros.md); ``--image-transport compressed`` publishes
CompressedImage on ``<image-topic>/compressed`` (recorded compressed frames unchanged).
A bad bag or option prints ``play_bag: error: ...`` and exits with status 2.
"""
import statistics
import sys

from brepose_ros.cli.common import ArgumentParser, positive_float, positive_int
from brepose_ros.ros.bags import BagError
from brepose_ros.ros.messages import PUBLISHER_QOS
from brepose_ros.ros.replay import TRANSPORTS, Player, RosSession, bag_frames


def main(argv: list[str] | None = None) -> int:
    parser = ArgumentParser(prog="play_bag", description=__doc__)
    parser.add_argument("bag", help="rosbag2 folder (mcap or sqlite3)")
    parser.add_argument("--mode", choices=("lockstep", "rate"), default="lockstep")
    parser.add_argument("--speed", type=positive_float, default=1.0, help="rate mode: playback speed factor")
    parser.add_argument("--reliability", choices=PUBLISHER_QOS, default="best_effort",
                        help="QoS reliability the player offers (default best_effort, as cameras)")
    parser.add_argument("--image-transport", choices=TRANSPORTS, default="raw",
                        help="raw Image or CompressedImage on <image-topic>/compressed")
    parser.add_argument("--bag-topic", help="the bag's Image topic if it has several")
    parser.add_argument("--bag-info-topic", help="the bag's CameraInfo topic (default: beside the images)")
    parser.add_argument("--image-topic", default="image_raw", help="where the node listens for images")
    parser.add_argument("--info-topic", default="camera_info", help="where the node listens for CameraInfo")
    parser.add_argument("--statuses", type=positive_int, default=1,
                        help="diagnostics statuses that answer one image: its parts over every estimator process "
                             "(run_partitioned.py); lock-step waits for all of them")
    parser.add_argument("--nodes", type=positive_int, default=1,
                        help="estimator nodes to wait for before playing (the processes of run_partitioned.py)")
    parser.add_argument("--timeout", type=positive_float, default=10.0,
                        help="seconds to wait for the node / an answer")
    args = parser.parse_args(argv)

    def frames():
        return bag_frames(args.bag, args.bag_topic, args.bag_info_topic, args.image_transport)

    try:  # the bag's first frame before any ROS set-up: a bad bag fails at once
        next(iter(frames()), None)
    except BagError as exc:
        print(f"play_bag: error: {exc}", file=sys.stderr)
        return 2
    with RosSession() as ros:
        player = Player(ros.node("bag_player"), args.image_topic, args.info_topic,
                        reliability=args.reliability, transport=args.image_transport, statuses=args.statuses)
        try:
            player.wait_for_node(args.timeout, args.nodes)
            playback = player.play(frames(), args.mode, args.speed, args.timeout)
        except (BagError, TimeoutError) as exc:
            print(f"play_bag: error: {exc}", file=sys.stderr)
            return 2
        if playback.published_at:
            player.diagnostics.wait_for(max(playback.published_at), args.timeout, args.statuses)
        answered = playback.answered(player.diagnostics, args.statuses)
        latencies = list(playback.latencies_ms(player.diagnostics).values())
        print(f"published {len(playback.published_at)} images in {playback.seconds:.1f} s, "
              f"the node answered {len(answered)} ({len(answered) / max(playback.seconds, 1e-9):.2f}/s)"
              + (f", median latency {statistics.median(latencies):.0f} ms" if latencies else ""))
        names = sorted({s.name for stamp in playback.published_at for s in player.diagnostics.statuses.get(stamp, ())})
        print(f"answered by: {', '.join(names)}")
    return 0


if __name__ == "__main__":
    sys.exit(main())
