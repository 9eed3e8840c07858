"""The sample format of a generated dataset: the fields of one image and how they are encoded.

A dataset folder (``synth generate ... --out DIR``) holds ``manifest.json``, the shards
``shard-000000.tar`` ... (WebDataset layout, see :mod:`synth.dataset.shards`) and ``subjects/``, one
``<subject>.npz`` per person used (:mod:`synth.subjects`), so every sample's mesh can be rebuilt.

Every sample (key ``f"{index:09d}"``) has these members, all made by one render of one scene:

==================  =============================================================================
``rgb.png``         (H, W, 3) uint8 sRGB image.
``json``            the labels (below), UTF-8 JSON.
``mask.png``        (H, W) uint8, mode ``L``: 0 background, ``i + 1`` person ``i`` of ``people``.
``parts.png``       (H, W) uint8, mode ``P`` with :data:`PART_PALETTE`: 0 background, ``1 + k``
                    the thesis' part ``PART_NAMES[k]`` (head, torso, left_arm, right_arm, left_leg,
                    right_leg; left is the person's left).
``bones.png``       (H, W) uint8, mode ``P`` with :data:`BONE_PALETTE`: 0 background, ``1 + j`` the
                    bone ``BONE_NAMES[j]`` (the bone of largest skinning weight of the hit face).
``depth.exr``       (H, W) float32 OpenEXR, one channel ``Z``: camera-space z in metres of the
                    surface hit by the ray through the pixel centre; 0 where nothing is hit.
``corr.npy.gz``     (H, W, 3) float32 (gzip of ``numpy.save``): ``[face, b1, b2]``: the index of the
                    hit face of the person's rendered mesh (-1 on background) and the barycentric
                    coordinates of the hit point on it (``b0 = 1 - b1 - b2`` for the face's first
                    vertex). A person with hair has the body's ``F`` faces followed by the hair's
                    (:mod:`synth.hair`): a face index ``>= F`` is hair, which has no point of the
                    body surface under it. A person with clothes (``garments``) has then ``F``
                    faces of the cloth layer (face ``F + Fh + f`` lies over body face ``f``,
                    ``Fh`` the hair's faces or 0) and the skirt's (``>= 2F + Fh``;
                    :mod:`synth.garments`).
==================  =============================================================================

With ``labels.topology`` (off by default) a sample also has ``vertices_<name>.npy.gz``: (P, V2, 3)
float32 (gzip of ``numpy.save``), the people's bodies in a second mesh topology, world metres, in
mask order (:mod:`synth.topology`; docs/reparam.md).

Every label pixel is the first hit of the ray through the pixel centre ``(u + 0.5, v + 0.5)``: the
pixel whose top-left corner is ``(u, v)`` covers ``[u, u + 1) x [v, v + 1)`` in the OpenCV image
coordinates used by ``K``. The RGB is the same scene with the same camera rendered with many samples
per pixel, so its edges are anti-aliased while the labels are exact per pixel centre.

The JSON (``format`` "blsm-synth-sample", ``version`` 1) holds:

- ``index``, ``seed``; ``image``: ``width``, ``height``, ``pixel_center`` (0.5);
- ``camera``: ``K`` (3x3), ``R`` (3x3) and ``t`` (3) world to camera (OpenCV: x right, y down,
  z forward), and what the sampler drew (``info``);
- ``background``: its kind and source, rotation and exposure;
- ``keypoint_names`` (the model's keypoints), ``bone_names``, ``part_names``;
- ``people``: one entry per person, in mask order:
  ``subject`` (id in ``subjects/``), ``pipeline`` (rigged, raw or blsm), ``motion`` (source, clip,
  frame), ``hair`` (only with hair: the :class:`synth.hair.HairSpec` it was grown from),
  ``garments`` (only with clothing geometry: the :class:`synth.garments.GarmentSpec`; every other
  label stays the body's underneath), ``blsm`` (``pose`` 47 unconstrained values x of Eq. 6, ``angles`` 47 radians, ``bone``,
  ``shape``, ``global_orient`` axis-angle, ``transl`` metres), ``bone_lengths`` (metres, per bone),
  ``keypoints_3d`` (K, 3) world metres, ``keypoints_3d_cam`` (K, 3) camera metres,
  ``keypoints_2d`` (K, 2) pixels, ``visible`` (K) whether the ray through the keypoint's pixel first
  hits this person on a face of the keypoint's own body region (hair counts as the head for the
  joints inside it and hides the surface keypoints under it: eyes, ears, nose), ``in_frame`` (K), ``box``
  ``[x0, y0, x1, y1]`` pixel edges of the person's visible mask, ``box_full`` the box of the
  person's whole projected mesh (may leave the image; null in a sequence's frame where the person is
  wholly behind the camera), ``pixels`` (visible mask area).

Optional keys, each only where its option is on (a default config writes none of them):

- ``occluders`` (with ``occluders.enabled`` or seats): the objects that belong to no person
  (:class:`synth.occluders.Occluder` records);
- ``placement`` (with ``people.placement: close``, :mod:`synth.close`): the image's
  ``arrangement``, whether the seated people share one ``bench``, and per placed pair ``people``
  [partner, person], the ``arrangement`` placed, ``depth_mm`` (the deepest vertex of one inside the
  other, exact test) and ``gap_mm`` (their closest vertex-to-surface distance);
- ``contacts`` (with ``labels.contact_distance``, :mod:`synth.contacts`): per pair of people ``i < j``,
  ``people``, ``distance`` (metres), ``vertices`` (two sorted lists of body-mesh vertex indices within
  ``distance`` of the other's body surface, inside included), ``parts`` (their part names) and
  ``closest_mm`` (their smallest signed vertex-to-surface distance; null over 50 mm).

With ``labels.occupancy`` = N a sample also has ``occupancy.npy.gz``: (P, N, 4) float32 (gzip of
``numpy.save``), per person in mask order N points in the camera frame (metres) and 1 where the
point is inside the person's body mesh (exact winding-number test), else 0 (:mod:`synth.contacts`).

**Precision.** Every real number of the JSON (``K``, ``R``, ``t``, keypoints, BLSM parameters) is
rounded to ``JSON_DECIMALS`` = 6 decimals, an error of at most ``JSON_ROUNDING`` = 5e-7 (metres,
pixels, radians). A check that recomputes one stored value from others must allow for that
rounding carried through its formula; :func:`camera_point_tolerance` and
:func:`projection_tolerance` give the first-order bounds for ``keypoints_3d_cam = R keypoints_3d +
t`` and ``keypoints_2d = project(K, R, t, keypoints_3d)``, with ``e = JSON_ROUNDING`` and ``X`` a
stored world point, ``x = R X + t`` its camera coordinates, ``a = x / z``, ``b = y / z``:

- camera coordinates (each component): ``|dx| <= e (|X|_1 + |R_i|_1 + 1) <= e (|X|_1 + sqrt(3) + 1)``
  (the rounding of ``R``, of ``X`` and of ``t``); the stored ``x`` adds another ``e``;
- pixels: ``|du| <= (|K_00| + |K_01|) dx (1 + max(|a|, |b|)) / z + e (|a| + |b| + 1) + e`` (the
  division by ``z``, the rounding of ``K`` and of the stored 2D point), ``dv`` likewise with row 1.

A keypoint 20 m away seen with a 400 mm lens (about 2800 px of focal length in a 256 px image)
allows about 7e-4 px; one 3 m away with a 50 mm lens, about 2e-4 px. Any real error of 0.05 px or
more is found.

The correspondences (``corr``) are single precision: the renderer finds the hit of each pixel-centre
ray in float32 (the ray's origin and direction from float32 transforms, the ray-triangle test on
vertices taken relative to the ray's origin, the hit interpolated from its barycentrics) and ``corr``
stores float32 barycentrics. The point a correspondence names on the mesh rebuilt from the JSON
(:mod:`synth.validate`) is off the pixel-centre ray by at most

- ``HIT_ULPS u (|X| + D) (1 + tan th)`` from the single precision, with ``u = FLOAT32_ROUNDING`` =
  2^-24, ``D = |x|`` the ray's length and ``th`` the angle between the ray and the face's normal:
  each rounding is relative to a length up to ``|X| + D`` (the hit, the camera's position, the
  ray), and a rounding along the ray in the ray-triangle test slides the hit within the face by
  ``tan th`` times itself. Measured, with Mitsuba 3 (``llvm_ad_rgb``): at most 1.4 ``u (|X| + D)
  (1 + tan th)`` beyond the rounding of ``K``, ``R``, ``t``, over 337k pixels of 308 generated
  images (307 with 135-600 mm lenses, people up to 95 m away); ``HIT_ULPS`` = 8;
- ``e REBUILD_LEVER`` from the rebuilt mesh: its 53 rounded BLSM values (pose, ``global_orient``,
  ``transl``) each move a vertex by at most ``e`` times its sensitivity to that value, whose sum over
  the 53 is under 11 m on each of 12 people measured (lever arms along the kinematic chain, hair
  included); ``REBUILD_LEVER`` = 16 m.

:func:`correspondence_tolerance` carries that offset ``dX`` through the projection as for a
keypoint, ``(|K_00| + |K_01|) dX (1 + max(|a|, |b|)) / z`` added to the keypoints' bound above
(``dv`` likewise). A 600 mm lens on a 128 px image (2133 px of focal length) and a person 60 m away
allow about 1.4e-3 px where the surface faces the camera, 3e-3 px at 60 degrees, 0.019 px at 86.6
degrees; a 50 mm lens on a 256 px image (356 px) and a person 3 m away, 1.4e-3 px facing (mostly
the rebuild); a 600 mm lens on a 1024 px image, 0.011 px facing. A correspondence 0.1 px off is
found unless its surface is seen within a few degrees of edge-on.
"""

from __future__ import annotations

import gzip
import io
import json
import os
import tempfile
from typing import Any

import numpy as np
from PIL import Image

from blsm import skeleton

FORMAT = "blsm-synth-sample"
VERSION = 1
JSON_DECIMALS = 6
JSON_ROUNDING = 0.5 * 10.0**-JSON_DECIMALS
FLOAT32_ROUNDING = 2.0**-24  # float32's unit roundoff: the renderer's hits, the stored ``corr``
HIT_ULPS = 8.0  # a rendered hit's offset from its ray, in FLOAT32_ROUNDING (|X| + D) (1 + tan th)
REBUILD_LEVER = 16.0  # metres: a rebuilt vertex's summed sensitivity to the rounded BLSM values
FIELDS = ("rgb.png", "json", "mask.png", "parts.png", "bones.png", "depth.exr", "corr.npy.gz")

PART_NAMES = ("head", "torso", "left_arm", "right_arm", "left_leg", "right_leg")
CONTACT_REGIONS = ("heel_l", "heel_r", "toe_l", "toe_r", "hand_l", "hand_r", "knee_l", "knee_r", "pelvis")
"""The body regions of a sequence sample's ground-contact labels (``contact``, ``contact_velocity``),
in this order wherever they are arrays (:mod:`synth.sequence` says how each is decided)."""
PART_PALETTE = np.array(
    [
        [0, 0, 0],  # background
        [230, 159, 0],  # head
        [86, 180, 233],  # torso
        [0, 158, 115],  # left_arm
        [213, 94, 0],  # right_arm
        [0, 114, 178],  # left_leg
        [204, 121, 167],  # right_leg
    ],
    dtype=np.uint8,
)
"""Background black, then the Okabe-Ito colours: distinguishable with colour-blindness."""

BONE_NAMES = tuple(skeleton.BONE_NAMES)


def _bone_palette() -> np.ndarray:
    # Golden-angle hues: neighbouring bone indices get distant colours.
    out = [[0, 0, 0]]
    for j in range(len(BONE_NAMES)):
        h = (j * 0.381966) % 1.0
        i, f = int(h * 6), h * 6 - int(h * 6)
        v, s = 0.95, 0.75 if j % 2 else 0.55
        p, q, t = v * (1 - s), v * (1 - s * f), v * (1 - s * (1 - f))
        rgb = [(v, t, p), (q, v, p), (p, v, t), (p, q, v), (t, p, v), (v, p, q)][i % 6]
        out.append([round(255 * c) for c in rgb])
    return np.array(out, dtype=np.uint8)


BONE_PALETTE = _bone_palette()
"""Background black, then one colour per bone in ``BONE_NAMES`` order."""


def json_round(a: Any) -> Any:
    """Array to nested lists of Python floats rounded to ``JSON_DECIMALS`` (stable JSON)."""
    return np.round(np.asarray(a, dtype=np.float64), JSON_DECIMALS).tolist()


def camera_point_tolerance(points: np.ndarray, R: np.ndarray) -> np.ndarray:
    """(N,) metres: how far ``R X + t`` computed from stored (rounded) values may be from the stored
    camera coordinates of the (N, 3) stored world points ``X`` (module docstring, Precision)."""
    x1 = np.abs(np.asarray(points, np.float64)).sum(-1)
    r1 = np.abs(np.asarray(R, np.float64)).sum(-1).max()
    return JSON_ROUNDING * (x1 + r1 + 2.0)


def projection_tolerance(
    points: np.ndarray, K: np.ndarray, R: np.ndarray, t: np.ndarray, point_error: np.ndarray | float = 0.0
) -> np.ndarray:
    """(N,) pixels: how far the projection of the (N, 3) stored world points with the stored ``K``,
    ``R``, ``t`` may be from the stored ``keypoints_2d``, from the rounding alone (module
    docstring, Precision), plus ``point_error`` (metres, scalar or (N,)) by which each point
    itself may be off (:func:`correspondence_tolerance`). Points must be in front of the camera."""
    K, R = np.asarray(K, np.float64), np.asarray(R, np.float64)
    pts = np.asarray(points, np.float64)
    xc = pts @ R.T + np.asarray(t, np.float64)
    z = xc[:, 2]
    ab = np.abs(xc[:, :2] / z[:, None])
    dx = JSON_ROUNDING * (np.abs(pts).sum(-1) + np.abs(R).sum(-1).max() + 1.0) + point_error
    gain = np.maximum(np.abs(K[0, :2]).sum(), np.abs(K[1, :2]).sum())
    return gain * dx * (1.0 + ab.max(-1)) / z + JSON_ROUNDING * (ab.sum(-1) + 2.0)


def correspondence_tolerance(
    points: np.ndarray, normals: np.ndarray, K: np.ndarray, R: np.ndarray, t: np.ndarray
) -> np.ndarray:
    """(N,) pixels: how far the projection of the (N, 3) world points that correspondences name on
    the rebuilt mesh may be from their pixel centres, from the labels' single precision, the
    rebuild from rounded parameters and the rounding of ``K``, ``R``, ``t`` (module docstring,
    Precision). ``normals`` (N, 3): the normals of their faces (any length). A face seen edge-on
    (or of no area) pins no point along the ray: its tolerance is huge. Points must be in front of
    the camera."""
    R = np.asarray(R, np.float64)
    pts = np.asarray(points, np.float64)
    ray = pts @ R.T + np.asarray(t, np.float64)  # from the camera's centre, camera coordinates
    dist = np.linalg.norm(ray, axis=-1)
    n = np.asarray(normals, np.float64) @ R.T
    with np.errstate(divide="ignore", invalid="ignore"):
        cos = np.abs((n * ray).sum(-1)) / (np.linalg.norm(n, axis=-1) * dist)
    cos = np.clip(np.nan_to_num(cos, nan=0.0), FLOAT32_ROUNDING, 1.0)
    tan = np.sqrt(1.0 - cos * cos) / cos
    hit = HIT_ULPS * FLOAT32_ROUNDING * (np.linalg.norm(pts, axis=-1) + dist) * (1.0 + tan)
    return projection_tolerance(pts, K, R, t, point_error=hit + JSON_ROUNDING * REBUILD_LEVER)


def seen_keypoints(person: dict[str, Any]) -> np.ndarray:
    """(K,) bool: a person's keypoints that are in frame and visible (``visible & in_frame``)."""
    return np.asarray(person["visible"], bool) & np.asarray(person["in_frame"], bool)


def person_box(person: dict[str, Any]) -> tuple[float, float, float, float]:
    """``(x0, y0, x1, y1)``: the person's visible ``box``, or ``box_full`` when nothing is visible."""
    x0, y0, x1, y1 = (float(v) for v in (person.get("box") or person["box_full"]))
    return x0, y0, x1, y1


# ------------------------------------------------------------------------------------------------
# Encoders (deterministic bytes: the same arrays always give the same bytes)


def encode_png(image: np.ndarray, palette: np.ndarray | None = None) -> bytes:
    """(H, W, 3) or (H, W) uint8 to PNG bytes; with ``palette`` (N, 3) a mode ``P`` label image."""
    if image.dtype != np.uint8:
        raise ValueError(f"PNG images must be uint8, got {image.dtype}")
    img = Image.fromarray(image)
    if palette is not None:
        if image.ndim != 2:
            raise ValueError(f"a label image must be (H, W), got {image.shape}")
        img = Image.fromarray(image, mode="L").convert("P")
        img.putpalette(palette.reshape(-1).tolist())
    buf = io.BytesIO()
    img.save(buf, format="PNG", compress_level=1)  # fast (as OpenCV's default); ~25 % larger than 6
    return buf.getvalue()


def decode_png(data: bytes, what: str = "png") -> np.ndarray:
    """PNG bytes to a uint8 array; label (``P``) images give their indices, not colours."""
    try:
        img = Image.open(io.BytesIO(data))
        img.load()
    except Exception as exc:  # PIL raises many types for bad data
        raise ValueError(f"{what}: not a readable PNG ({exc})") from None
    if img.mode == "P":
        return np.asarray(img, dtype=np.uint8)
    return np.asarray(img.convert("RGB") if img.mode not in ("L", "RGB") else img, dtype=np.uint8)


def encode_npy_gz(array: np.ndarray) -> bytes:
    buf = io.BytesIO()
    np.save(buf, np.ascontiguousarray(array), allow_pickle=False)
    return gzip.compress(buf.getvalue(), compresslevel=1, mtime=0)  # fast; ~10 % larger than 6


def decode_npy_gz(data: bytes, what: str = "npy.gz") -> np.ndarray:
    try:
        return np.load(io.BytesIO(gzip.decompress(data)), allow_pickle=False)
    except Exception as exc:
        raise ValueError(f"{what}: not a readable gzipped .npy ({exc})") from None


_SHM = "/dev/shm"


def encode_exr(depth: np.ndarray) -> bytes:
    """(H, W) float32 metres to single-channel (``Z``) zip-compressed OpenEXR bytes (OpenImageIO)."""
    import OpenImageIO as oiio

    depth = np.ascontiguousarray(depth, dtype=np.float32)
    if depth.ndim != 2:
        raise ValueError(f"depth must be (H, W), got {depth.shape}")
    spec = oiio.ImageSpec(depth.shape[1], depth.shape[0], 1, "float")
    spec.channelnames = ("Z",)
    spec.attribute("compression", "zip")
    # OpenImageIO stamps the current time otherwise; a fixed one keeps shards byte-reproducible.
    spec.attribute("DateTime", "1970:01:01 00:00:00")
    # OpenImageIO's Python API writes files only: a temporary one, in memory (/dev/shm) where there is one.
    fd, tmp = tempfile.mkstemp(suffix=".exr", dir=_SHM if os.access(_SHM, os.W_OK) else None)
    os.close(fd)
    try:
        out = oiio.ImageOutput.create(tmp)
        if out is None or not out.open(tmp, spec):
            raise RuntimeError(f"OpenImageIO cannot write EXR: {oiio.geterror()}")
        out.write_image(depth[..., None])
        out.close()
        with open(tmp, "rb") as f:
            return f.read()
    finally:
        os.unlink(tmp)


def decode_exr(data: bytes, what: str = "exr") -> np.ndarray:
    """OpenEXR bytes to an (H, W) float32 array (first channel)."""
    import OpenImageIO as oiio

    fd, tmp = tempfile.mkstemp(suffix=".exr")
    try:
        with os.fdopen(fd, "wb") as f:
            f.write(data)
        inp = oiio.ImageInput.open(tmp)
        if inp is None:
            raise ValueError(f"{what}: not a readable EXR ({oiio.geterror()})")
        arr = inp.read_image("float")
        inp.close()
    finally:
        os.unlink(tmp)
    arr = np.asarray(arr, dtype=np.float32)
    return arr[..., 0] if arr.ndim == 3 else arr


def encode_json(obj: Any) -> bytes:
    return (json.dumps(obj, sort_keys=True, separators=(",", ":"), allow_nan=False) + "\n").encode()


def decode_json(data: bytes, what: str = "json") -> Any:
    try:
        return json.loads(data.decode("utf-8"))
    except (UnicodeDecodeError, json.JSONDecodeError) as exc:
        raise ValueError(f"{what}: not valid JSON ({exc})") from None


def decode_sample(fields: dict[str, bytes], what: str = "sample") -> dict[str, Any]:
    """All members of one sample as arrays: ``rgb``, ``json``, ``mask``, ``parts``, ``bones``,
    ``depth``, ``corr`` (the ones present)."""
    out: dict[str, Any] = {}
    for name, data in fields.items():
        where = f"{what}.{name}"
        if name == "json":
            out["json"] = decode_json(data, where)
        elif name.endswith(".png"):
            out[name[:-4]] = decode_png(data, where)
        elif name.endswith(".exr"):
            out[name[:-4]] = decode_exr(data, where)
        elif name.endswith(".npy.gz"):
            out[name[:-7]] = decode_npy_gz(data, where)
    return out


def colorize(labels: np.ndarray, palette: np.ndarray) -> np.ndarray:
    """(H, W) label indices to (H, W, 3) uint8 colours (for previews)."""
    return palette[np.clip(labels, 0, len(palette) - 1)]
