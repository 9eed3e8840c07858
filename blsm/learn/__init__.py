"""Learning BLSM from scans (paper 000 Sec. 4; thesis Sec. 5.4) and evaluating it (Sec. 5.5).

- :mod:`blsm.learn.cli`: the commands ``blsm scans | register | learn | train | evaluate | train-smpl``.
- :mod:`blsm.learn.posing`: LBS of any template with per-bone scales (the unknowns of Eq. 5.13).
- :mod:`blsm.learn.scans`: the scan file format and the checks on it.
- :mod:`blsm.learn.landmarks`: the rules that place the anatomical landmarks on the template.
- :mod:`blsm.learn.population`: Anny people as the CAESAR / D-FAUST stand-in scans.
- :mod:`blsm.learn.register`: registering the template to scans (Eqs. 5.13-5.25), the driver;
  its settings in :mod:`blsm.learn.register_config`, its stages in :mod:`blsm.learn.landmark_fit`
  (Eq. 5.13) and :mod:`blsm.learn.surface_fit` (surface fit, Eqs. 5.14-5.25).
- :mod:`blsm.learn.registrations`: registration files, and a folder of them as one set with the
  held-out subsets picked from it.
- :mod:`blsm.learn.train`: bone basis, bone-corrective and shape blendshapes, blend weights
  (Eqs. 5.26-5.31); its math in :mod:`blsm.learn.bases`, its per-registration fit (Eq. 5.26) in
  :mod:`blsm.learn.train_fit`.
- :mod:`blsm.learn.pipeline`: the whole run of ``blsm train`` (population, registration, learning,
  evaluation).
- :mod:`blsm.learn.fit`: staged fitting of a model to registrations (Sec. 5.5.2).
- :mod:`blsm.learn.smpl_reimpl`: the SMPL-type baseline (Sec. 5.5.1).
- :mod:`blsm.learn.evaluate`: held-out errors against the number of coefficients (Fig. 5.6).
"""
