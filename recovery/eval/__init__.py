"""Evaluation: the metrics (:mod:`.metrics`), the evaluation joint set (:mod:`.joints`), ``recovery
evaluate`` (:mod:`.evaluate`), temporal metrics on sequences (:mod:`.temporal`) and the real-photo
transfer check (:mod:`.transfer`, with its stand-alone reference script :mod:`blsm.pose2d.mediapipe_pose`)."""
