"""Tracking across a camera stream: per-object tracks with a filtered SE(3) pose (`tracker.Tracker`,
`filter.PoseFilter`)."""
