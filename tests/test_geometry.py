import json

import numpy as np
import pytest

from weatheralign.geometry import (
    NonRigidTransformError,
    apply,
    camera_rotation_from_yaw,
    check_rigid,
    interpolate_poses,
    invert,
    make_transform,
    project,
    quaternion_wxyz,
    transform_from_quaternion,
    yaw_matrix,
)


def test_quaternion_round_trip():
    rng = np.random.default_rng(0)
    for _ in range(20):
        q = rng.normal(size=4)
        q /= np.linalg.norm(q)
        T = transform_from_quaternion(q, rng.normal(size=3))
        q2 = quaternion_wxyz(T[:3, :3])
        assert np.allclose(transform_from_quaternion(q2, T[:3, 3]), T, atol=1e-12)
        assert q2[0] >= 0


def test_yaw_quaternion_matches_closed_form():
    q = quaternion_wxyz(yaw_matrix(0.7))
    assert np.allclose(q, [np.cos(0.35), 0, 0, np.sin(0.35)])


def test_invert_and_apply():
    T = make_transform(yaw_matrix(1.1), np.array([3.0, -2.0, 0.5]))
    p = np.random.default_rng(1).normal(size=(10, 3))
    assert np.allclose(apply(invert(T), apply(T, p)), p)
    assert np.array_equal(apply(T, p), p @ T[:3, :3].T + T[:3, 3])  # the inline form it replaces, bit for bit


def test_invert_is_the_closed_form_rigid_inverse():
    rng = np.random.default_rng(7)
    for _ in range(20):
        q = rng.normal(size=4)
        T = transform_from_quaternion(q / np.linalg.norm(q), rng.normal(scale=500.0, size=3))
        Ti = invert(T)
        R, t = T[:3, :3], T[:3, 3]
        assert np.array_equal(Ti[:3, :3], R.T) and np.array_equal(Ti[:3, 3], -R.T @ t)
        assert np.array_equal(Ti[3], [0.0, 0.0, 0.0, 1.0])
        np.testing.assert_allclose(Ti @ T, np.eye(4), atol=1e-12)
        np.testing.assert_allclose(T @ Ti, np.eye(4), atol=1e-12)
        np.testing.assert_allclose(Ti, np.linalg.inv(T), rtol=0, atol=1e-12)
    # not a general inverse: a scaled matrix is not inverted (callers use np.linalg.inv for non-rigid matrices)
    S = np.diag([2.0, 2.0, 2.0, 1.0])
    assert not np.allclose(invert(S) @ S, np.eye(4))


@pytest.mark.parametrize("bad, match", [
    (np.eye(3), "4x4"),
    (np.diag([1.0, 1.0, 2.0, 1.0]), "orthonormal"),
    (np.diag([1.0, 1.0, -1.0, 1.0]), "det"),
    (np.array([[1, 0, 0, 0], [0, 1, 0, 0], [0, 0, 1, 0], [0, 0, 1, 1.0]]), "last row"),
    (np.full((4, 4), np.nan), "NaN"),
])
def test_check_rigid_rejects(bad, match):
    with pytest.raises(NonRigidTransformError, match=match):
        check_rigid(bad, "T_test")


def test_interpolate_poses_linear_and_slerp():
    T0 = make_transform(yaw_matrix(0.0), np.zeros(3))
    T1 = make_transform(yaw_matrix(0.4), np.array([2.0, 0, 0]))
    out = interpolate_poses(np.array([0.0, 0.5, 1.0, 2.0]), np.array([0.0, 1.0]), np.stack([T0, T1]))
    assert np.allclose(out[1][:3, 3], [1.0, 0, 0])
    assert np.allclose(out[1][:3, :3], yaw_matrix(0.2))
    assert np.allclose(out[3], T1)  # clamped


def test_camera_rotation_projects_forward_point_to_principal_point():
    K = np.array([[1000.0, 0, 800], [0, 1000.0, 450], [0, 0, 1]])
    for yaw in (0.0, 1.0, -2.0):
        R = camera_rotation_from_yaw(yaw)
        p_ego = np.array([[np.cos(yaw) * 10, np.sin(yaw) * 10, 0.0], [np.cos(yaw) * 10, np.sin(yaw) * 10, 1.0]])
        uv, z = project(p_ego @ R, K)  # R^T p
        assert np.allclose(uv[0], [800, 450]) and np.allclose(z, 10)
        assert uv[1, 1] < 450  # up in the world is up in the image


def test_atomic_write_leaves_no_partial_file_and_readable_output(tmp_path):
    from weatheralign import atomic

    target = tmp_path / "sub" / "out.json"
    atomic.write_json(target, {"a": 1})
    assert json.loads(target.read_text()) == {"a": 1} and (target.stat().st_mode & 0o777) == 0o644
    with pytest.raises(RuntimeError):
        with atomic.atomic_path(tmp_path / "sub" / "half.bin") as tmp:
            tmp.write_bytes(b"partial")
            raise RuntimeError("interrupted")
    assert sorted(p.name for p in (tmp_path / "sub").iterdir()) == ["out.json"]


@pytest.mark.parametrize("compress", [True, False])
def test_save_npz_round_trips_byte_identically(tmp_path, compress):
    """Both forms load back exactly, are the same bytes when written twice (fixed member dates) and differ in size as
    their names say."""
    import time

    from weatheralign import atomic

    arrays = {"a": np.arange(5000, dtype=np.int16) % 7, "b": np.linspace(0, 1, 30).astype(np.float32).reshape(5, 6)}
    atomic.save_npz(tmp_path / "x.npz", arrays, compress)
    time.sleep(1.1)  # zip dates have a 2 s resolution: a stamped time could still coincide without the pause
    atomic.save_npz(tmp_path / "y.npz", arrays, compress)
    assert (tmp_path / "x.npz").read_bytes() == (tmp_path / "y.npz").read_bytes()
    with np.load(tmp_path / "x.npz") as z:
        assert list(z) == ["a", "b"] and all(np.array_equal(z[k], v) and z[k].dtype == v.dtype
                                             for k, v in arrays.items())
    stored = sum(v.nbytes for v in arrays.values())
    assert ((tmp_path / "x.npz").stat().st_size < stored) == compress
    if compress:  # deflate level 1, as documented (a ZipInfo written through ZipFile.open would get level 6)
        import io
        import zipfile
        import zlib

        raw = io.BytesIO()
        np.lib.format.write_array(raw, arrays["a"], allow_pickle=False)
        level1 = zlib.compressobj(1, zlib.DEFLATED, -15)
        with zipfile.ZipFile(tmp_path / "x.npz") as zf:
            assert zf.getinfo("a.npy").compress_size == len(level1.compress(raw.getvalue()) + level1.flush())
