"""Scan keypoints and landmarks without markers: multi-view renders, 2D detectors (thesis Sec. 6.3.1)."""
