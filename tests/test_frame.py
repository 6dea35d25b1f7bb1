"""PCA tunnel frame: axis direction against synthetic truth, frame algebra, non-tunnels."""

from __future__ import annotations

import numpy as np
import pytest

from tunneldef.errors import NotATunnelError
from tunneldef.frame import pca_axes, principal_frame
from tunneldef.synth import TunnelSpec, make_tunnel


def _rot_z(deg: float) -> np.ndarray:
    a = np.radians(deg)
    return np.array([[np.cos(a), -np.sin(a), 0.0], [np.sin(a), np.cos(a), 0.0], [0.0, 0.0, 1.0]])


def _rot_y(deg: float) -> np.ndarray:
    a = np.radians(deg)
    return np.array([[np.cos(a), 0.0, np.sin(a)], [0.0, 1.0, 0.0], [-np.sin(a), 0.0, np.cos(a)]])


@pytest.fixture(scope="module")
def tunnel() -> np.ndarray:
    # straight design axis along +x (synth's design frame), pipes and a conveyor on one side
    cloud, truth = make_tunnel(
        TunnelSpec(length=30.0, density=60.0, equipment=True, conveyor=True), seed=3
    )
    axis = truth.centerline.points[-1] - truth.centerline.points[0]
    assert np.allclose(axis / np.linalg.norm(axis), [1.0, 0.0, 0.0])
    return cloud.xyz


def _angle_deg(a: np.ndarray, b: np.ndarray) -> float:
    """Angle between two lines (sign-free), degrees."""
    c = abs(float(a @ b)) / (np.linalg.norm(a) * np.linalg.norm(b))
    return float(np.degrees(np.arccos(min(c, 1.0))))


@pytest.mark.parametrize("yaw", [0.0, 23.0, 90.0, 137.5, 211.0, 333.3])
def test_axis_at_any_yaw_within_0_2_deg(tunnel: np.ndarray, yaw: float) -> None:
    r = _rot_z(yaw)
    xyz = tunnel @ r.T + np.array([350_000.0, -5_120_000.0, 415.0])  # survey-sized offsets
    frame = principal_frame(xyz)
    assert _angle_deg(frame.axes[0], r @ [1.0, 0.0, 0.0]) < 0.2
    assert np.allclose(frame.axes[2], [0.0, 0.0, 1.0])  # world z kept vertical
    assert np.allclose(frame.axes @ frame.axes.T, np.eye(3), atol=1e-12)
    assert np.linalg.det(frame.axes) == pytest.approx(1.0)
    # y points to the left of x
    assert np.allclose(np.cross(frame.axes[0], frame.axes[1]), frame.axes[2])
    assert frame.elongation > 2.5


def test_pca_vertical_follows_a_tilted_cloud(tunnel: np.ndarray) -> None:
    r = _rot_z(40.0) @ _rot_y(-4.0)  # tunnel rising 4 degrees
    xyz = tunnel @ r.T
    frame = principal_frame(xyz, vertical="pca")
    assert _angle_deg(frame.axes[0], r @ [1.0, 0.0, 0.0]) < 0.2
    # the world-vertical frame keeps z = world up and projects the axis horizontally
    world = principal_frame(xyz)
    assert np.allclose(world.axes[2], [0, 0, 1])
    assert _angle_deg(world.axes[0], r @ [1.0, 0.0, 0.0]) == pytest.approx(4.0, abs=0.2)


def test_local_world_round_trip_and_matrix(tunnel: np.ndarray) -> None:
    xyz = tunnel[:1000] @ _rot_z(70.0).T + [10.0, 20.0, 30.0]
    frame = principal_frame(tunnel @ _rot_z(70.0).T + [10.0, 20.0, 30.0])
    local = frame.to_local(xyz)
    assert np.allclose(frame.to_world(local), xyz, atol=1e-9)
    hom = np.c_[xyz, np.ones(len(xyz))] @ frame.matrix.T
    assert np.allclose(hom[:, :3], local, atol=1e-9)


def test_pca_axes_sorted_and_right_handed() -> None:
    rng = np.random.default_rng(0)
    pts = rng.normal(size=(5000, 3)) * [5.0, 2.0, 0.5]
    _, axes, var = pca_axes(pts)
    assert np.all(np.diff(var) < 0)
    assert np.linalg.det(axes) == pytest.approx(1.0)
    assert _angle_deg(axes[0], np.array([1.0, 0, 0])) < 2.0


def test_blob_is_not_a_tunnel() -> None:
    rng = np.random.default_rng(1)
    blob = rng.normal(size=(20_000, 3)) * [3.0, 2.8, 2.0]
    with pytest.raises(NotATunnelError, match="not elongated"):
        principal_frame(blob)


def test_square_plane_is_not_a_tunnel() -> None:
    rng = np.random.default_rng(2)
    plane = np.c_[rng.uniform(0, 10, (20_000, 2)), rng.normal(0, 0.01, 20_000)]
    with pytest.raises(NotATunnelError, match="not elongated"):
        principal_frame(plane)
