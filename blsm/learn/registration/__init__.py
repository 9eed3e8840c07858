"""Registering the template to scans (thesis Eqs. 5.13-5.25) or to 3D keypoints (Sec. 6.3)."""
