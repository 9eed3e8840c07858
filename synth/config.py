"""Generator configuration: YAML files loaded into frozen dataclasses, strictly.

Every key must be a field of its dataclass (an unknown or misspelt key is an error naming the file and
the key's path, e.g. ``configs/synth/x.yaml: camera.focal: unknown key (known: focal_mm, ...)``);
values are checked against the field types (int, float, bool, str, tuples of them, nested
dataclasses) and then by each dataclass's own ``__post_init__``. Omitted keys keep their defaults,
so an empty file is the embedded default configuration. The file must be UTF-8 (a leading
byte-order mark is allowed).

Limits, checked when the config is loaded, before any work:

- ``camera.width`` and ``camera.height`` at most ``MAX_IMAGE_SIDE`` = 8192 px;
- the estimated memory of rendering one image, :func:`render_memory_bytes` (per worker process),
  at most ``MAX_RENDER_GIB`` = 32 GiB (the environment variable ``SYNTH_MAX_RENDER_GIB`` raises or
  lowers it: it is a property of the machine, not of the dataset, so it is not a config key);
- ``num`` at most ``MAX_SAMPLES`` = 10^9 (sample keys have nine digits).
"""

from __future__ import annotations

import math
import os
from dataclasses import dataclass, field
from pathlib import Path
from typing import Any

from blsm.config import config_from_dict as from_dict
from blsm.io import read_yaml
from synth.backgrounds import KINDS, background_kind
from synth.camera import MAX_IMAGE_SIDE, CameraConfig

MAX_SAMPLES = 10**9
MAX_RENDER_GIB = 32.0
RENDER_BYTES_PER_SAMPLE = 256
"""Mitsuba's wavefront path tracer keeps every sample of an image in flight at once: a ray, its
throughput and radiance, the random generator's state and a surface interaction, about 60 floats."""
LABEL_BYTES_PER_PIXEL = 256
"""The film, the one-sample label pass (depth, position, face) and the label arrays made from it."""


def render_memory_bytes(width: int, height: int, spp: int) -> int:
    """Estimated peak memory (bytes) of one image in one worker: ``W * H * (spp *
    RENDER_BYTES_PER_SAMPLE + LABEL_BYTES_PER_PIXEL)``; 256 x 256 at 16 spp is about 0.3 GiB."""
    return width * height * (spp * RENDER_BYTES_PER_SAMPLE + LABEL_BYTES_PER_PIXEL)


def max_render_gib() -> float:
    """The memory limit of :func:`render_memory_bytes`, GiB (``SYNTH_MAX_RENDER_GIB`` overrides it)."""
    env = os.environ.get("SYNTH_MAX_RENDER_GIB", "")
    try:
        return float(env) if env else MAX_RENDER_GIB
    except ValueError:
        raise ValueError(f"SYNTH_MAX_RENDER_GIB must be a number of GiB, got {env!r}") from None


@dataclass(frozen=True)
class OutputConfig:
    """How samples are written: samples per shard."""

    shard_size: int = 256

    def __post_init__(self) -> None:
        if self.shard_size < 1:
            raise ValueError(f"output.shard_size must be positive, got {self.shard_size}")


@dataclass(frozen=True)
class LabelsConfig:
    """Optional labels (off by default). ``topology``: a model file from ``blsm reparam``; every
    sample then gets ``vertices_<topology_name>.npy.gz``, the people's bodies in that topology
    (:mod:`synth.topology`). ``contact_distance`` (metres, > 0): the JSON's ``contacts``, the
    vertices of each pair of people within that distance of the other's body
    (:mod:`synth.contacts`). ``occupancy`` (points a person, > 0): ``occupancy.npy.gz``, points
    near and around each body with inside/outside from the exact test, in the camera frame."""

    topology: str = ""
    topology_name: str = "topo2"
    contact_distance: float = 0.0
    occupancy: int = 0

    def __post_init__(self) -> None:
        import re

        if not 0.0 <= self.contact_distance <= 0.5:
            raise ValueError(f"labels.contact_distance must be in [0, 0.5] metres (0: off), got {self.contact_distance}")
        if not 0 <= self.occupancy <= 100_000:
            raise ValueError(f"labels.occupancy must be 0 (off) to 100000 points a person, got {self.occupancy}")

        if not re.match(r"^[a-z0-9_]{1,32}$", self.topology_name):
            raise ValueError(f"labels.topology_name must be 1-32 of a-z, 0-9, _; got {self.topology_name!r}")


@dataclass(frozen=True)
class SubjectsConfig:
    """Who is rendered: ``anny`` (``count`` people sampled from Anny) or ``folder`` (user scans in
    the folder format of :mod:`synth.scans`, path relative to the working directory).

    Anny's people are adults aged uniformly in ``age`` (years) or, with probability ``children``,
    children aged uniformly in ``child_age`` (:class:`synth.subjects.Population`). The default --
    adults 18-80, 10 % children of 5-17 -- holds no infant; ``age: [0, 90], children: 0`` is Anny's
    own population (all ages, infants included), which the generator used before these keys.

    ``detail`` (off by default; Anny only) paints face, skin and hand detail into each person's
    texture (:mod:`synth.skin_detail`: eyes in eyeballs that close Anny's empty sockets, eyebrows,
    lips, flush, stubble or beards for some men, pores, freckles, moles, knuckles, palms, nails),
    drawn from a random stream of its own: off, subjects are the same as without this key."""

    source: str = "anny"
    count: int = 8
    folder: str = ""
    texture_size: int = 1024
    age: tuple[float, float] = (18.0, 80.0)
    children: float = 0.1
    child_age: tuple[float, float] = (5.0, 17.0)
    detail: bool = False

    def __post_init__(self) -> None:
        if self.source not in ("anny", "folder"):
            raise ValueError(f"subjects.source must be anny or folder, got {self.source!r}")
        if not isinstance(self.detail, bool):
            raise ValueError(f"subjects.detail must be true or false, got {self.detail!r}")
        if self.detail and self.source != "anny":
            raise ValueError("subjects.detail applies to source: anny only (scans keep their own textures)")
        if self.source == "folder" and not self.folder:
            raise ValueError("subjects.folder is needed with source: folder")
        if self.count < 1:
            raise ValueError(f"subjects.count must be positive, got {self.count}")
        if not 16 <= self.texture_size <= 8192:
            raise ValueError(f"subjects.texture_size must be in [16, 8192], got {self.texture_size}")
        try:
            self.population()
        except ValueError as exc:
            raise ValueError(f"subjects: {exc}") from None

    def population(self) -> Any:
        """The :class:`synth.subjects.Population` of these keys."""
        from synth.subjects import Population

        if len(self.age) != 2 or len(self.child_age) != 2:
            raise ValueError(f"age and child_age must be [low, high], got {list(self.age)}, {list(self.child_age)}")
        return Population(age=tuple(map(float, self.age)), children=float(self.children),
                          child_age=tuple(map(float, self.child_age)))


@dataclass(frozen=True)
class PosesConfig:
    """Where poses come from: ``prior`` (the pose prior; ``prior`` file, empty for the packaged
    one), ``library`` (frames of the clips in the motion library folder ``library``), or ``mix``
    (the library with probability ``library_rate``, else the prior). ``clips`` keeps only the named
    clips of the library (empty: all) and ``exclude_clips`` leaves the named ones out, so that a test
    set can use motions held out of training (e.g. the clips held out of the packaged prior).

    ``plausible`` (on by default) re-draws a prior sample whose foot points backwards or whose limb
    passes through the torso (:mod:`blsm.mocap.plausible`), up to ``max_redraws`` times; off, every
    prior draw is used as drawn (the generator before this option). Library frames are real poses
    and are never re-drawn.

    ``child_clips`` matches motions to age: when set, people younger than 18 (Anny's age) take
    library frames from these clips only (walking, playing) while adults take any clip; empty, every
    person draws from every clip.

    ``seated_rate`` and ``arms_rate`` (0, off, by default; :mod:`synth.postures`) widen the prior's
    draws: the probability that a person sits on a box seat, and that each arm is drawn uniformly
    within its joint limits (prior draws only; library frames stay as captured)."""

    source: str = "prior"
    prior: str = ""
    library: str = ""
    library_rate: float = 0.5
    clips: tuple[str, ...] = ()
    exclude_clips: tuple[str, ...] = ()
    plausible: bool = True
    max_redraws: int = 100
    child_clips: tuple[str, ...] = ()
    seated_rate: float = 0.0
    arms_rate: float = 0.0

    def __post_init__(self) -> None:
        if self.source not in ("prior", "library", "mix"):
            raise ValueError(f"poses.source must be prior, library or mix, got {self.source!r}")
        if self.source != "prior" and not self.library:
            raise ValueError(f"poses.library (a motion library folder) is needed with source: {self.source}")
        if (self.clips or self.exclude_clips or self.child_clips) and self.source == "prior":
            raise ValueError("poses.clips, exclude_clips and child_clips need source: library or mix")
        if not 0.0 <= self.library_rate <= 1.0:
            raise ValueError(f"poses.library_rate must be in [0, 1], got {self.library_rate}")
        for key in ("seated_rate", "arms_rate"):
            if not 0.0 <= getattr(self, key) <= 1.0:
                raise ValueError(f"poses.{key} must be in [0, 1], got {getattr(self, key)}")
        if (self.seated_rate or self.arms_rate) and self.source == "library":
            raise ValueError("poses.seated_rate and arms_rate change prior draws: they need source: prior or mix")
        if not 1 <= self.max_redraws <= 10000:
            raise ValueError(f"poses.max_redraws must be in [1, 10000], got {self.max_redraws}")


@dataclass(frozen=True)
class CloseConfig:
    """``people.close``: the weights of the arrangements of ``people.placement: close``
    (:mod:`synth.close`: side, facing, hands, shoulder, seated), the deepest vertex allowed inside
    another person's body or seat (``tolerance``, metres), the spread of the relative facing
    (``yaw_deg``) and how far a seated person may be raised to share a bench (``max_raise``, metres)."""

    side: float = 1.0
    facing: float = 1.0
    hands: float = 1.0
    shoulder: float = 1.0
    seated: float = 1.0
    tolerance: float = 0.002
    yaw_deg: float = 20.0
    max_raise: float = 0.1

    def weights(self) -> dict[str, float]:
        return {"side": self.side, "facing": self.facing, "hands": self.hands, "shoulder": self.shoulder,
                "seated": self.seated}

    def __post_init__(self) -> None:
        w = self.weights()
        if min(w.values()) < 0 or not sum(w.values()) > 0:
            raise ValueError(f"people.close weights must be >= 0 and not all 0, got {w}")
        if not 0.0 <= self.tolerance <= 0.05:
            raise ValueError(f"people.close.tolerance must be in [0, 0.05] metres, got {self.tolerance}")
        if not 0.0 <= self.yaw_deg <= 90.0 or not 0.0 <= self.max_raise <= 0.5:
            raise ValueError(f"people.close: yaw_deg in [0, 90] and max_raise in [0, 0.5], got {self.yaw_deg}, {self.max_raise}")


@dataclass(frozen=True)
class PeopleConfig:
    """How many people per image (uniform in [min, max]) and the gap (metres) kept between their
    footprints, so that they never interpenetrate.

    ``placement``: ``apart`` (default; the footprints ``gap`` apart) or ``close`` (people within
    reach, touching without interpenetrating: :mod:`synth.close`, arranged by ``close``).

    ``distinct``: whether the people of one image (or clip) are different subjects. ``null``
    (default): they are whenever the subject pool holds ``max`` subjects; with fewer, a subject
    repeats only once every subject is in the image, and the run says so in one line before it
    starts. ``true``: they must be; a pool smaller than ``max`` is an error before any work.
    ``false``: subjects are drawn with replacement (twins possible), as before this key: the images
    of a dataset made before it (:func:`synth.people.draw_subject`; the manifest holds the key, so
    ``--resume`` into such a dataset is refused all the same)."""

    min: int = 1
    max: int = 1
    gap: float = 0.1
    distinct: bool | None = None
    placement: str = "apart"
    close: CloseConfig = field(default_factory=CloseConfig)

    def __post_init__(self) -> None:
        if not 1 <= self.min <= self.max <= 8:
            raise ValueError(f"people must satisfy 1 <= min <= max <= 8, got {self.min}, {self.max}")
        if self.placement not in ("apart", "close"):
            raise ValueError(f"people.placement must be apart or close, got {self.placement!r}")
        if self.gap < 0:
            raise ValueError(f"people.gap must be >= 0, got {self.gap}")


@dataclass(frozen=True)
class BackgroundConfig:
    """Backgrounds (:mod:`synth.backgrounds`): ``default`` (embedded procedural sky), ``hdri`` or
    ``images`` (a ``folder``); exposure in stops, drawn uniformly; environment width in texels.
    ``files`` keeps only the named files of the folder (empty: all) and ``exclude`` leaves the named
    ones out, so that train and test sets can hold out backgrounds of one folder. ``align_horizon``
    (images): where the folder's ``plates.json`` gives a plate's horizon, the plate is cropped so
    that its horizon lies on the camera's, and the people stand on the photograph's ground
    (:func:`synth.backgrounds.plates.crop_backplate_at_horizon`); the sample's background info records
    ``horizon_row`` (null where the camera is not upright or no crop fits: a random crop then)."""

    kind: str = "default"
    folder: str = ""
    files: tuple[str, ...] = ()
    exclude: tuple[str, ...] = ()
    exposure_ev: tuple[float, float] = (-0.5, 0.5)
    env_width: int = 512
    align_horizon: bool = True

    def __post_init__(self) -> None:
        kind = background_kind(self.kind)
        if kind.needs_folder and not self.folder:
            raise ValueError(f"background.folder is needed with kind: {self.kind}")
        if not self.exposure_ev[0] <= self.exposure_ev[1]:
            raise ValueError(f"background.exposure_ev must be [low, high], got {list(self.exposure_ev)}")
        if (self.files or self.exclude) and not kind.needs_folder:
            folders = " or ".join(k for k, v in KINDS.items() if v.needs_folder)
            raise ValueError(f"background.files and background.exclude need kind: {folders}")
        if not 64 <= self.env_width <= 8192:
            raise ValueError(f"background.env_width must be in [64, 8192], got {self.env_width}")


SAMPLERS = ("independent", "stratified", "multijitter", "ldsampler", "orthogonal")  # Mitsuba's
_SPP_RULE = {"stratified": "a square", "ldsampler": "a power of 4", "orthogonal": "the square of a prime",
             "multijitter": "an isqrt(spp) by ceil(spp / isqrt(spp)) grid"}


def sampler_spp(sampler: str, spp: int) -> int:
    """The samples per pixel Mitsuba's ``sampler`` renders when asked for ``spp``: ``stratified``
    rounds up to a square, ``ldsampler`` to a power of 4 (at least 4), ``orthogonal`` to the square
    of a prime and ``multijitter`` to an ``x`` by ``ceil(spp / x)`` grid (``x = isqrt(spp)``);
    ``independent`` takes any count. tests/synth/test_config.py checks these rules against
    Mitsuba's own ``sample_count()``."""
    if sampler == "stratified":
        return math.ceil(math.sqrt(spp) - 1e-9) ** 2
    if sampler == "ldsampler":
        return 4 ** max(1, math.ceil(math.log(spp, 4) - 1e-9))
    if sampler == "orthogonal":
        p = max(2, math.ceil(math.sqrt(spp) - 1e-9))
        while any(p % d == 0 for d in range(2, int(math.isqrt(p)) + 1)):
            p += 1
        return p * p
    if sampler == "multijitter":
        x = math.isqrt(spp)
        return x * math.ceil(spp / x)
    return spp


@dataclass(frozen=True)
class RenderConfig:
    """Mitsuba settings: samples per pixel and the ``sampler`` that places them, path depth, the
    variant (empty: llvm on CPU, cuda where a GPU works, probed once), the recycling of a worker
    after ``recycle_after`` images, and ``denoise``: Open Image Denoise on the path-traced RGB with
    albedo and normal from the same samples (:mod:`synth.denoise`). The default, multi-jittered 36
    spp undenoised, has less noise than an independent 128-spp render; at 192 px on a CPU it costs
    less than the denoiser (docs/realism.md, "Denoising"). The labels are the same for every setting."""

    spp: int = 36
    max_depth: int = 4
    variant: str = ""
    recycle_after: int = 2000
    denoise: bool = False
    denoise_quality: str = "high"
    sampler: str = "multijitter"

    def __post_init__(self) -> None:
        if self.spp < 1 or self.max_depth < 1 or self.recycle_after < 1:
            raise ValueError("render.spp, render.max_depth and render.recycle_after must be positive")
        if self.denoise_quality not in ("high", "balanced", "fast"):
            raise ValueError(f"render.denoise_quality must be high, balanced or fast, got {self.denoise_quality!r}")
        if self.sampler not in SAMPLERS:
            raise ValueError(f"render.sampler must be one of {', '.join(SAMPLERS)}, got {self.sampler!r}")
        used = sampler_spp(self.sampler, self.spp)
        if used != self.spp:
            raise ValueError(f"render.spp {self.spp} with render.sampler {self.sampler}: Mitsuba would render {used} "
                             f"samples per pixel ({_SPP_RULE[self.sampler]}); set render.spp to {used}")


@dataclass(frozen=True)
class EngineConfig:
    """How shards are spread over a Ray cluster (``synth generate --engine ray``). It changes no
    byte of the data, so resuming and merging ignore it: ``cpus_per_task`` CPUs are reserved for
    each shard task (and are Dr.Jit's threads in it); a task whose worker process or node dies is
    re-run up to ``max_retries`` times (a sample that fails for a data reason is never retried)."""

    cpus_per_task: int = 1
    max_retries: int = 3

    def __post_init__(self) -> None:
        if self.cpus_per_task < 1:
            raise ValueError(f"engine.cpus_per_task must be positive, got {self.cpus_per_task}")
        if self.max_retries < 0:
            raise ValueError(f"engine.max_retries must be non-negative, got {self.max_retries}")


@dataclass(frozen=True)
class GroundConfig:
    """The ground the people stand on (:mod:`synth.ground`): with ``shadows`` (on by default) the
    backdrop -- environment or backplate -- is darkened where the people shadow the plane ``y = 0``
    (a shadow catcher, ``samples`` shadow rays per ground pixel up to ``max_distance`` metres from
    the camera). Off, the environment is seen as before."""

    shadows: bool = True
    samples: int = 32
    max_distance: float = 60.0

    def __post_init__(self) -> None:
        if not 1 <= self.samples <= 1024:
            raise ValueError(f"ground.samples must be in [1, 1024], got {self.samples}")
        if not self.max_distance > 0:
            raise ValueError(f"ground.max_distance must be positive, got {self.max_distance}")


@dataclass(frozen=True)
class HairStyles:
    """Relative weights of the hair styles of :mod:`synth.hair` (0 leaves a style out)."""

    short: float = 0.35
    long: float = 0.3
    tied: float = 0.15
    curly: float = 0.2

    def __post_init__(self) -> None:
        w = [self.short, self.long, self.tied, self.curly]
        if min(w) < 0 or sum(w) <= 0:
            raise ValueError(f"hair.styles must be non-negative weights, not all 0, got {w}")


@dataclass(frozen=True)
class HairConfig:
    """Hair geometry on the people (:mod:`synth.hair`; on by default): each of Anny's people gets
    one hair, its style drawn by ``styles``' weights, in the colour of its painted hair. User scans
    (``subjects.source: folder``) carry their own hair and the ``raw`` pipeline shows scans as
    captured: neither grows any. Off, people have only the painted hair cap, as before."""

    enabled: bool = True
    styles: HairStyles = field(default_factory=HairStyles)


@dataclass(frozen=True)
class GarmentFits:
    """Relative weights of the garment fits of :mod:`synth.garments` (0 leaves a fit out)."""

    fitted: float = 0.3
    regular: float = 0.45
    loose: float = 0.25

    def __post_init__(self) -> None:
        w = [self.fitted, self.regular, self.loose]
        if min(w) < 0 or sum(w) <= 0:
            raise ValueError(f"garments.fits must be non-negative weights, not all 0, got {w}")


@dataclass(frozen=True)
class GarmentsConfig:
    """Clothing geometry (:mod:`synth.garments`; off by default): each of Anny's people wears its
    painted outfit as cloth over the body (a layer standing off the skin, a skirt or dress as a
    tube), its fit drawn by ``fits``' weights; a long-sleeved top is a jacket with probability
    ``jacket``, a skirt a dress with probability ``dress``. Labels stay the body's; masks and parts
    include the clothes. Needs the ``rigged`` pipeline and ``subjects.source: anny`` with subjects
    made by this version (their outfit borders, ``meta.outfit_cuts``)."""

    enabled: bool = False
    fits: GarmentFits = field(default_factory=GarmentFits)
    jacket: float = 0.4
    dress: float = 0.5

    def __post_init__(self) -> None:
        for name in ("jacket", "dress"):
            if not 0.0 <= getattr(self, name) <= 1.0:
                raise ValueError(f"garments.{name} must be a probability in [0, 1], got {getattr(self, name)}")


@dataclass(frozen=True)
class OccludersConfig:
    """Objects in front of the people (:mod:`synth.occluders`; off by default): with probability
    ``prob`` a sample gets 1 to ``max`` boxes and cylinders on the ground between the camera and its
    people. Pixels they cover belong to no person; keypoints behind them are not visible. Single
    images only (not with ``sequence``)."""

    enabled: bool = False
    prob: float = 0.5
    max: int = 2

    def __post_init__(self) -> None:
        if not 0.0 <= self.prob <= 1.0:
            raise ValueError(f"occluders.prob must be a probability in [0, 1], got {self.prob}")
        if not 1 <= self.max <= 4:
            raise ValueError(f"occluders.max must be in [1, 4], got {self.max}")


@dataclass(frozen=True)
class CameraPaths:
    """Relative weights of the camera paths of a sequence (:mod:`synth.camera_paths`; 0 leaves a
    path out) and their parameters, each drawn uniformly per sequence from its ``[low, high]``."""

    static: float = 1.0
    pan: float = 1.0
    dolly: float = 1.0
    orbit: float = 1.0
    tracking: float = 1.0
    zoom: float = 1.0
    handheld: float = 1.0
    portrait: float = 0.5
    long_lens: float = 0.5
    pan_smoothing_s: float = 0.4
    dolly_m: tuple[float, float] = (0.5, 2.0)
    orbit_deg_s: tuple[float, float] = (10.0, 40.0)
    tracking_smoothing_s: float = 0.8
    zoom_ratio: tuple[float, float] = (1.5, 3.0)
    shake_low_deg: tuple[float, float] = (0.3, 1.5)
    shake_low_hz: tuple[float, float] = (0.2, 1.0)
    shake_high_deg: tuple[float, float] = (0.03, 0.15)
    shake_high_hz: tuple[float, float] = (6.0, 12.0)
    shake_m: tuple[float, float] = (0.005, 0.02)
    long_lens_mm: tuple[float, float] = (135.0, 300.0)

    def weights(self) -> dict[str, float]:
        from synth.camera_paths import PATHS

        return {k: float(getattr(self, k)) for k in PATHS}

    def __post_init__(self) -> None:
        w = self.weights()
        if min(w.values()) < 0 or sum(w.values()) <= 0:
            raise ValueError(f"sequence.cameras weights must be non-negative, not all 0, got {w}")
        for name in ("dolly_m", "orbit_deg_s", "zoom_ratio", "shake_low_deg", "shake_low_hz", "shake_high_deg",
                     "shake_high_hz", "shake_m", "long_lens_mm"):
            v = getattr(self, name)
            if len(v) != 2 or not 0 <= v[0] <= v[1]:
                raise ValueError(f"sequence.cameras.{name} must be [low, high] with 0 <= low <= high, got {list(v)}")
        if self.zoom_ratio[0] < 1.0:
            raise ValueError(f"sequence.cameras.zoom_ratio must be >= 1 (zoom in or out by it), got {list(self.zoom_ratio)}")
        if self.long_lens_mm[0] <= 0:
            raise ValueError(f"sequence.cameras.long_lens_mm must be positive, got {list(self.long_lens_mm)}")
        if self.pan_smoothing_s < 0 or self.tracking_smoothing_s < 0:
            raise ValueError("sequence.cameras pan_smoothing_s and tracking_smoothing_s must be >= 0")


@dataclass(frozen=True)
class MotionBlur:
    """Motion blur (off by default): each frame is the mean of ``subframes`` renders at times spread
    evenly over the open shutter, ``shutter`` of the frame interval (0.5: a 180-degree shutter),
    centred on the frame's time; the labels are those of the centre sub-frame (``subframes`` is odd),
    i.e. of the frame's own time. Costs ``subframes`` renders a frame."""

    enabled: bool = False
    subframes: int = 5
    shutter: float = 0.5

    def __post_init__(self) -> None:
        if self.subframes < 1 or self.subframes % 2 == 0 or self.subframes > 64:
            raise ValueError(f"sequence.motion_blur.subframes must be odd, 1 to 63, got {self.subframes}")
        if not 0 < self.shutter <= 1:
            raise ValueError(f"sequence.motion_blur.shutter must be in (0, 1], got {self.shutter}")


@dataclass(frozen=True)
class ContactConfig:
    """Ground contact (:func:`synth.sequence.contact`): a body region touches the ground ``y = 0``
    when one of its vertices is within ``distance`` metres of it and slower than ``speed`` m/s. The
    field's velocity rule, reported beside it: the region's point (the keypoint; the toe base for the
    toes, :data:`synth.sequence.RULE_POINT`) slower than ``velocity_rule`` m/s."""

    distance: float = 0.015
    speed: float = 0.3
    velocity_rule: float = 0.3

    def __post_init__(self) -> None:
        if self.distance <= 0 or self.speed <= 0 or self.velocity_rule <= 0:
            raise ValueError("sequence.contact distance, speed and velocity_rule must be positive")


@dataclass(frozen=True)
class SequenceConfig:
    """Video (docs/video.md): with ``enabled``, ``num`` counts sequences of ``frames`` frames at
    ``fps``, ``per_shard`` sequences a shard. Each person plays a motion-library clip (root
    trajectory included, resampled to ``fps``) in one world frame, with one subject, background and
    light throughout, under a camera path drawn by ``cameras``' weights. Sequences need
    ``poses.source: library`` and clips at least ``frames / fps`` seconds long."""

    enabled: bool = False
    frames: int = 90
    fps: float = 30.0
    per_shard: int = 1
    cameras: CameraPaths = field(default_factory=CameraPaths)
    motion_blur: MotionBlur = field(default_factory=MotionBlur)
    contact: ContactConfig = field(default_factory=ContactConfig)

    def __post_init__(self) -> None:
        if not 2 <= self.frames <= 100000:
            raise ValueError(f"sequence.frames must be in [2, 100000], got {self.frames}")
        if not 1.0 <= self.fps <= 240.0:
            raise ValueError(f"sequence.fps must be in [1, 240], got {self.fps}")
        if self.per_shard < 1:
            raise ValueError(f"sequence.per_shard must be positive, got {self.per_shard}")


@dataclass(frozen=True)
class GeneratorConfig:
    """The top level of a ``configs/synth/*.yaml`` file.

    ``pipeline`` is one of ``rigged`` (default), ``raw``, ``blsm`` (thesis Fig. 6.11);
    ``subdivide`` (blsm only) splits every triangle into four once for denser labels; ``skip_bad``
    skips a sample that fails and lists it in the manifest instead of stopping.
    """

    seed: int = 0
    num: int = 64
    pipeline: str = "rigged"
    subdivide: bool = False
    skip_bad: bool = False
    subjects: SubjectsConfig = field(default_factory=SubjectsConfig)
    poses: PosesConfig = field(default_factory=PosesConfig)
    people: PeopleConfig = field(default_factory=PeopleConfig)
    camera: CameraConfig = field(default_factory=CameraConfig)
    background: BackgroundConfig = field(default_factory=BackgroundConfig)
    render: RenderConfig = field(default_factory=RenderConfig)
    ground: GroundConfig = field(default_factory=GroundConfig)
    hair: HairConfig = field(default_factory=HairConfig)
    garments: GarmentsConfig = field(default_factory=GarmentsConfig)
    occluders: OccludersConfig = field(default_factory=OccludersConfig)
    output: OutputConfig = field(default_factory=OutputConfig)
    engine: EngineConfig = field(default_factory=EngineConfig)
    sequence: SequenceConfig = field(default_factory=SequenceConfig)
    labels: LabelsConfig = field(default_factory=LabelsConfig)

    @property
    def occluder_slots(self) -> int:
        """The renderer's slots for objects that belong to no person: the scene's occluders and, with
        ``poses.seated_rate``, one seat per person (:mod:`synth.postures`)."""
        seated = self.poses.seated_rate or (self.people.placement == "close" and self.people.close.seated)
        return (self.occluders.max if self.occluders.enabled else 0) + (self.people.max if seated else 0)

    def __post_init__(self) -> None:
        if self.labels.topology and self.pipeline == "raw":
            raise ValueError("labels.topology needs a posable pipeline (rigged or blsm), not raw")
        if self.seed < 0:
            raise ValueError(f"seed must be non-negative, got {self.seed}")
        what = "sequences" if self.sequence.enabled else "images"  # what num counts
        if self.num < 1:
            raise ValueError(f"num (the number of {what}) must be positive, got {self.num}")
        if self.num > MAX_SAMPLES:
            raise ValueError(f"num (the number of {what}) must be at most {MAX_SAMPLES} (sample keys have nine "
                             f"digits), got {self.num}")
        if self.pipeline not in ("rigged", "raw", "blsm"):
            raise ValueError(f"pipeline must be rigged, raw or blsm, got {self.pipeline!r}")
        if (self.poses.seated_rate or self.poses.arms_rate) and self.pipeline == "raw":
            raise ValueError("poses.seated_rate and arms_rate need a posable pipeline (rigged or blsm), not raw")
        if self.subdivide and self.pipeline != "blsm":
            raise ValueError("subdivide applies to the blsm pipeline only")
        if self.garments.enabled and (self.pipeline != "rigged" or self.subjects.source != "anny"):
            raise ValueError("garments.enabled needs pipeline: rigged and subjects.source: anny (the painted outfits)")
        if self.people.placement == "close" and self.pipeline == "raw":
            raise ValueError("people.placement: close needs a posable pipeline (rigged or blsm), not raw")
        if self.sequence.enabled:
            if self.people.placement != "apart":
                raise ValueError("people.placement: close applies to single images, not to sequence.enabled")
            if self.labels.occupancy:
                raise ValueError("labels.occupancy applies to single images, not to sequence.enabled")
            if self.occluders.enabled:
                raise ValueError("occluders.enabled applies to single images, not to sequence.enabled")
            if self.camera.frontal_rate:
                raise ValueError("camera.frontal_rate applies to single images, not to sequence.enabled")
            if self.poses.source != "library":
                raise ValueError("sequence.enabled needs poses.source: library (each person plays a motion clip)")
            if self.pipeline == "raw":
                raise ValueError("sequence.enabled needs a posable pipeline (rigged or blsm), not raw")
            if not background_kind(self.background.kind).follows_cameras:
                moving = [k for k, w in self.sequence.cameras.weights().items() if w > 0 and k not in ("static", "long_lens")]
                if moving:
                    ok = " or ".join(k for k, v in KINDS.items() if v.follows_cameras)
                    raise ValueError(f"sequence: a backplate photograph cannot follow a moving camera ({moving[0]}); "
                                     f"use background kind {ok}, or only static and long_lens cameras")
            if self.num * self.sequence.frames > MAX_SAMPLES:
                raise ValueError(f"num * sequence.frames must be at most {MAX_SAMPLES}, got {self.num * self.sequence.frames}")
        need, limit = render_memory_bytes(self.camera.width, self.camera.height, self.render.spp) / 2**30, max_render_gib()
        if need > limit:
            raise ValueError(
                f"rendering {self.camera.width}x{self.camera.height} px at {self.render.spp} spp needs about "
                f"{need:.1f} GiB per worker, over the limit of {limit:g} GiB (SYNTH_MAX_RENDER_GIB; "
                f"images are at most {MAX_IMAGE_SIDE} px a side)"
            )


def apply_overrides(data: Any, overrides: list[str] | tuple[str, ...], where: str) -> dict:
    """``data`` (a config mapping) with ``KEY=VALUE`` overrides applied: ``KEY`` a dotted path
    (``hair.enabled``, ``render.spp``), ``VALUE`` parsed as YAML (``false``, ``8``, ``[0, 90]``,
    ``[]``). Missing sections are created; the keys are then checked like the file's own."""
    import copy

    import yaml

    out = copy.deepcopy(data) if data is not None else {}
    if not isinstance(out, dict):
        return out  # from_dict reports the file's problem
    for item in overrides:
        key, sep, text = item.partition("=")
        if not sep or not key or any(not k for k in key.split(".")):
            raise ValueError(f"{where}: override {item!r} is not KEY=VALUE (e.g. hair.enabled=false)")
        try:
            value = yaml.safe_load(text)
        except yaml.YAMLError as exc:
            raise ValueError(f"{where}: override {key}: not a YAML value ({str(exc).splitlines()[0]})") from None
        node = out
        parts = key.split(".")
        for k in parts[:-1]:
            if not isinstance(node.get(k, {}), dict):
                raise ValueError(f"{where}: override {key}: {k} is not a section")
            node = node.setdefault(k, {})
        node[parts[-1]] = value
    return out


def load_config(path: str | Path, overrides: list[str] | tuple[str, ...] = ()) -> GeneratorConfig:
    """Read a generator configuration file (YAML; ``-`` for the embedded defaults) and apply
    ``KEY=VALUE`` overrides (:func:`apply_overrides`); see the module docstring."""
    where = "(defaults)" if str(path) == "-" else str(path)
    data = {} if str(path) == "-" else read_yaml(Path(path), "config")
    if overrides:
        data = apply_overrides(data, overrides, where)
        where += " with --set " + " ".join(overrides)
    return from_dict(GeneratorConfig, data, where)
