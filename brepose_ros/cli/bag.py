"""brepose-bag: write a scene folder's images as a rosbag2 (Image + CameraInfo).

    brepose-bag SCENE_DIR BAG_DIR [--storage mcap|sqlite3] [--topic /camera/image_raw]
                [--info-topic /camera/camera_info] [--rate HZ] [--frame-id FRAME]
                [--compressed png|jpeg]

A bad input prints the reason on stderr and exits with status 2.
"""
from __future__ import annotations

import argparse
from pathlib import Path

from ..ros.bags import COMPRESSIONS, FRAME_ID, STORAGES, write_scene_bag
from .common import ArgumentParser, positive_float, run


EXAMPLE = """example:
  brepose-bag renders renders_bag --topic /camera/image_raw --info-topic /camera/camera_info --rate 10"""


def parser() -> argparse.ArgumentParser:
    p = ArgumentParser(prog="brepose-bag", description=__doc__.splitlines()[0], epilog=EXAMPLE)
    p.add_argument("scene", type=Path, help="scene folder (camera.json, images/, gt.json)")
    p.add_argument("bag", type=Path, help="new bag folder")
    p.add_argument("--storage", choices=STORAGES, default="mcap", help="storage plugin (default mcap)")
    p.add_argument("--topic", default="/camera/image_raw", help="sensor_msgs/Image topic")
    p.add_argument("--info-topic", default="/camera/camera_info", help="sensor_msgs/CameraInfo topic")
    p.add_argument("--rate", type=positive_float, default=10.0, help="frames per second of the stamps (default 10)")
    p.add_argument("--frame-id", default=FRAME_ID, help=f"header frame_id (default {FRAME_ID})")
    p.add_argument("--compressed", choices=COMPRESSIONS,
                   help="write sensor_msgs/CompressedImage on TOPIC/compressed instead of raw Image")
    return p


def main(argv: list[str] | None = None) -> int:
    args = parser().parse_args(argv)

    def write() -> None:
        count = write_scene_bag(args.scene, args.bag, storage=args.storage, topic=args.topic,
                                info_topic=args.info_topic, rate=args.rate, frame_id=args.frame_id,
                                compression=args.compressed)
        topic = args.topic + ("/compressed" if args.compressed else "")
        print(f"{args.bag}: {count} frames on {topic} and {args.info_topic} ({args.storage}, {args.rate:g} Hz)")

    return run(write)


if __name__ == "__main__":
    raise SystemExit(main())
