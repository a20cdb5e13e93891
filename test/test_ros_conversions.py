import numpy as np
import pytest
from sensor_msgs.msg import CameraInfo, Image
from std_msgs.msg import Header

from axispose_core.lmo import LMO_K
from axispose_ros.conversions import InputError, Undistorter, camera_for_image, camera_from_info, image_to_rgb, rgb_to_image
from axispose_ros.sync import GapCounter, StampSynchronizer


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


def test_image_size_against_camera_info():
    cam = camera_from_info(_info())
    assert camera_for_image(cam, 640, 480) is cam
    half = camera_for_image(cam, 320, 240)
    assert half.K[0, 0] == pytest.approx(LMO_K[0, 0] / 2)
    with pytest.raises(InputError) as err:
        camera_for_image(cam, 640, 400)
    assert err.value.reason == "camera_info_mismatch"


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


def test_gap_counter_estimates_frames_lost_from_stamp_gaps():
    gaps = GapCounter()
    stamps = [k / 30 for k in range(10)] + [k / 30 for k in range(13, 20)] + [k / 30 for k in range(24, 30)]
    lost = [gaps.add(s) for s in stamps]
    assert gaps.lost == 3 + 4 and lost[10] == 3
    assert gaps.add(0.0) == 0 and gaps.add(0.0) == 0  # back in time or repeated: no gap counted
