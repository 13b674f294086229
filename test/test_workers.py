"""The worker threads of one image (online/workers.py): chunks in order, the same poses with
1 and 2 workers, and parameter changes from another thread while an image is in flight."""
from __future__ import annotations

import subprocess
import sys
import threading
import time

import cv2
import numpy as np
import pytest

from brepose_ros.offline.compiler import compile_aspect_graph
from brepose_ros.online.estimator import Estimator
from brepose_ros.online.workers import WorkerPool, cpu_count, resolve_workers
from brepose_ros.params import EstimatorParams
from brepose_ros.scene_folder import load_scene
from brepose_ros.synthetic.scenes import SceneConfig, generate_scene


def test_map_keeps_the_order_and_uses_the_threads():
    pool = WorkerPool(3)
    try:
        threads = set()

        def square(x):
            threads.add(threading.get_ident())
            time.sleep(0.01)
            return x * x

        assert pool.map(square, list(range(12))) == [x * x for x in range(12)]
        assert threading.get_ident() in threads and len(threads) == 3
    finally:
        pool.close()


def test_a_failing_chunk_raises_in_the_caller_after_every_chunk_ended():
    pool = WorkerPool(2)
    ended = []

    def work(x):
        time.sleep(0.02)
        ended.append(x)
        if x == 1:
            raise ValueError("chunk 1")

    try:
        with pytest.raises(ValueError, match="chunk 1"):
            pool.map(work, [0, 1, 2, 3])
        assert sorted(ended) == [0, 1, 2, 3]
    finally:
        pool.close()


@pytest.mark.parametrize("size, count, minimum, lengths", [
    (2, 10, 1, [5, 5]), (2, 3, 1, [1, 2]), (4, 3, 1, [1, 1, 1]), (2, 100, 64, [100]), (2, 0, 1, [0]),
    (1, 7, 1, [7]),
])
def test_split_gives_contiguous_near_equal_chunks(size, count, minimum, lengths):
    pool = WorkerPool(size)
    chunks = pool.split(count, minimum)
    pool.close()
    assert [c.stop - c.start for c in chunks] == lengths
    assert chunks[0].start == 0 and chunks[-1].stop == count
    assert all(a.stop == b.start for a, b in zip(chunks[:-1], chunks[1:]))


@pytest.mark.parametrize("size, count, dealt", [
    (2, 5, [[0, 2, 4], [1, 3]]), (3, 2, [[0], [1]]), (1, 3, [[0, 1, 2]]), (2, 0, [[]]),
])
def test_deal_hands_every_index_out_once_round_robin(size, count, dealt):
    pool = WorkerPool(size)
    chunks = pool.deal(count)
    pool.close()
    assert [list(range(count))[c] for c in chunks] == dealt


def test_map_dealt_puts_every_chunks_arrays_back_in_order():
    pool = WorkerPool(2)
    values = np.arange(7.0)
    index, squares = pool.map_dealt(lambda which: (values[which], values[which] ** 2), len(values))
    pool.close()
    assert index.tolist() == values.tolist()  # dealt 0 2 4 6 / 1 3 5, back in place
    assert squares.tolist() == (values ** 2).tolist()


def test_zero_workers_means_one_per_core():
    assert resolve_workers(0) == cpu_count() >= 1 and resolve_workers(3) == 3


FAULTS_OF_A_SECOND_IMAGE = """
import resource, sys
import numpy as np
from brepose_ros.online.workers import keep_freed_memory
if sys.argv[1] == "keep":
    assert keep_freed_memory()


def image_maps():  # an image's evidence maps at two tolerances: 35 MB
    return [np.ones((2, 8, 482, 642), np.uint8), np.ones((2, 8, 482, 642), np.float32),
            np.ones((8, 480, 640), np.int32)]


first = image_maps()
del first
before = resource.getrusage(resource.RUSAGE_SELF).ru_minflt
second = image_maps()
print(resource.getrusage(resource.RUSAGE_SELF).ru_minflt - before)
"""


@pytest.mark.skipif(not sys.platform.startswith("linux"), reason="glibc's malloc")
def test_a_second_images_maps_reuse_the_first_images_memory_once_freed_memory_is_kept():
    def faults(mode: str) -> int:
        return int(subprocess.run([sys.executable, "-c", FAULTS_OF_A_SECOND_IMAGE, mode], check=True,
                                  capture_output=True, text=True).stdout)

    assert faults("default") > 500  # mapped afresh, handed back when freed: faulted in again
    assert faults("keep") < 100


@pytest.fixture(scope="module")
def cluttered(sample_step, tmp_path_factory):
    """A 15-degree graph of the sample part and three cluttered, occluded images of it."""
    folder = tmp_path_factory.mktemp("workers")
    graph = compile_aspect_graph(sample_step, step_deg=15.0, workers=1, progress=False)
    scene = generate_scene(sample_step, folder / "scene", 3, seed=5,
                           config=SceneConfig(width=320, height=240, fx=300.0, offcenter=True, clutter=2,
                                              occlusion=0.2))
    images = [cv2.imread(str(e.path), cv2.IMREAD_UNCHANGED) for e in load_scene(folder / "scene").entries]
    return graph, scene.camera, images


def poses(estimator: Estimator, images, camera) -> list[tuple]:
    return [pose_of(estimator.estimate(image, camera)) for image in images]


def pose_of(e) -> tuple:
    return (None if e.R is None else e.R.tobytes(), None if e.t is None else e.t.tobytes(), e.score)


def with_workers(params: EstimatorParams, workers: int) -> EstimatorParams:
    return params.with_flat({"matching.workers": workers})


def test_one_and_two_workers_give_the_same_poses_to_the_bit(cluttered):
    graph, camera, images = cluttered
    one, two = (Estimator(graph, with_workers(EstimatorParams(), w)) for w in (1, 2))
    try:
        first = poses(one, images, camera)
        assert first == poses(two, images, camera)
        assert any(R is not None for R, _, _ in first), "a scene where nothing is found tests little"
    finally:
        one.close()
        two.close()


def test_edges_found_once_for_several_estimators_give_each_the_same_poses(cluttered):
    """The node's parts share one image's edges (Estimator.detect, by the first part for all):
    each part's poses are those it finds detecting its own edges, to the bit."""
    graph, camera, images = cluttered
    first, other = Estimator(graph, with_workers(EstimatorParams(), 2)), Estimator(graph)
    try:
        for image in images:
            frame = first.detect(image, camera, [other])
            alone = pose_of(other.estimate(image, camera))
            assert pose_of(other.estimate(image, camera, frame=frame)) == alone
            assert pose_of(first.estimate(image, camera, frame=frame)) == alone
    finally:
        first.close()
        other.close()


def test_parameter_changes_from_another_thread_never_break_an_image_in_flight(cluttered):
    """Workers (the thread pool) and the view features change while images are estimated:
    every image is answered with the poses of one whole parameter set, never an error."""
    graph, camera, images = cluttered
    coarse = EstimatorParams().with_flat({"matching.max_model_segments": 12})
    settings = [with_workers(EstimatorParams(), 1), with_workers(coarse, 2), with_workers(EstimatorParams(), 2),
                with_workers(coarse, 1)]
    expected = []  # the poses of each view-feature set, unchanged throughout
    for params in settings[:2]:
        reference = Estimator(graph, params)
        expected.append(poses(reference, images, camera))
        reference.close()
    assert expected[0] != expected[1], "the two sets must give different poses to tell them apart"
    estimator = Estimator(graph, settings[0])
    stop, changes = threading.Event(), [0]

    def change():
        while not stop.is_set():
            estimator.params = settings[changes[0] % len(settings)]
            changes[0] += 1
            time.sleep(0.003)

    changer = threading.Thread(target=change)
    changer.start()
    try:
        rounds = 0
        while rounds < 3 or (changes[0] <= 20 and rounds < 30):  # fast images: go on until enough changes
            for i, image in enumerate(images):
                got = pose_of(estimator.estimate(image, camera))
                assert got in (expected[0][i], expected[1][i])
            rounds += 1
    finally:
        stop.set()
        changer.join()
        estimator.close()
    assert changes[0] > 20
