"""brepose_ros: find a texture-less industrial part in one camera image from its STEP model.

Pipeline, one module per stage (ROS-free except ``node``):

    cad            STEP file -> OpenCascade shape in metres
    viewsphere     viewpoints on a sphere around the part
    aspect_graph   visible edges of every view (exact hidden-line removal), saved as .npz
    image_edges    Canny + Hough line segments of a camera image, merged
    metric_space   translation/scale normalisation and edge tetrads
    matching       distance matrix + Kuhn-Munkres with empty elements, view ranking
    pose           view + in-plane rotation + scale -> metric 6-DoF pose, refinement
    estimator      the whole online pipeline behind one call
    node           the rclpy adapter
"""

__version__ = "0.1.0"
