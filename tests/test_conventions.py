import numpy as np
import pytest

from jtus.data import conventions as cv


def test_motion_units_and_axes():
    mv = np.array([[0.25, 0.5]])
    np.testing.assert_allclose(cv.motion_to_jtus(mv, 8, 4, units="uv"), [[2.0, 2.0]])
    np.testing.assert_allclose(cv.motion_to_jtus(mv, 8, 4, units="ndc", y_up=True), [[1.0, -1.0]])
    np.testing.assert_allclose(cv.motion_to_jtus(mv, 8, 4, negate=True), [[-0.25, -0.5]])
    with pytest.raises(ValueError, match="units"):
        cv.motion_to_jtus(mv, 8, 4, units="mm")
    with pytest.raises(ValueError, match="motion"):
        cv.motion_to_jtus(np.zeros((3,)), 8, 4)


def test_jitter_kinds():
    np.testing.assert_allclose(cv.jitter_to_jtus([[-0.25, 0.25]], "centered"), [[0.25, 0.75]])
    np.testing.assert_allclose(cv.jitter_to_jtus([[0.25, 0.25]], y_up=True), [[0.25, 0.75]])


@pytest.mark.parametrize("kind", ["reversed", "linear", "view"])
def test_depth_round_trips_through_device(kind):
    near, far = 0.1, 100.0
    z = np.array([0.1, 0.5, 3.0, 42.0, 100.0])
    device = far / (far - near) * (1 - near / z)
    np.testing.assert_allclose(cv.view_depth(device, near, far), z, rtol=1e-12)
    src = {"reversed": 1 - device, "linear": (z - near) / (far - near), "view": z}[kind]
    np.testing.assert_allclose(cv.depth_to_device(src, kind, near, far), device, atol=1e-12)
    np.testing.assert_allclose(cv.linearize_depth(device, near, far), (z - near) / (far - near),
                               atol=1e-12)


def test_depth_planes_checked():
    with pytest.raises(ValueError, match="near/far"):
        cv.depth_to_device([0.5], "view", 1.0, 0.5)
