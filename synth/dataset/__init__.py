"""The dataset contract, apart from the generator that writes it: the sample format (:mod:`.format`),
the shards and manifest (:mod:`.shards`), the index of a dataset folder (:mod:`.index`), the crop
geometry (:mod:`.crops`) and the PyTorch readers of images (:mod:`.images`) and of sequences
(:mod:`.sequences`). No module here imports the generator (a test checks its import closure), so a
training job reads datasets without Mitsuba, Anny or the renderer.
"""
