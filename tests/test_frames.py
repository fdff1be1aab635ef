"""Units and axes of uploads (service/model/formats/frames.py)."""
from __future__ import annotations

import numpy as np
import pytest
from scipy.spatial import cKDTree

from service.model.formats import frames as Fr
from service.model.body.lbs import axis_angle_to_matrix


def _person():
    pts = np.random.default_rng(0).normal(size=(500, 3)) * [0.2, 0.5, 0.1]
    pts[:, 1] = np.linspace(0, 1.75, 500)
    return pts


def test_unit_detection():
    pts = _person()
    assert Fr.detect_unit(pts) == ("m", 1.0)
    assert Fr.detect_unit(pts * 100)[0] == "cm"
    assert Fr.detect_unit(pts * 1000)[0] == "mm"
    with pytest.raises(Fr.UnitError, match="units"):
        Fr.detect_unit(pts * 10)


def test_up_candidates():
    pts = _person()
    labels = [label for label, _ in Fr.up_candidates(pts[:, [0, 2, 1]])]
    assert labels == ["+z", "-z"]
    for label, R in Fr.up_candidates(pts[:, [0, 2, 1]]):
        assert np.allclose(R @ np.eye(3)[2] * (1 if label == "+z" else -1), [0, 1, 0])
        assert Fr.up_label(R) == label


@pytest.mark.parametrize("axis", range(6))
def test_rotation_to_y_is_the_quarter_or_half_turn(axis):
    u = np.vstack([np.eye(3), -np.eye(3)])[axis]
    R = Fr.rotation_to_y(u)
    assert np.allclose(R @ u, [0, 1, 0]) and np.isclose(np.linalg.det(R), 1.0)
    if abs(u[1]) < 0.5:
        k = np.cross(u, [0.0, 1.0, 0.0])
        assert np.allclose(R, axis_angle_to_matrix(k / np.linalg.norm(k) * np.pi / 2))


def test_unit_against_a_reference_body():
    body = _person()
    tree = cKDTree(body)
    garment = body[::7] + 0.01
    assert Fr.unit_against(garment * 100, tree)[0] == "cm"
    assert Fr.unit_against(garment * 1000, tree)[0] == "mm"
    assert Fr.unit_against(garment, tree)[0] == "m"


def test_nearest_axis_rotation_and_kabsch():
    rng = np.random.default_rng(2)
    Q = Fr.AXIS_ROTATIONS[5]
    R = axis_angle_to_matrix(rng.normal(size=3) * 0.05) @ Q
    assert np.allclose(Fr.nearest_axis_rotation(R), Q)
    src = rng.normal(size=(30, 3))
    R2, t2 = Fr.kabsch(src, src @ R.T + [1, 2, 3])
    assert np.allclose(R2, R, atol=1e-9) and np.allclose(t2, [1, 2, 3])
