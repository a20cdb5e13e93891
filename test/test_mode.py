"""`mode`: explicit modes are what they say; `auto` picks the mode the stream calls for and switches as it changes."""

from __future__ import annotations

import pytest

from axispose_core.tracking.mode import AutoConfig, Mode, ModeChooser


def _run(chooser: ModeChooser, frames: int, camera_pose: bool, held: int, lost: int, requested: Mode = Mode.AUTO,
         drop_every: int = 0) -> list[Mode]:  # fmt: skip
    """`frames` frames through the chooser, following holding `held` and losing `lost` contours a tracked frame, and
    the node dropping a frame for being busy every `drop_every` frames (0: never)."""
    modes = []
    for k in range(frames):
        if drop_every and k % drop_every == 0:
            chooser.dropped += 1
        choice = chooser.choose(requested, camera_pose, chooser.dropped)
        modes.append(choice.mode)
        if choice.tracking:
            chooser.record(held, lost)
    return modes


def _chooser(**config) -> ModeChooser:
    chooser = ModeChooser(AutoConfig(**config))
    chooser.dropped = 0  # the node's running count of frames dropped while busy
    return chooser


def test_explicit_modes_are_what_they_say():
    chooser = _chooser()
    assert _run(chooser, 30, True, 0, 5, Mode.STILLS) == [Mode.STILLS] * 30
    assert _run(chooser, 30, False, 0, 5, Mode.VIDEO) == [Mode.VIDEO] * 30  # contours lost: still video, as asked
    assert _run(chooser, 3, True, 5, 0, Mode.VIDEO_ODOMETRY) == [Mode.VIDEO_ODOMETRY] * 3
    choice = chooser.choose(Mode.VIDEO_ODOMETRY, False)
    assert choice.mode is Mode.VIDEO and "no camera_odom" in choice.reason


def test_auto_poses_stills_while_it_keeps_up_and_follows_once_it_falls_behind():
    chooser = _chooser()
    assert _run(chooser, 40, False, 5, 0) == [Mode.STILLS] * 40  # no odometry, no frame dropped: each posed on its own
    behind = _run(chooser, 40, False, 5, 0, drop_every=4)  # the camera outpaces stills
    assert behind[0] is Mode.VIDEO and set(behind) == {Mode.VIDEO}
    choice = chooser.choose(Mode.AUTO, False, chooser.dropped)  # keeping up now, in video: it stays while contours hold
    assert choice.mode is Mode.VIDEO and "20 of the last 20" in choice.reason


def test_auto_follows_with_odometry_and_goes_on_without_it_where_it_stops():
    chooser = _chooser()
    assert _run(chooser, 10, True, 5, 0) == [Mode.VIDEO_ODOMETRY] * 10
    choice = chooser.choose(Mode.AUTO, False)  # odometry stopped: the stream is still followed, its tracks kept
    assert choice.mode is Mode.VIDEO and "no camera_odom" in choice.reason and "20 of the last 20" in choice.reason
    assert _run(chooser, 5, False, 5, 0) == [Mode.VIDEO] * 5
    assert chooser.choose(Mode.AUTO, True).mode is Mode.VIDEO_ODOMETRY  # and it comes back


def test_auto_turns_to_stills_where_contours_stop_holding_and_tries_again_later():
    chooser = _chooser(window=20, least_held=0.5, retry_frames=10)
    assert _run(chooser, 8, True, 4, 1) == [Mode.VIDEO_ODOMETRY] * 8  # 80 % held
    # The frame rate drops: one contour of five holds. Following stops once the last 20 attempts fall under half.
    dropped = _run(chooser, 10, True, 1, 4)
    first = dropped.index(Mode.STILLS)
    assert dropped[:first] == [Mode.VIDEO_ODOMETRY] * first and first <= 4
    choice = chooser.choose(Mode.AUTO, True)
    assert choice.mode is Mode.STILLS and "held on" in choice.reason and "following again in" in choice.reason
    # After retry_frames stills it follows again, judged afresh: contours holding now keep it there.
    later = _run(chooser, 20, True, 5, 0)
    assert later[0] is Mode.STILLS and later[-1] is Mode.VIDEO_ODOMETRY
    assert Mode.STILLS not in later[later.index(Mode.VIDEO_ODOMETRY) :]


def test_auto_on_stills_follows_only_a_small_part_of_the_time():
    """A bag of stills with odometry, no contour holding: each try at following costs one window of attempts, then
    retry_frames frames run as stills."""
    modes = _run(_chooser(window=20, least_held=0.5, retry_frames=60), 300, True, 0, 5)
    assert modes.count(Mode.VIDEO_ODOMETRY) / len(modes) < 0.1


def test_a_mode_that_does_not_exist_is_refused_with_the_choices():
    with pytest.raises(ValueError, match="stills, video, video_odometry, auto"):
        Mode.parse("tracking")
    assert Mode.parse("video_odometry") is Mode.VIDEO_ODOMETRY
