"""synth: the synthetic data generator (rig, repose, render with Mitsuba 3, write labelled shards).

In progress (issue 4): ``shards`` (atomic, byte-reproducible, resumable WebDataset shards with a
manifest and per-sample seeding), ``camera`` (OpenCV camera sampling that frames a person, with rare
views and truncation) and ``config`` (strict YAML configs). Subjects, rendering, labels, the
``synth`` command and the loaders are not built yet.
Dependency direction: ``blsm`` <- ``synth`` <- ``recovery``.
"""
