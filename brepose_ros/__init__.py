"""brepose_ros: find a texture-less industrial part in one camera image from its CAD model.

The pipeline, in the order the data flows:

    offline/     CAD -> aspect graph: STEP reading (cad), hidden-line removal per view
                 (hidden_lines), the compiler that writes MODEL.brepose.npz (compiler)
    online/      image -> pose: image edges, matching, refinement, scoring and the
                 estimator that wires them
    ros/         the rclpy node, its message helpers, bag I/O and replay tools
    synthetic/   built-in parts, a renderer and scenes with exact ground truth
    evaluation/  metrics (../shared/CONVENTIONS.md) and overlays
    cli/         the brepose-* commands

Shared by both halves, plain numpy: ``aspect_graph`` (the file format), ``metric_space``
(the paper's normalisation and tetrads), ``viewsphere``, ``geometry``, ``camera``,
``params``, ``image_codec`` and ``scene_folder``. Dependencies point one way: nothing
imports ``ros`` but the scripts, and nothing on the online path imports the CAD stack.
"""

__version__ = "0.2.0"
