"""Rotation helpers shared by the tasks, the action space and the recorders.

Conventions:
- quaternions are scalar-last ``(x, y, z, w)``, as in scipy and Foxglove;
- the 6D rotation is the first two *columns* of the rotation matrix, i.e. the
  end effector's x and y axes expressed in the world frame, concatenated as
  ``(r00, r10, r20, r01, r11, r21)`` (Zhou et al. 2019, as in diffusion_policy).
"""

from __future__ import annotations

import numpy as np
from scipy.spatial.transform import Rotation


def mat_to_rot6d(mat: np.ndarray) -> np.ndarray:
    """(..., 3, 3) rotation matrices -> (..., 6) first two columns."""
    mat = np.asarray(mat, dtype=np.float64)
    return np.concatenate([mat[..., :, 0], mat[..., :, 1]], axis=-1)


def rot6d_to_mat(rot6d: np.ndarray) -> np.ndarray:
    """(..., 6) -> (..., 3, 3) by Gram-Schmidt; tolerant to unnormalised input, and to degenerate input
    (a zero first column becomes x; a second column parallel to the first, or zero, is replaced by a
    direction perpendicular to it), so every 6D vector gives a rotation."""
    rot6d = np.asarray(rot6d, dtype=np.float64)
    a1, a2 = rot6d[..., 0:3], rot6d[..., 3:6]
    n1 = np.linalg.norm(a1, axis=-1, keepdims=True)
    b1 = np.where(n1 > 1e-9, a1 / np.clip(n1, 1e-9, None), np.array([1.0, 0.0, 0.0]))
    a2 = a2 - np.sum(b1 * a2, axis=-1, keepdims=True) * b1
    n2 = np.linalg.norm(a2, axis=-1, keepdims=True)
    if np.any(n2 <= 1e-9):  # the axis least aligned with b1, made perpendicular to it
        axis = np.eye(3)[np.argmin(np.abs(b1), axis=-1)]
        other = axis - np.sum(b1 * axis, axis=-1, keepdims=True) * b1
        a2 = np.where(n2 > 1e-9, a2, other)
        n2 = np.linalg.norm(a2, axis=-1, keepdims=True)
    b2 = a2 / np.clip(n2, 1e-9, None)
    b3 = np.cross(b1, b2)
    return np.stack([b1, b2, b3], axis=-1)


def quat_to_rot6d(quat_xyzw: np.ndarray) -> np.ndarray:
    return mat_to_rot6d(Rotation.from_quat(quat_xyzw).as_matrix())


def rot6d_to_rotvec(rot6d: np.ndarray) -> np.ndarray:
    return Rotation.from_matrix(rot6d_to_mat(rot6d)).as_rotvec()


def wxyz_to_xyzw(quat_wxyz: np.ndarray) -> np.ndarray:
    """MuJoCo stores quaternions scalar-first."""
    q = np.asarray(quat_wxyz, dtype=np.float64)
    return np.concatenate([q[..., 1:], q[..., :1]], axis=-1)


def wrap_angle(a: float | np.ndarray) -> float | np.ndarray:
    return (np.asarray(a) + np.pi) % (2 * np.pi) - np.pi
