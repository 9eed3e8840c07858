"""2D human pose detectors for markerless scan keypoints (:mod:`blsm.learn.markerless.keypoints`).

:mod:`.detectors` holds the detector protocol, MediaPipe Pose run as a subprocess in its own
environment, and a projecting stand-in for tests; :mod:`.mediapipe_pose` is the stand-alone script
that runs inside that environment (it imports nothing from the project).
"""
