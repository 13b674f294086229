"""The pose covariance (PoseWithCovarianceStamped) predicts the scatter of the refined pose.

Many copies of one scene, each with its own Gaussian noise on the image lines, are refined
in one batch; the covariance each refinement reports must match the covariance of the
poses they reach around the true one (Monte Carlo), in size and in every direction.
"""
from __future__ import annotations

import cv2
import numpy as np

from brepose_ros.geometry import rot_z
from brepose_ros.online.refinement import refine_poses

TRIALS = 400
NOISE = 0.002  # normalised units: 1 pixel at a 500-pixel focal length


def test_covariance_matches_the_scatter_of_refined_poses():
    rng = np.random.default_rng(7)
    points = rng.uniform(-0.05, 0.05, (40, 3))
    R_true, t_true = rot_z(0.3) @ cv2.Rodrigues(np.array([0.4, -0.2, 0.1]))[0], np.array([0.01, -0.02, 0.5])
    cam = points @ R_true.T + t_true
    image = cam[:, :2] / cam[:, 2:]
    model, lines = [], []
    for _ in range(TRIALS):
        angle = rng.uniform(0, np.pi, len(points))
        direction = np.stack([np.cos(angle), np.sin(angle)], axis=1)
        normal = np.stack([-direction[:, 1], direction[:, 0]], axis=1)
        shifted = image + NOISE * rng.standard_normal((len(points), 1)) * normal
        lines.append(np.stack([shifted - direction, shifted + direction], axis=1))
        model.append(points[:, None])
    spans = np.arange(TRIALS + 1) * len(points)
    R0 = np.repeat((cv2.Rodrigues(np.array([0.01, 0.0, -0.01]))[0] @ R_true)[None], TRIALS, axis=0)
    t0 = np.repeat((t_true + [0.002, 0.0, 0.01])[None], TRIALS, axis=0)
    covariance = np.full((TRIALS, 6, 6), np.nan)
    R, t = refine_poses(R0, t0, np.concatenate(model), np.concatenate(lines), spans, f_scale=1.0, iterations=10,
                        covariance_out=covariance)
    rotation_error = np.array([cv2.Rodrigues(R_b @ R_true.T)[0][:, 0] for R_b in R])  # exp(w) R_true = R_b
    errors = np.hstack([t - t_true, rotation_error])
    empirical = np.cov(errors.T)
    predicted = covariance.mean(axis=0)
    ratio = np.diag(predicted) / np.diag(empirical)
    assert np.all((ratio > 0.75) & (ratio < 1.33)), ratio
    # the whole matrix, correlations included: whitened by the prediction, the scatter is
    # the identity in every direction (within the Monte Carlo noise of 400 trials)
    whiten = np.linalg.inv(np.linalg.cholesky(predicted))
    assert np.all(np.abs(np.linalg.eigvalsh(whiten @ empirical @ whiten.T) - 1.0) < 0.3)
    assert np.allclose(predicted, predicted.T)
