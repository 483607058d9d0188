"""Rigid transforms, quaternions and pinhole projection.

Conventions: 4x4 float64 homogeneous transforms named ``T_<to>_<from>`` applied as ``T @ p``; quaternions in the
nuScenes order ``(w, x, y, z)``; camera frames are OpenCV (x right, y down, z forward).
"""

from __future__ import annotations

import numpy as np
from numpy.typing import NDArray
from scipy.spatial.transform import Rotation, Slerp

F64 = NDArray[np.float64]


class NonRigidTransformError(ValueError):
    """A 4x4 matrix that is not a proper rigid transform (rotation not orthonormal, det != 1, bad last row)."""


def make_transform(rotation: F64, translation: F64) -> F64:
    """Build ``T`` (4, 4) from a rotation matrix (3, 3) and a translation (3,) in metres."""
    T = np.eye(4)
    T[:3, :3] = rotation
    T[:3, 3] = translation
    return T


def transform_from_quaternion(rotation_wxyz: F64 | list[float], translation: F64 | list[float]) -> F64:
    """``T`` (4, 4) from a nuScenes ``rotation`` (w, x, y, z) and ``translation`` (3,)."""
    w, x, y, z = np.asarray(rotation_wxyz, dtype=np.float64)
    return make_transform(Rotation.from_quat([x, y, z, w]).as_matrix(), np.asarray(translation, dtype=np.float64))


def quaternion_wxyz(rotation: F64) -> list[float]:
    """The nuScenes (w, x, y, z) quaternion of a rotation matrix (3, 3), with w >= 0."""
    x, y, z, w = Rotation.from_matrix(rotation).as_quat()
    q = np.array([w, x, y, z])
    if q[0] < 0:
        q = -q
    return [float(v) for v in q]


def yaw_matrix(yaw: float) -> F64:
    """Rotation (3, 3) by ``yaw`` radians about +z."""
    c, s = np.cos(yaw), np.sin(yaw)
    return np.array([[c, -s, 0.0], [s, c, 0.0], [0.0, 0.0, 1.0]])


def invert(T: F64) -> F64:
    """Inverse of a rigid transform ``T = [R | t]`` (4, 4) by its closed form ``[Rᵀ | -Rᵀ t]``.

    Uses only that ``R`` is orthonormal (no LU factorisation as in ``np.linalg.inv``): for a rigid ``T`` it agrees
    with ``np.linalg.inv`` to rounding (~1e-16 relative), but not bit for bit. For a matrix that is only nearly rigid
    (e.g. KITTI's float32-printed calibration, orthonormal to ~1e-7) use ``np.linalg.inv``.
    """
    R = T[:3, :3]
    out = np.eye(4)
    out[:3, :3] = R.T
    out[:3, 3] = -R.T @ T[:3, 3]
    return out


def apply(T: F64, points: NDArray) -> F64:
    """Apply ``T`` (4, 4) to points (N, 3) -> (N, 3) float64."""
    p = np.asarray(points, dtype=np.float64)
    return p @ T[:3, :3].T + T[:3, 3]


def check_rigid(T: NDArray, what: str, tol: float = 1e-4) -> F64:
    """Return ``T`` as float64 (4, 4) or raise `NonRigidTransformError` naming ``what``."""
    T = np.asarray(T, dtype=np.float64)
    if T.shape != (4, 4):
        raise NonRigidTransformError(f"{what}: expected a 4x4 transform, got shape {T.shape}")
    if not np.all(np.isfinite(T)):
        raise NonRigidTransformError(f"{what}: contains NaN or inf")
    if not np.allclose(T[3], [0, 0, 0, 1], atol=tol):
        raise NonRigidTransformError(f"{what}: last row must be [0, 0, 0, 1], got {T[3].tolist()}")
    R = T[:3, :3]
    err = float(np.abs(R @ R.T - np.eye(3)).max())
    det = float(np.linalg.det(R))
    if err > tol or abs(det - 1.0) > tol:
        raise NonRigidTransformError(
            f"{what}: rotation part is not orthonormal with det +1 (max |R R^T - I| = {err:.2e}, det = {det:.6f})"
        )
    return T


def interpolate_poses(times: NDArray, pose_times: NDArray, poses: NDArray) -> F64:
    """Poses (N, 4, 4) at ``times`` (N,) s, interpolated (slerp + linear) between ``poses`` (K, 4, 4) at
    ``pose_times`` (K,) s; times outside the range are clamped to the end poses."""
    pose_times = np.asarray(pose_times, dtype=np.float64)
    times = np.clip(np.asarray(times, dtype=np.float64), pose_times[0], pose_times[-1])
    out = np.tile(np.eye(4), (len(times), 1, 1))
    if len(pose_times) == 1:
        out[:] = poses[0]
        return out
    slerp = Slerp(pose_times, Rotation.from_matrix(poses[:, :3, :3]))
    out[:, :3, :3] = slerp(times).as_matrix()
    for k in range(3):
        out[:, k, 3] = np.interp(times, pose_times, poses[:, k, 3])
    return out


def project(points_cam: NDArray, K: F64) -> tuple[F64, F64]:
    """Pinhole projection of camera-frame points (N, 3) with intrinsics ``K`` (3, 3).

    Returns:
        uv (N, 2) pixel coordinates (pixel centres at integer + 0.5 is NOT assumed: u = fx x/z + cx),
        z (N,) depth along the optical axis in metres (<= 0 means behind the camera).
    """
    p = np.asarray(points_cam, dtype=np.float64)
    z = p[:, 2]
    with np.errstate(divide="ignore", invalid="ignore"):
        u = K[0, 0] * p[:, 0] / z + K[0, 1] * p[:, 1] / z + K[0, 2]
        v = K[1, 1] * p[:, 1] / z + K[1, 2]
    return np.stack([u, v], axis=1), z


def camera_rotation_from_yaw(yaw: float) -> F64:
    """Rotation ``R_ego_cam`` (3, 3) of an upright OpenCV camera looking along ego yaw ``yaw`` (rad, 0 = forward)."""
    c, s = np.cos(yaw), np.sin(yaw)
    x_axis = np.array([s, -c, 0.0])  # image right
    y_axis = np.array([0.0, 0.0, -1.0])  # image down
    z_axis = np.array([c, s, 0.0])  # optical axis
    return np.stack([x_axis, y_axis, z_axis], axis=1)
