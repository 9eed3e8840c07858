"""synth: the synthetic data generator (thesis Sec. 6.4.3, Fig. 6.11).

People (Anny stand-in scans or user scans, :mod:`synth.subjects`, :mod:`synth.scans`) registered
to BLSM and rigged by nearest-vertex weight painting are reposed (:mod:`synth.sample`), framed by
an OpenCV camera (:mod:`synth.camera`), rendered with Mitsuba 3 over a sky, HDRI or backplate
(:mod:`synth.render`, :mod:`synth.backgrounds`) with a pixel-centre label pass
(:mod:`synth.labels`), and written as WebDataset shards (:mod:`synth.dataset.shards`, fields in
:mod:`synth.dataset.format`). ``synth generate`` (:mod:`synth.generate`) runs the workers of
:mod:`synth.worker` in a process pool or as Ray tasks (:mod:`synth.engine_ray`). ``synth validate``, ``preview`` and ``export`` check, show and convert a
dataset; :class:`synth.dataset.images.SynthDataset` loads it for PyTorch. Configs: :mod:`synth.config`.
Dependency direction: ``blsm`` <- ``synth`` <- ``recovery``.
"""
