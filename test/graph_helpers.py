"""Small aspect graphs built in memory for the maths tests (no CAD stack, no compile)."""
import numpy as np

from brepose_ros.aspect_graph import AspectGraph


def one_view_graph(xy_metres, seg_3d=None, diameter: float = 1.0) -> AspectGraph:
    """An aspect graph of one view whose sections have these view coordinates (and these
    model coordinates, zeros if not given)."""
    n = len(xy_metres)
    return AspectGraph(step_sha256="", params={}, model_center=np.zeros(3), model_diameter=diameter, n_faces=1,
                       view_directions=np.array([[0.0, 0.0, 1.0]]), view_rotations=np.eye(3)[None],
                       seg_offsets=np.array([0, n]), seg_xy=np.asarray(xy_metres, np.float32),
                       xy_origin=np.zeros((1, 2)), xy_scale=np.ones(1),
                       seg_3d=np.zeros((n, 2, 3)) if seg_3d is None else np.asarray(seg_3d, float),
                       seg_kind=np.zeros(n, np.uint8))
