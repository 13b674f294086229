"""Bags round-trip pixels, encodings, intrinsics and stamps; bad bags and images fail clearly."""
from __future__ import annotations

import cv2
import numpy as np
import pytest
from rosbags.highlevel import AnyReader
from rosbags.rosbag2 import StoragePlugin, Writer
from rosbags.typesys import Stores, get_typestore

from brepose_ros.ros.bags import START_NS, BagError, read_bag, write_bag, write_scene_bag
from brepose_ros.camera import Camera
from brepose_ros.cli import bag as bag_cli
from brepose_ros.image_codec import decode_image, encode_image
from brepose_ros.synthetic.scenes import SceneConfig, generate_scene
from brepose_ros.scene_folder import load_scene

STORE = get_typestore(Stores.ROS2_KILTED)
CAMERA = Camera(300.0, 310.0, 80.5, 59.0, 160, 120, (0.1, -0.05, 0.001, 0.002, 0.01))


@pytest.fixture(scope="module")
def scene(sample_step, tmp_path_factory):
    config = SceneConfig(width=160, height=120, fx=150.0, color=True)
    return generate_scene(sample_step, tmp_path_factory.mktemp("bags") / "scene", 3, seed=2, config=config)


@pytest.mark.parametrize("storage", ["mcap", "sqlite3"])
def test_scene_bag_round_trip(scene, tmp_path, storage):
    bag = tmp_path / "bag"
    assert write_scene_bag(scene.folder, bag, storage=storage, rate=4.0) == 3
    frames = list(read_bag(bag))
    assert [f.stamp_ns for f in frames] == [START_NS + i * 250_000_000 for i in range(3)]
    for frame, entry in zip(frames, load_scene(scene.folder).entries):
        assert frame.frame_id == "camera_optical_frame"
        assert frame.camera == scene.camera
        assert np.array_equal(frame.image, cv2.imread(str(entry.path), cv2.IMREAD_UNCHANGED))
    with AnyReader([bag]) as reader:  # CameraInfo shares the image's header
        headers = {}
        for conn, _, raw in reader.messages():
            msg = reader.deserialize(raw, conn.msgtype)
            headers.setdefault(conn.msgtype, []).append((msg.header.stamp.sec, msg.header.stamp.nanosec,
                                                         msg.header.frame_id))
            if conn.msgtype == "sensor_msgs/msg/Image":
                assert msg.encoding == "bgr8"
            else:
                assert msg.distortion_model == "plumb_bob"
    assert headers["sensor_msgs/msg/Image"] == headers["sensor_msgs/msg/CameraInfo"]


@pytest.mark.parametrize("storage", ["mcap", "sqlite3"])
def test_every_written_encoding_and_distortion_round_trip(tmp_path, storage):
    rng = np.random.default_rng(0)
    images = [rng.integers(0, 256, (120, 160), dtype=np.uint8),
              rng.integers(0, 65536, (120, 160), dtype=np.uint16),
              rng.integers(0, 256, (120, 160, 3), dtype=np.uint8),
              rng.integers(0, 256, (120, 160, 4), dtype=np.uint8)]
    write_bag(tmp_path / "bag", images, CAMERA, storage=storage, topic="/cam/image", info_topic="/cam/camera_info")
    frames = list(read_bag(tmp_path / "bag"))
    for frame, image in zip(frames, images):
        expected = image[..., :3] if image.ndim == 3 else image  # BGRA decodes to BGR
        assert frame.image.dtype == expected.dtype and np.array_equal(frame.image, expected)
        assert frame.camera == CAMERA


def write_foreign_bag(path, messages):
    """A bag as another recorder would write it: (topic, msgtype, msg) in order, stamp 1 s apart."""
    with Writer(path, version=9, storage_plugin=StoragePlugin.MCAP) as writer:
        conns = {}
        for i, (topic, msgtype, msg) in enumerate(messages):
            if topic not in conns:
                conns[topic] = writer.add_connection(topic, msgtype, typestore=STORE)
            writer.write(conns[topic], (i + 1) * 10**9, STORE.serialize_cdr(msg, msgtype))


def image_msg(encoding, pixels, sec):
    types = STORE.types
    header = types["std_msgs/msg/Header"](stamp=types["builtin_interfaces/msg/Time"](sec=sec, nanosec=0),
                                          frame_id="cam")
    return types["sensor_msgs/msg/Image"](header=header, height=pixels.shape[0], width=pixels.shape[1],
                                          encoding=encoding, is_bigendian=0, step=pixels[0].nbytes,
                                          data=pixels.reshape(-1).view(np.uint8))


def test_rgb_bags_without_camera_info_decode_to_bgr(tmp_path):
    rgba = np.random.default_rng(1).integers(0, 256, (4, 5, 4), dtype=np.uint8)
    write_foreign_bag(tmp_path / "bag", [
        ("/left/image_color", "sensor_msgs/msg/Image", image_msg("rgb8", rgba[..., :3].copy(), 7)),
        ("/left/image_color", "sensor_msgs/msg/Image", image_msg("rgba8", rgba, 8)),
    ])
    frames = list(read_bag(tmp_path / "bag"))
    assert [(f.stamp_ns, f.frame_id, f.camera) for f in frames] == [(7 * 10**9, "cam", None), (8 * 10**9, "cam", None)]
    for frame in frames:
        assert np.array_equal(frame.image, rgba[..., 2::-1])


def test_unreadable_bags_and_bags_without_images_raise_bag_error(tmp_path):
    with pytest.raises(BagError, match="cannot read bag"):
        list(read_bag(tmp_path / "missing"))
    (tmp_path / "plain").mkdir()
    with pytest.raises(BagError, match="cannot read bag"):
        list(read_bag(tmp_path / "plain"))
    for name in ("good", "damaged"):
        write_bag(tmp_path / name, [np.zeros((8, 8), np.uint8)], CAMERA)
    damaged = tmp_path / "damaged"
    storage_file = next(damaged.glob("*.mcap"))
    storage_file.write_bytes(storage_file.read_bytes()[:200])
    with pytest.raises(BagError, match="cannot read bag"):
        list(read_bag(damaged))
    string = STORE.types["std_msgs/msg/String"](data="hello")
    write_foreign_bag(tmp_path / "chatter", [("/chatter", "std_msgs/msg/String", string)])
    with pytest.raises(BagError, match="no sensor_msgs/msg/Image or .*CompressedImage topic.*/chatter"):
        list(read_bag(tmp_path / "chatter"))
    with pytest.raises(BagError, match="no image topic /other"):
        list(read_bag(tmp_path / "good", topic="/other"))


def test_decode_image_names_the_problem():
    data = bytes(range(24))
    assert decode_image("mono8", 4, 6, 6, data).shape == (4, 6)
    assert decode_image("mono8", 3, 5, 8, data)[:, 4].tolist() == [4, 12, 20]  # padded rows
    assert decode_image("mono16", 2, 2, 6, data[:12], is_bigendian=True)[1, 0] == (6 << 8) + 7
    for args, match in [(("32FC1", 4, 3, 6, data), "unsupported image encoding '32FC1'"),
                        (("bgr8", 4, 3, 6, data), "step 6 is shorter than one row"),
                        (("mono8", 5, 6, 6, data), "24 bytes, step 6 x height 5 = 30 expected"),
                        (("mono8", 0, 6, 6, data), "size must be positive"),
                        (("mono8", 4, 6, 6, b""), "empty")]:
        with pytest.raises(ValueError, match=match):
            decode_image(*args)
    with pytest.raises(ValueError, match="cannot encode"):
        encode_image(np.zeros((4, 4), np.float32))
    assert encode_image(np.zeros((2, 3, 3), np.uint8))[:2] == ("bgr8", 9)


def test_bag_command(scene, tmp_path, capsys):
    args = [str(scene.folder), str(tmp_path / "bag"), "--storage", "sqlite3", "--rate", "2"]
    assert bag_cli.main(args) == 0
    assert len(list(read_bag(tmp_path / "bag"))) == 3
    assert bag_cli.main(args) == 2
    assert "exists already" in capsys.readouterr().err
