"""The node's counters and its recent frame latencies, as /diagnostics reports them.

The executor's callbacks and the inference thread both count, so every change and every copy holds one lock:
iterating a Counter while the other thread adds a key fails.
"""

from __future__ import annotations

import threading
from collections import Counter

import numpy as np
from diagnostic_msgs.msg import KeyValue

LATENCY_WINDOW = 100
"""Frames whose latency the median of /diagnostics covers."""


class Counters:
    """Thread-safe event counters (`frames_in`, `dropped_<reason>`, ...) and the latencies of the last frames."""

    def __init__(self) -> None:
        self.counts: Counter[str] = Counter()
        self.latency: list[float] = []
        self._lock = threading.Lock()

    def add(self, key: str, n: int = 1) -> None:
        with self._lock:
            self.counts[key] += n

    def snapshot(self) -> dict[str, int]:
        """A consistent copy of the counts."""
        with self._lock:
            return dict(self.counts)

    def frames_done(self) -> int:
        """Frames that left the node: processed, or dropped for a reason."""
        counts = self.snapshot()
        return counts.get("frames_processed", 0) + sum(v for k, v in counts.items() if k.startswith("dropped_"))

    def frame_latency(self, seconds: float) -> None:
        """Record one frame's latency, keeping the last LATENCY_WINDOW (one thread records, a new list replaces
        the old one, so a reader sees either)."""
        self.latency = [*self.latency[-(LATENCY_WINDOW - 1) :], seconds]

    def key_values(self, described: dict[str, str] | None = None) -> list[KeyValue]:
        """The counts (totals), the median latency of the window in ms and what `described` adds, sorted by key, for
        a DiagnosticStatus."""
        values: dict[str, float | str] = dict(self.snapshot()) | (described or {})
        latency = self.latency
        if latency:
            values["latency_median_ms"] = 1000 * float(np.median(latency))
        return [KeyValue(key=k, value=f"{v:.1f}" if isinstance(v, float) else str(v)) for k, v in sorted(values.items())]
