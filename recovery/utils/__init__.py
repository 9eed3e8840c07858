"""Helpers of every part: rotations and the camera (:mod:`.geometry`), the z-buffer rasteriser
(:mod:`.raster`), mesh overlays without Mitsuba (:mod:`.viz`) and learning-rate schedules
(:mod:`.schedule`)."""
