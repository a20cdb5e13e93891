"""Tracking across a camera stream: per-object tracks with a filtered SE(3) pose (`tracker.Tracker`, scheduling its
parts `tracks`, `follow`, `fixed_frame` and `search`; `filter.PoseFilter`)."""
