"""`mode`: explicit modes are what they say; `auto` picks the mode the stream calls for and switches as it changes."""

from __future__ import annotations

import pytest

from axispose_core.tracking.mode import AutoConfig, Mode, ModeChooser


def _run(chooser: ModeChooser, frames: int, camera_pose: bool, held: int, lost: int, requested: Mode = Mode.AUTO) -> list[Mode]:
    modes = []
    for _ in range(frames):
        choice = chooser.choose(requested, camera_pose)
        modes.append(choice.mode)
        if choice.tracking:
            chooser.record(held, lost)
    return modes


def test_explicit_modes_are_what_they_say():
    chooser = ModeChooser()
    assert _run(chooser, 30, True, 0, 5, Mode.STILLS) == [Mode.STILLS] * 30
    assert _run(chooser, 30, False, 0, 5, Mode.VIDEO) == [Mode.VIDEO] * 30  # contours lost: still video, as asked
    assert _run(chooser, 3, True, 5, 0, Mode.VIDEO_ODOMETRY) == [Mode.VIDEO_ODOMETRY] * 3
    choice = chooser.choose(Mode.VIDEO_ODOMETRY, False)
    assert choice.mode is Mode.VIDEO and "no camera_odom" in choice.reason


def test_auto_follows_with_odometry_where_it_arrives_and_without_where_it_stops():
    chooser = ModeChooser()
    assert _run(chooser, 10, True, 5, 0) == [Mode.VIDEO_ODOMETRY] * 10
    choice = chooser.choose(Mode.AUTO, False)  # odometry stopped
    assert choice.mode is Mode.VIDEO and "no camera_odom" in choice.reason and "20 of the last 20" in choice.reason
    assert _run(chooser, 5, False, 5, 0) == [Mode.VIDEO] * 5
    assert chooser.choose(Mode.AUTO, True).mode is Mode.VIDEO_ODOMETRY  # and it comes back


def test_auto_turns_to_stills_where_contours_stop_holding_and_tries_again_later():
    chooser = ModeChooser(AutoConfig(window=20, least_held=0.5, retry_frames=10))
    assert _run(chooser, 8, False, 4, 1) == [Mode.VIDEO] * 8  # 80 % held
    # The frame rate drops: one contour of five holds. Following stops once the last 20 attempts fall under half.
    dropped = _run(chooser, 10, False, 1, 4)
    assert Mode.STILLS in dropped and dropped[: dropped.index(Mode.STILLS)] == [Mode.VIDEO] * dropped.index(Mode.STILLS)
    assert dropped.index(Mode.STILLS) <= 4
    choice = chooser.choose(Mode.AUTO, False)
    assert choice.mode is Mode.STILLS and "held on" in choice.reason and "following again in" in choice.reason
    # After retry_frames stills it follows again, judged afresh: contours holding now keep it there.
    later = _run(chooser, 20, False, 5, 0)
    assert later[0] is Mode.STILLS and later[-1] is Mode.VIDEO and Mode.STILLS not in later[later.index(Mode.VIDEO) :]


def test_auto_on_stills_follows_only_a_small_part_of_the_time():
    """A bag of stills (no contour holds): each try at following costs one window of attempts, then retry_frames
    frames run as stills."""
    config = AutoConfig(window=20, least_held=0.5, retry_frames=60)
    modes = _run(ModeChooser(config), 300, False, 0, 5)
    assert modes.count(Mode.VIDEO) / len(modes) < 0.1


def test_a_mode_that_does_not_exist_is_refused_with_the_choices():
    with pytest.raises(ValueError, match="stills, video, video_odometry, auto"):
        Mode.parse("tracking")
    assert Mode.parse("video_odometry") is Mode.VIDEO_ODOMETRY
