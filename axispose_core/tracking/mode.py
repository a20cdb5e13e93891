"""How the node treats its frames, the one tracking choice a user makes (`mode`), and `auto`'s pick among the others
from what it receives.

`stills` poses every frame on its own. `video` tracks objects and follows each by its contour from frame to frame, the
AGM posing only new and lost objects: a fraction of the time per frame and steadier poses, but on rendered streams a
few points of ADD(-S) below posing each frame. `video_odometry` is `video` with the camera's pose in a fixed frame:
each still object's views are fused there (`view_window`) and the localiser and the AGM search in a process of their
own, well above both.

`auto` runs `video_odometry` while frames come with the camera's pose; without it, `stills` while the node keeps up
with the frames, and `video` once it drops frames for being busy (and from then on, as after odometry stopped). Both
video modes need contours that hold from one frame to the next: where they mostly do not (frames far apart in time or
motion: a bag of stills, a slow camera, a fast turn) following only costs, and it runs `stills` for a while.
"""

from __future__ import annotations

from collections import deque
from dataclasses import dataclass
from enum import Enum


class Mode(str, Enum):
    STILLS = "stills"
    VIDEO = "video"
    VIDEO_ODOMETRY = "video_odometry"
    AUTO = "auto"

    @classmethod
    def parse(cls, text: str) -> Mode:
        """The mode named `text`; ValueError naming the choices otherwise."""
        try:
            return cls(text)
        except ValueError:
            raise ValueError(f"mode must be one of {', '.join(m.value for m in cls)}, got {text!r}") from None


@dataclass(frozen=True)
class AutoConfig:
    """When `auto` trusts contours to hold, and how long it waits before it tries again where they did not."""

    window: int = 20
    """Follow attempts (a track followed on a frame, held or lost) judged together."""
    least_held: float = 0.5
    """Fraction of those attempts whose contour must hold for following to go on."""
    retry_frames: int = 60
    """Frames posed as stills before following is tried again (2 s at 30 Hz)."""
    behind_frames: int = 30
    """Frames over which a frame dropped for the node being busy counts as falling behind the camera."""


@dataclass(frozen=True)
class Choice:
    """The mode a frame runs in, and why (what `/diagnostics` says)."""

    mode: Mode
    reason: str

    @property
    def tracking(self) -> bool:
        return self.mode is not Mode.STILLS

    @property
    def odometry(self) -> bool:
        return self.mode is Mode.VIDEO_ODOMETRY

    def described(self) -> dict[str, str]:
        """The mode and its reason as `/diagnostics` key-values."""
        return {"mode": self.mode.value, "mode_reason": self.reason}


class ModeChooser:
    """Each frame's mode: the requested one, or under `auto` the one the stream calls for, judged from whether the
    frame comes with the camera's pose, whether frames were dropped while the node was busy, and how often the
    contours held on the frames before (`record`)."""

    def __init__(self, config: AutoConfig = AutoConfig()) -> None:
        self.config = config
        self._attempts: deque[bool] = deque(maxlen=config.window)
        self._stills_left = 0
        """Under `auto`, frames still to pose as stills because contours stopped holding (0: following)."""
        self._streaming = False
        """Under `auto`, a stream is being followed (it came with odometry, or the node fell behind it)."""
        self._drops: deque[bool] = deque(maxlen=config.behind_frames)
        self._dropped = 0

    def choose(self, requested: Mode, has_camera_pose: bool, dropped: int = 0) -> Choice:
        """The mode of the next frame; `dropped`: the frames dropped so far for the node being busy (a running
        count). An explicit `video_odometry` without the camera's pose runs as `video` for the frame (there is
        nothing to fuse in)."""
        self._drops.append(dropped > self._dropped)
        self._dropped = dropped
        if requested is Mode.STILLS:
            return Choice(Mode.STILLS, "requested")
        if requested is Mode.VIDEO:
            return Choice(Mode.VIDEO, "requested")
        if requested is Mode.VIDEO_ODOMETRY:
            return Choice(Mode.VIDEO_ODOMETRY, "requested") if has_camera_pose else Choice(Mode.VIDEO, "requested; no camera_odom")
        if self._stills_left > 0:
            self._stills_left -= 1
            if self._stills_left > 0:
                return Choice(Mode.STILLS, f"contours held on {self._held_text()}; following again in {self._stills_left} frames")
            self._attempts = deque(maxlen=self.config.window)
        held = f"contours held on {self._held_text()}" if self._attempts else "following"
        if has_camera_pose:
            self._streaming = True
            return Choice(Mode.VIDEO_ODOMETRY, f"camera_odom arriving; {held}")
        if any(self._drops) and not self._streaming:
            self._streaming = True
            return Choice(Mode.VIDEO, "frames dropped while busy: following")
        if self._streaming:
            return Choice(Mode.VIDEO, f"no camera_odom; {held}")
        return Choice(Mode.STILLS, "no camera_odom, every frame kept up with")

    def record(self, held: int, lost: int) -> None:
        """What following did on the frame just run: tracks whose contour held, and those it lost. Under `auto`, too
        few held over the last `window` attempts turn the next `retry_frames` frames to `stills`."""
        self._attempts.extend([True] * held + [False] * lost)
        full = len(self._attempts) == self._attempts.maxlen
        if self._stills_left == 0 and full and sum(self._attempts) < self.config.least_held * len(self._attempts):
            self._stills_left, self._streaming = self.config.retry_frames + 1, False

    def _held_text(self) -> str:
        return f"{sum(self._attempts)} of the last {len(self._attempts)} followed tracks"
