"""synth: the synthetic data generator (rig, repose, render with Mitsuba 3, write labelled shards).

Not built yet: it depends on the BLSM model (``blsm``) and the motion library; see the open issues.
Dependency direction: ``blsm`` <- ``synth`` <- ``recovery``.
"""
