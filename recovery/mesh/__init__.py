"""Mesh operators of a BLSM model file with their cache (:mod:`.operators`): the hierarchy of
:mod:`blsm.spiral.hierarchy` (spiral sequences, down- and up-sampling) and a keypoint regressor."""
