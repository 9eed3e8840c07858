"""The pose of each person of a sample: the packaged pose prior (with the plausibility check and the
seated and arm-range variations of :mod:`synth.postures`) or frames of a motion library
(``blsm mocap import``), as ``poses`` of the config says (:class:`PoseSource`)."""

from __future__ import annotations

from pathlib import Path
from typing import Any

import numpy as np
import torch

from synth.config import GeneratorConfig
from synth.postures import vary

__all__ = ["PoseSource"]


class PoseSource:
    """Draws a pose (x, global orientation) from the prior or the motion library."""

    def __init__(self, cfg: GeneratorConfig) -> None:
        import blsm
        from blsm.mocap.plausible import PoseChecker
        from blsm.mocap.prior import DEFAULT_PRIOR, load_prior

        self.cfg = cfg.poses
        self.prior_path = self.cfg.prior or DEFAULT_PRIOR
        self.prior = load_prior(self.prior_path)
        check = self.cfg.plausible and self.cfg.source != "library"
        self.model = blsm.load() if check or self.cfg.seated_rate or self.cfg.arms_rate else None  # loaded once
        self.checker = PoseChecker(self.model) if check else None
        self.clips: list[Any] = []
        if self.cfg.source != "prior":
            self.clips = self._load_clips()
        self.child_clips = [i for i, c in enumerate(self.clips) if c.name in self.cfg.child_clips]

    def _load_clips(self) -> list[Any]:
        """The library's clips the config keeps (``clips``, ``exclude_clips``); a ValueError naming
        the library for a clip it does not hold, or for none left."""
        from blsm.mocap.library import list_clips, load_clip

        try:
            files = list_clips(self.cfg.library)
        except ValueError as e:  # no folder, or no clips in it
            raise ValueError(
                f"{self.cfg.library}: no motion library (poses.library) there ({str(e).split(': ', 1)[-1]}); "
                "make it with `make motions` or set poses.library to a folder written by `blsm mocap import`"
            ) from None
        names = {Path(f).stem for f in files}
        unknown = [n for n in (*self.cfg.clips, *self.cfg.exclude_clips, *self.cfg.child_clips) if n not in names]
        if unknown:
            raise ValueError(f"{self.cfg.library}: the motion library has no clip {unknown[0]!r}")
        if self.cfg.clips:
            files = [f for f in files if Path(f).stem in self.cfg.clips]
        files = [f for f in files if Path(f).stem not in self.cfg.exclude_clips]
        if not files:
            raise ValueError(f"{self.cfg.library}: the motion library holds no clips (after clips/exclude_clips)")
        clips = [load_clip(f) for f in files]
        kept = {c.name for c in clips}
        left_out = [n for n in self.cfg.child_clips if n not in kept]
        if left_out:
            raise ValueError(f"{self.cfg.library}: poses.child_clips names {left_out[0]!r}, which clips/exclude_clips leave out")
        return clips

    def sample(self, rng: np.random.Generator, child: bool = False, seated: bool = False) -> tuple[np.ndarray, np.ndarray, dict]:
        """A pose for one person; ``child`` (younger than 18) restricts library frames to
        ``poses.child_clips`` where the config names them; ``seated`` seats a prior draw whatever
        ``poses.seated_rate`` says (:mod:`synth.close`'s benches)."""
        use_lib = self.cfg.source == "library" or (self.cfg.source == "mix" and rng.uniform() < self.cfg.library_rate)
        if use_lib:
            if child and self.child_clips:
                ci = self.child_clips[int(rng.integers(len(self.child_clips)))]
            else:
                ci = int(rng.integers(len(self.clips)))
            clip = self.clips[ci]
            fr = int(rng.integers(clip.num_frames))
            return clip.pose[fr].astype(np.float32), clip.global_orient[fr].astype(np.float32), {"source": "library", "clip": clip.name, "frame": fr}
        for redraws in range(self.cfg.max_redraws + 1):
            g = torch.Generator().manual_seed(int(rng.integers(2**62)))
            x = self.prior.sample(1, g)[0].numpy().astype(np.float32)
            varied = {}
            if seated or self.cfg.seated_rate or self.cfg.arms_rate:  # synth.postures; off, no draw is spent
                x, varied = vary(x, self.model, 1.0 if seated else self.cfg.seated_rate, self.cfg.arms_rate, rng)
            if self.checker is None:
                return x, np.zeros(3, np.float32), {"source": "prior", "clip": "", "frame": -1, **varied}
            if self.checker.check(torch.from_numpy(x)[None]).plausible[0]:
                return x, np.zeros(3, np.float32), {"source": "prior", "clip": "", "frame": -1, "redraws": redraws, **varied}
        raise ValueError(
            f"{self.prior_path}: no plausible pose in {self.cfg.max_redraws + 1} draws "
            "(a prior of implausible poses; set poses.plausible: false to use it as drawn)"
        )
