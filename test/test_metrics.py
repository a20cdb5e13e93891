import numpy as np
import pytest
from scipy.spatial.transform import Rotation

from axispose_core.metrics import add, add_or_adi, adi, nearest_truth, pose_scores, proj, re, te

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
    sym = pose_scores(R, t0, np.eye(3), t0, K, CUBE, diameter, symmetries=())
    asym = pose_scores(R, t0, np.eye(3), t0, K, CUBE, diameter)
    assert sym["add_0.1d"] == 1.0 and asym["add_0.1d"] == 0.0


def test_symmetric_rotation_and_reprojection_errors_are_minimised_over_the_equivalent_poses():
    # The cube's half turn about z is one of its symmetries: an estimate 10 degrees off that turned pose is 10
    # degrees off, not 170, when the symmetries are given; for an asymmetric object it is 170.
    half = (Rotation.from_euler("z", 180, degrees=True).as_matrix(), np.zeros(3))
    syms = [(np.eye(3), np.zeros(3)), half]
    R = Rotation.from_euler("z", 170, degrees=True).as_matrix()
    diameter = np.linalg.norm(CUBE[0] - CUBE[-1])
    sym = pose_scores(R, t0, np.eye(3), t0, K, CUBE, diameter, symmetries=syms)
    plain = pose_scores(R, t0, np.eye(3), t0, K, CUBE, diameter)
    assert sym["rot_err_deg"] == pytest.approx(10.0) and plain["rot_err_deg"] == pytest.approx(170.0)
    assert sym["reproj_err_px"] == pytest.approx(proj(R @ half[0].T, t0, np.eye(3), t0, K, CUBE))
    assert sym["reproj_err_px"] < plain["reproj_err_px"] / 5
    R_ref, t_ref = nearest_truth(R, np.eye(3), t0, syms)
    assert re(R_ref, half[0]) == pytest.approx(0.0, abs=1e-9) and np.allclose(t_ref, t0)


def test_thresholds_at_their_edges():
    diameter = 0.1
    s = pose_scores(np.eye(3), t0 + [0.015, 0, 0], np.eye(3), t0, K, CUBE, diameter)
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
