"""The states of a frame (``VOResult.status``); `odometry.py`'s module docstring says what moves between them."""
INITIALISING, TRACKING, RELOCALISED, REINITIALISED, LOST = (
    "initialising", "tracking", "relocalised", "reinitialised", "lost")
SKIPPED = "skipped"  # the frame could not be used (see VOResult.problem); the pose is held
TRACKED_STATES = (TRACKING, RELOCALISED, REINITIALISED)
