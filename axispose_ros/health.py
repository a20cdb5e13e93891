"""The node's health for `/diagnostics`, judged on a recent window rather than on counters since start.

Counters since start say OK forever once one frame was processed. Here each image in, camera_info in, output
and drop is recorded with its time, and `judge` looks at the last `window_s` seconds only: no images (WARN; when
camera_infos do arrive, it names the likely cause: large images lost between processes), images but no
camera_info (WARN; ERROR once no output came for `stale_s`), images but no output for `stale_s` (ERROR), images
short of the camera_infos by more than `max_image_shortfall` (WARN: lost in transport), more than
`max_drop_ratio` of the frames that reached a verdict dropped (WARN), the median latency over `latency_budget_s`
(WARN), else OK. Frames replaced by a newer one while inference was busy are not drops here: keeping only the
latest frame is the node's design, not a fault.
"""

from __future__ import annotations

import threading
from collections import Counter, deque
from dataclasses import dataclass

from diagnostic_msgs.msg import DiagnosticStatus

TRANSPORT_HINT = "README, 'Beside a camera driver': the camera driver needs the shipped Fast DDS profile"


@dataclass(frozen=True)
class HealthConfig:
    window_s: float = 10.0
    stale_s: float = 5.0
    max_drop_ratio: float = 0.5
    latency_budget_s: float = 2.0
    max_image_shortfall: float = 0.25
    """Images fewer than camera_infos by more than this fraction of them: images are being lost (WARN)."""


class Health:
    """Thread-safe record of recent events (the executor and the inference thread both report)."""

    def __init__(self, config: HealthConfig, now: float) -> None:
        self.config = config
        self._events: deque[tuple[float, str, str]] = deque()  # (time, kind, drop reason)
        self._latency: deque[tuple[float, float]] = deque()
        self._last_out = now
        self._lock = threading.Lock()

    def image(self, now: float) -> None:
        self._add(now, "in")

    def info(self, now: float) -> None:
        self._add(now, "info")

    def output(self, now: float, latency_s: float) -> None:
        with self._lock:
            self._last_out = now
            self._latency.append((now, latency_s))
        self._add(now, "out")

    def drop(self, now: float, reason: str) -> None:
        self._add(now, "drop", reason)

    def _add(self, now: float, kind: str, reason: str = "") -> None:
        with self._lock:
            self._events.append((now, kind, reason))
            self._forget(now)

    def _forget(self, now: float) -> None:
        start = now - self.config.window_s
        while self._events and self._events[0][0] < start:
            self._events.popleft()
        while self._latency and self._latency[0][0] < start:
            self._latency.popleft()

    def judge(self, now: float) -> tuple[bytes, str]:
        """(DiagnosticStatus level, message) for the last window."""
        c = self.config
        with self._lock:
            self._forget(now)
            kinds = Counter(kind for _, kind, _ in self._events)
            reasons = Counter(reason for _, kind, reason in self._events if kind == "drop")
            latencies = sorted(s for _, s in self._latency)
            since_out = now - self._last_out
        n_in, n_info, n_out, n_drop = kinds["in"], kinds["info"], kinds["out"], kinds["drop"]
        why = ", ".join(f"{r} {n}" for r, n in reasons.most_common(3))
        span = f"in the last {c.window_s:g} s"
        if n_in == 0 and n_info:
            return DiagnosticStatus.WARN, (
                f"camera_info arrives ({n_info} {span}) but no images: large images are likely lost in transport between "
                f"processes ({TRANSPORT_HINT})"
            )
        if n_in == 0:
            return DiagnosticStatus.WARN, f"no images {span}"
        stale = n_out == 0 and since_out > c.stale_s
        if n_info == 0:
            return DiagnosticStatus.ERROR if stale else DiagnosticStatus.WARN, (
                f"images arrive ({n_in} {span}) but no camera_info: is `camera_info` remapped to the camera's topic, "
                "and does the driver publish it?"
            )
        if stale:
            return DiagnosticStatus.ERROR, f"{n_in} images {span}, no pose output for {since_out:.0f} s" + (
                f" (dropped: {why})" if why else ""
            )
        if n_info >= 10 and n_in < (1.0 - c.max_image_shortfall) * n_info:
            return DiagnosticStatus.WARN, (
                f"only {n_in} images for {n_info} camera_infos {span}: large images are likely lost in transport between "
                f"processes ({TRANSPORT_HINT})"
            )
        if n_drop > c.max_drop_ratio * (n_drop + n_out):
            return DiagnosticStatus.WARN, f"{n_drop} of {n_drop + n_out} frames dropped {span} ({why})"
        median = latencies[len(latencies) // 2] if latencies else 0.0
        if median > c.latency_budget_s:
            return DiagnosticStatus.WARN, f"median latency {median:.2f} s {span}, over the {c.latency_budget_s:g} s budget"
        return DiagnosticStatus.OK, f"{n_out} frames processed {span}, median latency {median:.2f} s"
