"""Rigid fits of point sets: how far a block (a joint's or a beam's points) is turned and moved, apart from its shape.

The best rotation of one point set onto another is Kabsch's: with both centred, H = sum_i s_i t_i^T = U S V^T and
R = V diag(1, 1, det(V U^T)) U^T minimises sum_i |R s_i - t_i|^2 over proper rotations. Used by learn.diagnose to split
a rollout's error per block into orientation, placement and shape, and by learn.evaluate to take from a whole
answer's error the part a rigid motion of the whole explains (shape_error).
"""
from __future__ import annotations

import numpy as np


def best_rotation(source: np.ndarray, target: np.ndarray) -> np.ndarray:
    """[..., N, 3] two point sets, point i matching point i -> [..., 3, 3] the proper rotation R that best turns the
    centred source onto the centred target (Kabsch)."""
    s = source - source.mean(-2, keepdims=True)
    t = target - target.mean(-2, keepdims=True)
    U, _, Vt = np.linalg.svd(np.swapaxes(s, -1, -2) @ t)
    V, Ut = np.swapaxes(Vt, -1, -2), np.swapaxes(U, -1, -2)
    D = np.broadcast_to(np.eye(3), V.shape).copy()
    D[..., 2, 2] = np.where(np.linalg.det(V @ Ut) < 0, -1.0, 1.0)  # never a reflection
    return V @ D @ Ut


def rotation_angle_deg(R: np.ndarray) -> np.ndarray:
    """[..., 3, 3] rotations -> [...] the angle each turns by, degrees."""
    return np.degrees(np.arccos(np.clip((np.trace(R, axis1=-2, axis2=-1) - 1.0) / 2.0, -1.0, 1.0)))


def block_parts(predicted: np.ndarray, truth: np.ndarray, start: np.ndarray) -> dict[str, np.ndarray]:
    """[..., N, 3] a block's predicted and true points, and its true points at the start -> per block [...]:
    orientation_error_deg, the angle of the best rotation of the true block onto the predicted one;
    turn_deg, the angle the true block has turned since the start; placement (mm), the distance between the two
    blocks' centroids; shape (mm), the largest distance left once the true block is moved rigidly onto the
    predicted one (what no rotation or translation explains)."""
    R = best_rotation(truth, predicted)
    pc, tc = predicted.mean(-2, keepdims=True), truth.mean(-2, keepdims=True)
    fitted = (truth - tc) @ np.swapaxes(R, -1, -2) + pc
    return {"orientation_error_deg": rotation_angle_deg(R),
            "turn_deg": rotation_angle_deg(best_rotation(start, truth)),
            "placement": np.linalg.norm(pc - tc, axis=-1)[..., 0],
            "shape": np.linalg.norm(predicted - fitted, axis=-1).max(-1)}


def shape_error(predicted: np.ndarray, truth: np.ndarray) -> np.ndarray:
    """[..., N, 3] a whole answer's predicted and true points -> [...] the largest distance left once the predicted
    points are moved rigidly onto the true ones (the least-squares rotation and translation, Kabsch): the error of the
    shape itself, apart from how the whole answer is turned and where it sits, which the max point error counts too.
    The fit minimises the squared distances, not the largest, so this bounds the best rigid fit's largest distance
    from above."""
    R = best_rotation(predicted, truth)
    pc, tc = predicted.mean(-2, keepdims=True), truth.mean(-2, keepdims=True)
    fitted = (predicted - pc) @ np.swapaxes(R, -1, -2) + tc
    return np.linalg.norm(fitted - truth, axis=-1).max(-1)
