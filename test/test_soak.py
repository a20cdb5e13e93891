"""`axispose soak` in short: the node in its own process, a bag looped at a camera's rate with every fault injected
once; the node stays up, every frame arrives, and every fault shows in /diagnostics."""

from __future__ import annotations

import json
from pathlib import Path

import pytest
from conftest import save_tiny_estimator

from axispose_ros.soak import FAULTS, SoakOptions, soak

REPO = Path(__file__).resolve().parents[1]


@pytest.mark.slow
def test_a_short_soak_keeps_the_node_up_and_counts_every_fault(tmp_path):
    checkpoint = save_tiny_estimator(tmp_path / "tiny.safetensors")
    opts = SoakOptions(seconds=36.0, rate=15.0, threads=1, warmup_boxes=0)
    report = soak(REPO / "demo" / "lmo_sample_bag", checkpoint, opts, tmp_path / "soak")
    assert report["alive"]
    assert report["frames_in"] == report["frames_sent"] > 400  # every frame delivered (the shipped transport profile)
    handled = report["frames_processed"] + sum(report["dropped"].values())
    assert report["frames_sent"] - 3 <= handled <= report["frames_sent"]  # the last frames may still be in flight
    assert {f["fault"] for f in report["faults"]} == set(FAULTS)
    assert all(f["counted"] for f in report["faults"]), report["faults"]
    assert report["stamps"].get("stamps_backwards", 0) >= 1
    assert len(report["rss_series"]) > 10 and report["rss_mb"]["end"] > 50
    saved = json.loads((tmp_path / "soak" / "soak.json").read_text())
    assert saved["frames_sent"] == report["frames_sent"] and (tmp_path / "soak" / "rss.png").is_file()
