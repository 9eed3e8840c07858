"""Mesh convolution on the BLSM template (paper 000 Eqs. 9-11; thesis Sec. 4.3) and the BLSM-spiral
shape space.

- :mod:`.sequences`: spiral sequences (Eq. 10 / thesis Eq. 4.3), precomputed on a template.
- :mod:`.sampling`: quadric edge collapse down-sampling ``Q^d`` and barycentric up-sampling ``Q^u``.
- :mod:`.hierarchy`: both for every level of a mesh (:class:`~.hierarchy.MeshOperators`).
- :mod:`.conv`: ``SpiralConv`` (Eq. 9 / thesis Eq. 4.4), ``Pool``, ``Unpool``.
- :mod:`.decoder`: the spiral decoder (thesis Table 4.1's half) and the per-vertex normaliser.
- :mod:`.shape`: BLSM-spiral's shape decoder ``V_s = D(z)`` (Eq. 11), its model-file arrays.
- :mod:`.autodecoder`: learning ``D`` and one code per body jointly (Eq. 17, DeepSDF style).

``recovery`` builds its networks from these (``recovery.mesh.operators`` caches the hierarchy per
model file and adds the keypoint regressor); ``blsm`` imports nothing from ``recovery``.
"""
