"""The scans BLSM is learnt from: the ``blsm-scan`` file, its landmarks, the Anny stand-in population."""
