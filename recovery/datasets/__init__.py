"""Training data: pre-cropped caches of ``synth`` datasets (:mod:`.cache`), their per-batch
augmentation (:mod:`.augment`), the resumable data order (:mod:`.sampling`), the loaders a run reads
(:mod:`.loaders`), meshes made without rendering (:mod:`.meshes`) and the discriminator's real poses
(:mod:`.real_poses`)."""
