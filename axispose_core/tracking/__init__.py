"""Tracking across a camera stream: the mode a frame runs in (`mode`: stills, video, video_odometry, or `auto`'s
pick), per-object tracks with a filtered SE(3) pose (`tracker.Tracker`, scheduling its parts `tracks`, `follow`,
`fixed_frame` and `search`; `filter.PoseFilter`)."""
