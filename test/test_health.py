"""The node's health: judged on the recent window, so that it cannot say OK forever once one frame went through."""

from diagnostic_msgs.msg import DiagnosticStatus

from axispose_ros.health import Health, HealthConfig

CFG = HealthConfig(window_s=10.0, stale_s=5.0, max_drop_ratio=0.5, latency_budget_s=1.0)


def _healthy(start: float = 0.0) -> Health:
    h = Health(CFG, start)
    for k in range(8):
        h.info(start + k)
        h.image(start + k)
        h.output(start + k + 0.3, 0.3)
    return h


def test_ok_while_frames_go_through_in_budget():
    level, message = _healthy().judge(8.0)
    assert level == DiagnosticStatus.OK and "8 frames processed" in message


def test_warn_without_images():
    level, message = _healthy().judge(30.0)  # the camera went quiet 22 s ago
    assert level == DiagnosticStatus.WARN and "no images" in message
    assert Health(CFG, 0.0).judge(1.0)[0] == DiagnosticStatus.WARN  # before the first image


def test_error_when_images_come_but_nothing_goes_out():
    """The fuzzing run's case: frames processed early, then only drops. Totals since start said OK forever."""
    h = _healthy()
    for k in range(40):
        h.info(20.0 + 0.25 * k)
        h.image(20.0 + 0.25 * k)
        h.drop(20.0 + 0.25 * k, "encoding")
    level, message = h.judge(30.0)
    assert level == DiagnosticStatus.ERROR and "no pose output" in message and "encoding 40" in message


def test_warn_when_most_frames_are_dropped_or_late():
    h = _healthy()
    for k in range(3):
        h.drop(8.5 + k * 0.1, "no_camera_info")  # 3 of 11 verdicts: fine
    assert h.judge(9.0)[0] == DiagnosticStatus.OK
    for k in range(10):
        h.drop(9.0 + k * 0.05, "no_camera_info")  # 13 of 21
    level, message = h.judge(9.6)
    assert level == DiagnosticStatus.WARN and "13 of 21 frames dropped" in message
    slow = Health(CFG, 0.0)
    for k in range(5):
        slow.info(k)
        slow.image(k)
        slow.output(k + 0.1, 1.5)
    level, message = slow.judge(5.0)
    assert level == DiagnosticStatus.WARN and "over the 1 s budget" in message


def test_warn_names_the_transport_when_camera_info_arrives_but_images_do_not():
    """The cross-process case: 350-byte camera_infos arrive, 921,600-byte images are lost between processes."""
    h = _healthy()
    for k in range(30):
        h.info(20.0 + 0.1 * k)
    level, message = h.judge(23.0)
    assert level == DiagnosticStatus.WARN and "camera_info arrives (30 in the last 10 s) but no images" in message
    assert "lost in transport" in message and "Beside a camera driver" in message and "Fast DDS profile" in message
    partial = Health(CFG, 0.0)  # 190 of 300 arrived, as in the run: most but not all
    for k in range(30):
        partial.info(0.3 * k)
        if k % 3:
            partial.image(0.3 * k)
            partial.output(0.3 * k + 0.05, 0.05)
    level, message = partial.judge(9.0)
    assert level == DiagnosticStatus.WARN and "only 20 images for 30 camera_infos" in message and "lost in transport" in message
    fine = Health(CFG, 0.0)  # a camera_info or two more than images (the last pair in flight): no warning
    for k in range(30):
        fine.info(0.3 * k)
        if k < 28:
            fine.image(0.3 * k)
            fine.output(0.3 * k + 0.05, 0.05)
    assert fine.judge(9.0)[0] == DiagnosticStatus.OK


def test_images_without_camera_info_name_the_missing_topic():
    h = Health(CFG, 0.0)
    for k in range(4):
        h.image(0.5 * k)
    level, message = h.judge(2.0)
    assert level == DiagnosticStatus.WARN and "images arrive (4 in the last 10 s) but no camera_info" in message
    for k in range(20):  # still none later: nothing went out for longer than stale_s
        h.image(2.0 + 0.5 * k)
    level, message = h.judge(12.0)
    assert level == DiagnosticStatus.ERROR and "no camera_info" in message and "remapped" in message
