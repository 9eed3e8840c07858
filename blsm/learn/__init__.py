"""Learning BLSM from scans (paper 000 Sec. 4; thesis Sec. 5.4) and evaluating it (Sec. 5.5).

- :mod:`blsm.learn.posing`: LBS of any template with per-bone scales (the unknowns of Eq. 5.13).
- :mod:`blsm.learn.scans`: the scan file format and the checks on it.
- :mod:`blsm.learn.population`: Anny people as the CAESAR / D-FAUST stand-in scans.
- :mod:`blsm.learn.register`: landmark fit and free-form registration (Eqs. 5.13-5.25).
- :mod:`blsm.learn.train`: bone basis, bone-corrective and shape blendshapes, blend weights
  (Eqs. 5.26-5.31).
- :mod:`blsm.learn.fit`: staged fitting of a model to registrations (Sec. 5.5.2).
- :mod:`blsm.learn.smpl_reimpl`: the SMPL-type baseline (Sec. 5.5.1).
- :mod:`blsm.learn.evaluate`: held-out errors against the number of coefficients (Fig. 5.6).
- :mod:`blsm.learn.registrations`: reading a folder of registrations and picking held-out subsets.
"""
