"""recovery: networks that recover a BLSM body from one image, trained on ``synth`` datasets.

HMR-BLSM (HMR's regressor with a BLSM head), the image-to-mesh spiral network with its BEGAN mesh
discriminator, and the mesh autoencoder (thesis chapters 4 and 6); the ``recovery`` command trains,
evaluates, predicts, exports and runs the real-photo transfer check (:mod:`recovery.cli`).

Sub-packages: ``models`` (backbones, heads, networks, losses), ``mesh`` (spiral and sampling
operators precomputed on the template), ``datasets`` (crop caches, augmentation, data order, meshes
without rendering), ``tasks`` (each network's training step, found by the config's ``task``),
``eval`` (metrics, evaluation, temporal and transfer checks) and ``utils`` (geometry, z-buffer,
overlays); ``weights`` holds the packaged checkpoint.
Dependency direction: ``blsm`` <- ``synth`` <- ``recovery``.
"""
