import numpy as np
import pytest
from scipy.spatial.transform import Rotation

from axispose_core.metrics import add, add_or_adi, adi, pose_scores, proj, re, te

CUBE = np.array([[x, y, z] for x in (-0.05, 0.05) for y in (-0.05, 0.05) for z in (-0.05, 0.05)])
K = np.array([[500.0, 0, 320], [0, 500.0, 240], [0, 0, 1]])
t0 = np.array([0.0, 0.0, 1.0])


def test_add_is_mean_point_distance_for_a_shift():
    assert add(np.eye(3), t0 + [0.01, 0, 0], np.eye(3), t0, CUBE) == pytest.approx(0.01)


def test_reprojection_of_a_lateral_shift_at_one_metre():
    # 1 cm sideways at 1 m with f = 500 px is 5 px for every point at depth 1 m; the cube's points sit at
    # depths 0.95 and 1.05, giving 500*0.01/0.95 and 500*0.01/1.05.
    expected = 0.5 * (5 / 0.95 + 5 / 1.05)
    assert proj(np.eye(3), t0 + [0.01, 0, 0], np.eye(3), t0, K, CUBE) == pytest.approx(expected)


def test_rotation_and_translation_errors():
    R = Rotation.from_euler("z", 30, degrees=True).as_matrix()
    assert re(R, np.eye(3)) == pytest.approx(30.0)
    assert re(np.eye(3), np.eye(3)) == 0.0
    assert re(Rotation.from_euler("x", 1e-9, degrees=True).as_matrix(), np.eye(3)) == pytest.approx(1e-9, rel=1e-3)
    assert te([0.0, 0.03, 0.04], [0, 0, 0]) == pytest.approx(0.05)


def test_symmetric_object_fails_add_and_passes_adi():
    # A cube turned 90 degrees about z looks the same: ADD sees a large error, ADD-S none.
    R = Rotation.from_euler("z", 90, degrees=True).as_matrix()
    diameter = np.linalg.norm(CUBE[0] - CUBE[-1])
    err_add = add(R, t0, np.eye(3), t0, CUBE)
    assert err_add == pytest.approx(0.1)  # corners at radius sqrt(2)*5 cm turn 90 degrees: chord 10 cm
    assert adi(R, t0, np.eye(3), t0, CUBE) == pytest.approx(0.0, abs=1e-12)
    assert add_or_adi(R, t0, np.eye(3), t0, CUBE, symmetric=True) == pytest.approx(0.0, abs=1e-12)
    sym = pose_scores(R, t0, np.eye(3), t0, K, CUBE, diameter, symmetric=True)
    asym = pose_scores(R, t0, np.eye(3), t0, K, CUBE, diameter, symmetric=False)
    assert sym["add_0.1d"] == 1.0 and asym["add_0.1d"] == 0.0


def test_thresholds_at_their_edges():
    diameter = 0.1
    s = pose_scores(np.eye(3), t0 + [0.015, 0, 0], np.eye(3), t0, K, CUBE, diameter, symmetric=False)
    assert s["add_0.1d"] == 0.0 and s["add_0.2d"] == 1.0  # 1.5 cm against 1 cm and 2 cm
    assert s["reproj_5px"] == 0.0 and s["reproj_15px"] == 1.0  # about 7.5 px
    assert s["trans_err_mm"] == pytest.approx(15.0)
    assert set(s) == {
        "add_err_m",
        "reproj_err_px",
        "add_0.1d",
        "add_0.2d",
        "reproj_5px",
        "reproj_15px",
        "rot_err_deg",
        "trans_err_mm",
    }
