import struct

import numpy as np
import pytest
from diagnostic_msgs.msg import DiagnosticArray
from geometry_msgs.msg import PoseStamped
from rclpy.serialization import serialize_message
from sensor_msgs.msg import CameraInfo, Image
from std_msgs.msg import Header

from axispose_core.lmo import LMO_K
from axispose_ros.conversions import (
    InputError,
    Undistorter,
    camera_for_image,
    camera_from_info,
    cdr_stamp,
    check_frame,
    image_to_rgb,
    rgb_to_image,
)
from axispose_ros.sync import STAMP_ANOMALIES, StampAudit, StampSynchronizer


def _image(pixels: np.ndarray, encoding: str, pad: int = 0) -> Image:
    h, w = pixels.shape[:2]
    c = 1 if pixels.ndim == 2 else pixels.shape[2]
    rows = np.zeros((h, w * c + pad), np.uint8)
    rows[:, : w * c] = pixels.reshape(h, w * c)
    msg = Image(height=h, width=w, encoding=encoding, step=w * c + pad)
    msg.data = rows.tobytes()
    return msg


@pytest.mark.parametrize("pad", [0, 7])
def test_every_supported_encoding_reads_as_rgb(rng, pad):
    rgb = rng.integers(0, 256, (5, 6, 3), dtype=np.uint8)
    alpha = np.full((5, 6, 1), 200, np.uint8)
    np.testing.assert_array_equal(image_to_rgb(_image(rgb, "rgb8", pad)), rgb)
    np.testing.assert_array_equal(image_to_rgb(_image(rgb[..., ::-1], "bgr8", pad)), rgb)
    np.testing.assert_array_equal(image_to_rgb(_image(np.concatenate([rgb, alpha], 2), "rgba8", pad)), rgb)
    np.testing.assert_array_equal(image_to_rgb(_image(np.concatenate([rgb[..., ::-1], alpha], 2), "bgra8", pad)), rgb)
    mono = rgb[..., 0]
    np.testing.assert_array_equal(image_to_rgb(_image(mono, "mono8", pad)), np.repeat(mono[..., None], 3, 2))


def test_round_trip_keeps_the_header(rng):
    rgb = rng.integers(0, 256, (4, 3, 3), dtype=np.uint8)
    header = Header(frame_id="camera_optical")
    header.stamp.sec, header.stamp.nanosec = 12, 345
    msg = rgb_to_image(rgb, header)
    assert msg.header.frame_id == "camera_optical" and msg.header.stamp.nanosec == 345
    np.testing.assert_array_equal(image_to_rgb(msg), rgb)


def test_a_stamp_is_read_from_serialized_bytes():
    header = Header(frame_id="camera_optical")
    header.stamp.sec, header.stamp.nanosec = 1_700_000_123, 999_999_999
    assert cdr_stamp(serialize_message(PoseStamped(header=header))) == 1_700_000_123_999_999_999
    assert cdr_stamp(serialize_message(DiagnosticArray(header=header))) == 1_700_000_123_999_999_999
    big_endian = bytes([0, 0, 0, 0]) + struct.pack(">iI", 42, 7)  # CDR_BE encapsulation
    assert cdr_stamp(big_endian) == 42 * 10**9 + 7
    assert cdr_stamp(bytes(8)) is None


@pytest.mark.parametrize(
    "mutate, reason",
    [
        (lambda m: setattr(m, "encoding", "16UC1"), "encoding"),
        (lambda m: setattr(m, "encoding", "x\n" * 40), "encoding"),
        (lambda m: setattr(m, "step", 2), "image_step"),
        (lambda m: setattr(m, "data", bytes(10)), "image_data"),
        (lambda m: setattr(m, "height", 0), "image_size"),
    ],
)
def test_bad_images_are_refused_with_a_reason(mutate, reason):
    msg = _image(np.zeros((4, 4, 3), np.uint8), "rgb8")
    mutate(msg)
    with pytest.raises(InputError) as err:
        image_to_rgb(msg)
    assert err.value.reason == reason
    assert "\n" not in str(err.value) and len(str(err.value)) < 200  # what the node logs: one short line
    with pytest.raises(InputError) as early:  # the node's check on arrival finds the same, without the pixels
        check_frame(msg, _info(w=4, h=4))
    assert early.value.reason == reason


def _info(K=LMO_K, w=640, h=480) -> CameraInfo:
    info = CameraInfo(width=w, height=h)
    info.k = [float(v) for v in np.asarray(K).ravel()]
    P = np.zeros((3, 4))
    P[:, :3] = K
    info.p = [float(v) for v in P.ravel()]
    return info


def test_camera_info_checks():
    cam = camera_from_info(_info())
    np.testing.assert_allclose(cam.K, LMO_K)
    np.testing.assert_allclose(camera_from_info(_info(), use_rectified=True).K, LMO_K)
    with pytest.raises(InputError, match="focal") as err:
        camera_from_info(_info(K=np.zeros((3, 3))))
    assert err.value.reason == "camera_info_k"
    with pytest.raises(InputError, match="non-finite"):
        camera_from_info(_info(K=np.full((3, 3), np.nan)))
    with pytest.raises(InputError) as err:
        camera_from_info(_info(w=0))
    assert err.value.reason == "camera_info_size"


@pytest.mark.parametrize(
    "fx, fy, cx, cy, reason",
    [
        (572.4, 573.6, 1e9, 242.0, "camera_info_principal_point"),  # the fuzz run's: finite, overflows the crops later
        (572.4, 573.6, 325.3, -1e6, "camera_info_principal_point"),
        (572.4, 573.6, -400.0, 242.0, "camera_info_principal_point"),
        (1e-12, 1e-12, 325.3, 242.0, "camera_info_focal_length"),  # the fuzz run's
        (1e9, 1e9, 325.3, 242.0, "camera_info_focal_length"),
        (5.0, 5.0, 325.3, 242.0, "camera_info_focal_length"),
        (572.4, 50.0, 325.3, 242.0, "camera_info_focal_length"),  # fx / fy 11: no lens
        (572.4, 573.6, 325.3, 242.0, "camera_info_k"),  # with a skew of 1e300 (below)
    ],
)
def test_absurd_but_finite_intrinsics_are_refused_with_their_reason(fx, fy, cx, cy, reason):
    K = [[fx, 1e300 if reason == "camera_info_k" else 0.0, cx], [0.0, fy, cy], [0.0, 0.0, 1.0]]
    for rectified in (False, True):
        with pytest.raises(InputError) as err:
            camera_from_info(_info(K=K), use_rectified=rectified)
        assert err.value.reason == reason and ("P" if rectified else "K") in str(err.value)


@pytest.mark.parametrize(
    "K",
    [
        [[200.0, 0, 320], [0, 200.0, 240], [0, 0, 1]],  # a wide lens (~116 degrees)
        [[20000.0, 0, 320], [0, 20000.0, 240], [0, 0, 1]],  # a telephoto (~1.8 degrees)
        [[572.4, 0, -100.0], [0, 573.6, 600.0], [0, 0, 1]],  # an off-centre crop of a larger sensor
        [[600.0, 0, 320], [0, 300.0, 240], [0, 0, 1]],  # 2:1 pixels
    ],
)
def test_unusual_but_real_intrinsics_pass(K):
    np.testing.assert_allclose(camera_from_info(_info(K=np.asarray(K))).K, K)


def test_image_size_against_camera_info():
    cam = camera_from_info(_info())
    assert camera_for_image(cam, 640, 480) is cam
    half = camera_for_image(cam, 320, 240)
    assert half.K[0, 0] == pytest.approx(LMO_K[0, 0] / 2)
    with pytest.raises(InputError) as err:
        camera_for_image(cam, 640, 400)
    assert err.value.reason == "camera_info_mismatch"
    image = _image(np.zeros((400, 640, 3), np.uint8), "rgb8")
    with pytest.raises(InputError) as err:
        check_frame(image, _info())
    assert err.value.reason == "camera_info_mismatch"
    assert check_frame(_image(np.zeros((240, 320, 3), np.uint8), "rgb8"), _info()).K[0, 0] == pytest.approx(LMO_K[0, 0] / 2)


@pytest.mark.parametrize("model, D", [("plumb_bob", [-0.28, 0.09, 0.001, -0.002, 0.0]),
                                      ("rational_polynomial", [0.5, -0.1, 0.001, 0.0, 0.02, 0.8, -0.05, 0.03]),
                                      ("equidistant", [0.1, -0.05, 0.01, -0.002])])  # fmt: skip
def test_distorted_images_are_undistorted_to_the_pinhole_image_of_k(model, D):
    """A dot drawn where the lens puts a 3D point lands, after undistortion, where the pinhole K projects it."""
    import cv2

    K = np.asarray(LMO_K, dtype=np.float64)
    info = CameraInfo(width=640, height=480, distortion_model=model, d=D)
    info.k = [float(v) for v in K.ravel()]
    assert Undistorter.needed(info) and not Undistorter.needed(CameraInfo(width=640, height=480, d=[0.0] * 5))
    point = np.array([[[0.22, -0.15, 0.6]]])
    project = cv2.fisheye.projectPoints if model == "equidistant" else cv2.projectPoints
    distorted = project(point, np.zeros(3), np.zeros(3), K, np.asarray(D))[0].ravel()
    pinhole = (K @ point.ravel())[:2] / point.ravel()[2]
    assert np.linalg.norm(distorted - pinhole) > 5  # the lens moves it visibly
    image = np.zeros((480, 640, 3), np.uint8)
    cv2.circle(image, tuple(round(float(v)) for v in distorted), 4, (255, 255, 255), -1)
    out = Undistorter()(info, K, image)
    ys, xs = np.nonzero(out[..., 0] > 128)
    assert np.linalg.norm([xs.mean() - pinhole[0], ys.mean() - pinhole[1]]) < 1.0


def test_unsupported_distortion_is_refused_with_a_reason():
    K = np.asarray(LMO_K, dtype=np.float64)
    image = np.zeros((48, 64, 3), np.uint8)
    for model, D, reason in (("fov", [0.9], "distortion_model"), ("plumb_bob", [0.1, 0.2, 0.0], "distortion_coefficients"),
                             ("plumb_bob", [float("nan")] * 5, "distortion_coefficients")):  # fmt: skip
        with pytest.raises(InputError) as err:
            Undistorter()(CameraInfo(width=64, height=48, distortion_model=model, d=D), K, image)
        assert err.value.reason == reason


def test_synchroniser_pairs_within_slop_and_drops_the_rest():
    pairs, drops = [], []
    sync = StampSynchronizer(0.01, lambda i, c: pairs.append((i, c)), lambda i, r: drops.append((i, r)), max_images=2)
    sync.add_info(1.000, "info1")
    sync.add_image(1.005, "img1")  # info already there
    sync.add_image(2.000, "img2")  # waits
    sync.add_info(2.004, "info2")
    sync.add_image(3.000, "img3")
    sync.add_info(3.500, "info3")  # later than img3 + slop: img3 can never be paired
    assert pairs == [("img1", "info1"), ("img2", "info2")]
    assert drops == [("img3", "no_camera_info")]
    for k in range(4):  # images with no info at all: bounded queue, oldest dropped
        sync.add_image(10.0 + k, f"late{k}")
    assert [d[0] for d in drops[1:]] == ["late0", "late1"]
    with pytest.raises(ValueError, match="slop"):
        StampSynchronizer(-1.0, print, print)


def test_synchroniser_pairs_whatever_the_arrival_order():
    pairs, drops = [], []
    sync = StampSynchronizer(0.01, lambda i, c: pairs.append((i, c)), lambda i, r: drops.append((i, r)))
    sync.add_image(1.0, "img1")
    sync.add_info(1.1, "info1.1")  # an info of the next frame overtakes img1's own (within `reorder`)
    sync.add_info(1.0, "info1")
    sync.add_info(1.2, "info1.2")
    sync.add_image(1.2, "img1.2")
    assert pairs == [("img1", "info1"), ("img1.2", "info1.2")] and drops == []
    sync.add_image(1.1, "img1.1")  # older than a frame already paired: the node wants only the latest
    assert drops == [("img1.1", "out_of_order")]


def test_synchroniser_starts_over_when_time_jumps_back():
    """A bag that loops: stamps fall from 50 s to 1 s. Pairing resumes at once instead of waiting images out."""
    pairs, drops = [], []
    sync = StampSynchronizer(0.01, lambda i, c: pairs.append((i, c)), lambda i, r: drops.append((i, r)))
    sync.add_info(50.0, "info50")
    sync.add_image(50.0, "img50")
    sync.add_image(50.1, "img50.1")  # waits for its info
    sync.add_image(1.0, "img1")  # the jump: the waiting image is given up on, the old infos are forgotten
    sync.add_info(1.0, "info1")
    assert pairs == [("img50", "info50"), ("img1", "info1")]
    assert drops == [("img50.1", "time_jump")] and sync.jumps == 1


def test_stamp_audit_estimates_frames_lost_from_stamp_gaps():
    audit = StampAudit()
    stamps = [k / 30 for k in range(1, 10)] + [k / 30 for k in range(13, 20)] + [k / 30 for k in range(24, 30)]
    verdicts = [audit.add(s) for s in stamps]
    assert audit.lost == 3 + 4 and verdicts[9].lost == 3 and not any(v.anomaly for v in verdicts)
    assert audit.add(0.0).anomaly == "zero" and audit.add(-5.0).anomaly == "zero" and audit.lost == 7
    assert audit.add(29 / 30).anomaly == "backwards"  # repeated: not later than the previous
    assert audit.add(31 / 30).lost == 0  # the interval after a step back is not read
    assert audit.add(33 / 30).lost == 1


def test_stamp_audit_sorts_out_stamps_that_say_nothing_about_loss():
    """The fuzz run's stamps (zero, far future, back and forth, a camera pause) are each counted under their own
    anomaly; none of them is taken for frames lost."""
    now = 1_700_000_000.0
    audit = StampAudit()
    steady = [now - 1000 + k / 15 for k in range(20)]
    assert all(not audit.add(s, now).anomaly for s in steady)
    assert audit.add(0.0, now).anomaly == "zero"
    assert audit.add(now + 86_400, now).anomaly == "future"
    assert StampAudit().add(now + 5, now).anomaly is None  # within future_s of the receiver's clock: a clock a little ahead
    assert audit.add(steady[3], now).anomaly == "backwards"
    assert audit.add(steady[-1] + 1 / 15, now).lost == 0  # back on the timeline: not read
    assert audit.add(steady[-1] + 2 / 15, now).lost == 0
    assert audit.add(steady[-1] + 600, now).anomaly == "discontinuity"  # 10 minutes of silence: a pause, not 9,000 frames lost
    assert audit.add(now + 86_400).anomaly == "discontinuity"  # without a clock, no stamp is judged to be in the future
    assert audit.lost == 0 and audit.seen == 27


@pytest.mark.parametrize("seed", range(5))
def test_stamp_audit_never_counts_more_frames_lost_than_it_saw(seed):
    """Adversarial stamps: the anomalies keep to their bounded names and the frames lost to the frames seen."""
    rng = np.random.default_rng(seed)
    audit, now, t = StampAudit(), 1_700_000_000.0, 1_699_999_000.0
    anomalies = set()
    for _ in range(2000):
        kind = rng.integers(6)
        if kind == 0:
            stamp = rng.choice([0.0, -1.0, 1e-9, now + 1e6, 2.0**31, -(2.0**31)])
        elif kind == 1:
            stamp = t - rng.uniform(0, 100)
        elif kind == 2:
            t += (rng.integers(2, 40)) / 15  # a gap, within max_gap or beyond
            stamp = t
        else:
            t += 1 / 15 + rng.normal(0, 1e-4)
            stamp = t
        v = audit.add(float(stamp), now)
        assert 0 <= v.lost <= audit.max_gap and audit.lost <= audit.seen
        anomalies.add(v.anomaly)
    assert anomalies <= {None, *STAMP_ANOMALIES} and audit.lost > 0
    every_other = StampAudit()  # half the frames lost, all the time: the count stays a lower bound
    for k in range(1, 400):
        every_other.add(1000 + (k if k < 10 else 10 + 3 * (k - 10)) / 15)
    assert every_other.lost <= every_other.seen
