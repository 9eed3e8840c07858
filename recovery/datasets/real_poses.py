"""The pose discriminator's real poses: draws from the pose prior and frames of a motion library,
never the training images' own labels."""

from __future__ import annotations

from collections.abc import Sequence
from dataclasses import dataclass

import torch


@dataclass
class RealPoses:
    """The discriminator's real poses: angles (N, 47) from prior samples and library frames,
    drawn once; batches are drawn with a generator the trainer checkpoints."""

    angles: torch.Tensor
    sources: dict[str, int]

    def sample(self, n: int, generator: torch.Generator) -> torch.Tensor:
        idx = torch.randint(0, self.angles.shape[0], (n,), generator=generator)
        return self.angles[idx]


def real_poses(body: torch.nn.Module, prior_path: str, prior_samples: int, library: str,
               exclude_clips: Sequence[str], seed: int) -> RealPoses:
    """Real poses for the 47-D discriminator: never the training images' own labels.

    Args:
        body: the BLSM model (its Eq. 6 maps unconstrained values to angles).
        prior_path: pose prior file ("" for the packaged one).
        prior_samples: how many poses to draw from the prior.
        library: motion library folder ("" for none); clips in ``exclude_clips`` are left out.
        seed: seed of the prior draws.
    """
    from blsm.joint_limits import angles_from_unconstrained
    from blsm.mocap.prior import DEFAULT_PRIOR, load_prior

    chunks, sources = [], {}
    if prior_samples:
        prior = load_prior(prior_path or DEFAULT_PRIOR)
        x = prior.sample(prior_samples, torch.Generator().manual_seed(seed)).float()
        chunks.append(x)
        sources["prior"] = int(x.shape[0])
    if library:
        from blsm.mocap.library import list_clips, load_clip

        n = 0
        for f in list_clips(library):
            if f.stem in exclude_clips:
                continue
            clip = load_clip(f)
            chunks.append(torch.as_tensor(clip.pose, dtype=torch.float32))
            n += clip.num_frames
        sources["library"] = n
    if not chunks:
        raise ValueError("discriminator: no real poses (prior_samples is 0 and no library)")
    x = torch.cat(chunks)
    with torch.no_grad():
        angles = angles_from_unconstrained(x, body.dof_limits.float())
    return RealPoses(angles=angles, sources=sources)
