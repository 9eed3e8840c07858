"""Mesh operators precomputed once on the BLSM template: spiral sequences (:mod:`.spiral_sequences`),
down- and up-sampling (:mod:`.sampling`), and everything for a model file with its cache
(:mod:`.operators`)."""
