"""Held-out evaluation of the learnt model against the SMPL-type baseline (thesis Sec. 5.5)."""
