"""Kinematics of Sec. 2.1 (Eq. 2.1-2.15): frames, axes and their invariants."""

from __future__ import annotations

import numpy as np
import pytest
from hypothesis import given
from hypothesis import strategies as st
from hypothesis.extra.numpy import arrays

from hal.errors import ShapeError
from hal.robot import Kinematics, RobotDescription, base_stator_rotation, rot_x, rot_y, rot_z

angles = arrays(np.float64, (7, 4), elements=st.floats(-np.pi, np.pi))


def test_base_rotation_matches_equations_2_1_to_2_9(description: RobotDescription) -> None:
    r = base_stator_rotation(description.geometry.base_rotation)
    assert r @ r.T == pytest.approx(np.eye(3), abs=1e-12)
    assert np.linalg.det(r) == pytest.approx(1.0)
    # Eq. 2.3-2.4 by hand: v1 = -(row 1 of Rz(-10 deg)) x (row 3 of Rx(-30 deg)), normalised.
    row1 = np.array([np.cos(np.deg2rad(-10)), -np.sin(np.deg2rad(-10)), 0.0])
    row3 = np.array([0.0, np.sin(np.deg2rad(-30)), np.cos(np.deg2rad(-30))])
    v1 = -np.cross(row1, row3)
    v1 /= np.linalg.norm(v1)
    assert r[:, 2] == pytest.approx(v1, abs=1e-12)  # the AoR of R1 is v1 (R_bar maps z to v1)
    # The AoR of R1 is tilted from the vertical (y up) by about 31 degrees, not vertical.
    assert np.degrees(np.arccos(v1[1])) == pytest.approx(31.1, abs=0.1)


@given(angles)
def test_rotor_rotations_are_rotations_and_chain_as_eq_2_14(q: np.ndarray) -> None:
    kin = Kinematics(RobotDescription.model_validate(_packaged()).geometry)
    rotors = kin.rotor_rotations(q)
    eye = np.broadcast_to(np.eye(3), rotors.shape)
    assert np.allclose(rotors @ np.swapaxes(rotors, -1, -2), eye, atol=1e-12)
    assert np.allclose(np.linalg.det(rotors), 1.0)
    r60 = rot_y(np.deg2rad(60.0))
    for n in range(q.shape[0]):
        r1 = kin.base_rotation @ rot_z(q[n, 0])
        r2 = r1 @ r60 @ rot_z(q[n, 1])
        r3 = r2 @ r60 @ rot_z(q[n, 2])
        r4 = r3 @ rot_z(q[n, 3])
        assert np.allclose(rotors[n], np.stack([r1, r2, r3, r4]), atol=1e-12)


@given(angles)
def test_axis_geometry_invariants(q: np.ndarray) -> None:
    kin = Kinematics(RobotDescription.model_validate(_packaged()).geometry)
    axes = kin.joint_axes(q)
    # Consecutive shoulder axes meet at 60 degrees whatever the configuration (Eq. 2.14).
    assert np.allclose(np.einsum("nk,nk->n", axes[:, 0], axes[:, 1]), 0.5)
    assert np.allclose(np.einsum("nk,nk->n", axes[:, 1], axes[:, 2]), 0.5)
    # R4 turns about an axis parallel to R3's (Eq. 2.15), 0.275 m away along the upper arm.
    assert np.allclose(axes[:, 2], axes[:, 3])
    origins = kin.frame_origins(q)
    assert np.allclose(origins[:, :3], 0.0)
    assert np.allclose(np.linalg.norm(origins[:, 3], axis=1), 0.275)
    assert np.allclose(np.einsum("nk,nk->n", origins[:, 3], axes[:, 2]), 0.0, atol=1e-12)


def test_vectorised_equals_single_configuration(description: RobotDescription, rng: np.random.Generator) -> None:
    kin = description.kinematics()
    q = rng.uniform(-2, 2, (20, 4))
    batch = kin.rotor_rotations(q)
    for n in range(q.shape[0]):
        assert np.array_equal(kin.rotor_rotations(q[n])[0], batch[n])


def test_point_in_world_of_elbow_point(description: RobotDescription) -> None:
    kin = description.kinematics()
    q = np.array([0.3, -0.2, 0.5, 1.1])
    # A point on the forearm 0.1 m from the elbow: elbow + R4 [0.1, 0, 0].
    expected = kin.rotor_rotations(q)[0, 2] @ [0.275, 0, 0] + kin.rotor_rotations(q)[0, 3] @ [0.1, 0, 0]
    assert kin.point_in_world(q, 4, [0.1, 0, 0])[0] == pytest.approx(expected)


def test_rotation_helpers_broadcast() -> None:
    a = np.array([[0.1, 0.2], [0.3, 0.4]])
    for rot in (rot_x, rot_y, rot_z):
        r = rot(a)
        assert r.shape == (2, 2, 3, 3)
        assert np.allclose(r[1, 0], rot(0.3))


def test_wrong_shape_is_refused(description: RobotDescription) -> None:
    with pytest.raises(ShapeError, match=r"\(N, 4\)"):
        description.kinematics().rotor_rotations(np.zeros((3, 5)))


def _packaged() -> dict:
    from importlib import resources

    import yaml

    return yaml.safe_load((resources.files("hal") / "daror01.yaml").read_text())
