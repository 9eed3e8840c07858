"""recovery: HMR-style BLSM regressor and mesh-convolution / BEGAN recovery networks.

Not built yet: it consumes ``synth`` datasets; see the open issues.
Dependency direction: ``blsm`` <- ``synth`` <- ``recovery``.
"""
