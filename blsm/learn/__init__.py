"""Learning BLSM from scans (paper 000 Sec. 4; thesis Sec. 5.4) and evaluating it (Sec. 5.5).

- :mod:`blsm.learn.scans`: the scan file format, the template landmarks (A_lm of Eq. 5.13) and the
  Anny people that stand in for CAESAR / D-FAUST scans.
- :mod:`blsm.learn.registration`: the template registered to scans (Eqs. 5.13-5.25: the driver
  ``register``, its stages ``landmark_fit`` and ``surface_fit``) or to 3D keypoints over frames
  (Sec. 6.3: ``keypoint_fit``, ``temporal``, ``end_search``), and the registration files.
- :mod:`blsm.learn.markerless`: keypoints and landmarks of a scan without markers (Sec. 6.3.1):
  multi-view renders, 2D detectors, triangulation, the learnt detector and keypoint regressor.
- :mod:`blsm.learn.training`: bone basis, bone-corrective and shape blendshapes, blend weights
  (Eqs. 5.26-5.31) learnt from registrations.
- :mod:`blsm.learn.evaluation`: the staged fit, the SMPL-type baseline and the held-out errors
  against the number of coefficients (Sec. 5.5, Fig. 5.6).
- :mod:`blsm.learn.reparam`: a model in another template topology, and its evaluation (ch. 3).
- :mod:`blsm.learn.posing`: LBS of any template with per-bone scales (the unknowns of Eq. 5.13),
  shared by all of them.
- :mod:`blsm.learn.pipeline`: the whole run of ``blsm train`` (population, registration, learning,
  evaluation); :mod:`blsm.learn.cli`: the commands ``blsm scans | register | learn | train |
  evaluate | train-smpl``.
"""
