"""The BLSM model file: one versioned ``.npz`` archive (format ``blsm-model``, version 1).

Also the one reader and writer of versioned ``.npz`` files (:func:`write_versioned_npz`,
:func:`read_versioned_npz`) that every ``blsm`` file format uses, and the file helpers
(:func:`atomic_write`, :func:`read_npz`, :func:`read_yaml`, :func:`sha256_file`).

Arrays (V vertices, F faces, J bones, D = 47 atoms, Kb bone and Ks shape coefficients, K keypoints):

=====================  ==================  ==========================================================
key                    shape / dtype       meaning
=====================  ==================  ==========================================================
format                 str                 ``"blsm-model"``
format_version         int                 1
meta_json              str                 JSON: bone/part/keypoint names, parents, build provenance
dof_table_yaml         str                 the DoF table (``blsm/data/dofs.yaml``) it was built with
template               (V, 3) float32      mean template V_mean, metres, Y up, facing +Z
faces                  (F, 3) int32        triangles, counter-clockwise seen from outside
uvs                    (U, 2) float32      texture coordinates in [0, 1], v up
faces_uv               (F, 3) int32        per-corner indices into ``uvs``
weights                (V, J) float32      LBS weights, >= 0, rows sum to 1
heads                  (J, 3) float64      bind-pose joint positions
frames                 (J, 3, 3) float64   bind frames, columns are the x, y, z axes
bone_mean              (J,) float32        b_mean of Eq. 4
bone_basis             (Kb, J) float32     P_b of Eq. 4, per standard deviation
bone_correctives       (Kb, V, 3) float32  P_bc of Eq. 7
shape_basis            (Ks, V, 3) float32  P_s of Eq. 8, per standard deviation
population_bone        (N, Kb) float32     c_b of the N bodies the model was built from
population_shape       (N, Ks) float32     c_s of the same bodies (an empirical shape prior)
vertex_parts           (V,) int32          index into the six part names
vertex_bones           (V,) int32          index into the bone names (largest weight)
vertex_mirror          (V,) int32          vertex that mirrors each vertex across x = 0
keypoint_joint         (K,) int32          joint index of a joint keypoint, -1 for surface ones
keypoint_vertices      (K, 3) int32        surface keypoints: three vertices ...
keypoint_weights       (K, 3) float32      ... and their barycentric weights
=====================  ==================  ==========================================================

Optional: a BLSM-spiral model (Eq. 11) has a ``shape_decoder`` entry in ``meta_json`` and arrays
``shape_decoder__*`` (:mod:`blsm.spiral.shape`); its ``population_shape`` stays the PCA coefficients
of ``shape_basis`` in the file, and the loaded model's are the decoder's latent codes.
"""

from __future__ import annotations

import contextlib
import hashlib
import json
import os
import zipfile
import zlib
from collections.abc import Iterator
from dataclasses import dataclass, field
from pathlib import Path
from typing import IO, Any

import numpy as np

FORMAT = "blsm-model"
FORMAT_VERSION = 1
SHAPE_DECODER_PREFIX = "shape_decoder__"
"""Arrays of a non-linear shape decoder (meta ``shape_decoder``; :mod:`blsm.spiral.shape`), kept on read."""

_ARRAYS: dict[str, tuple[str, tuple[str, ...]]] = {
    "template": ("f", ("V", "3")),
    "faces": ("i", ("F", "3")),
    "uvs": ("f", ("U", "2")),
    "faces_uv": ("i", ("F", "3")),
    "weights": ("f", ("V", "J")),
    "heads": ("f", ("J", "3")),
    "frames": ("f", ("J", "3", "3")),
    "bone_mean": ("f", ("J",)),
    "bone_basis": ("f", ("Kb", "J")),
    "bone_correctives": ("f", ("Kb", "V", "3")),
    "shape_basis": ("f", ("Ks", "V", "3")),
    "population_bone": ("f", ("N", "Kb")),
    "population_shape": ("f", ("N", "Ks")),
    "vertex_parts": ("i", ("V",)),
    "vertex_bones": ("i", ("V",)),
    "vertex_mirror": ("i", ("V",)),
    "keypoint_joint": ("i", ("K",)),
    "keypoint_vertices": ("i", ("K", "3")),
    "keypoint_weights": ("f", ("K", "3")),
}


@dataclass
class ModelData:
    """Everything a model file holds, as numpy arrays plus metadata."""

    arrays: dict[str, np.ndarray]
    meta: dict[str, Any]
    dof_table_yaml: str
    path: Path | None = field(default=None)


def validate(data: ModelData, where: str = "model") -> None:
    """Check array presence, kinds and mutually consistent sizes; raise ValueError naming ``where``."""
    dims: dict[str, int] = {"3": 3, "2": 2}
    for key, (kind, shape) in _ARRAYS.items():
        if key not in data.arrays:
            raise ValueError(f"{where}: missing array {key!r}")
        arr = data.arrays[key]
        if arr.dtype.kind != kind and not (kind == "i" and arr.dtype.kind == "u"):
            raise ValueError(f"{where}: array {key!r} has dtype {arr.dtype}, expected kind {kind!r}")
        if arr.ndim != len(shape):
            raise ValueError(f"{where}: array {key!r} has shape {arr.shape}, expected {shape}")
        if kind == "f" and not np.isfinite(arr).all():
            raise ValueError(f"{where}: array {key!r} has NaN or infinite values")
        for size, name in zip(arr.shape, shape):
            if dims.setdefault(name, size) != size:
                raise ValueError(
                    f"{where}: array {key!r} has shape {arr.shape}; dimension {name} should be {dims[name]}"
                )
    for key in ("bone_names", "parents", "part_names", "keypoint_names"):
        if key not in data.meta:
            raise ValueError(f"{where}: metadata is missing {key!r}")
    if len(data.meta["bone_names"]) != dims["J"] or len(data.meta["parents"]) != dims["J"]:
        raise ValueError(f"{where}: bone_names/parents do not match J = {dims['J']}")
    if len(data.meta["keypoint_names"]) != dims["K"]:
        raise ValueError(f"{where}: keypoint_names do not match K = {dims['K']}")
    w = data.arrays["weights"]
    if (w < 0).any() or not np.allclose(w.sum(1), 1.0, atol=1e-4):
        raise ValueError(f"{where}: LBS weights must be >= 0 and sum to 1 per vertex")
    faces = data.arrays["faces"]
    if faces.min() < 0 or faces.max() >= dims["V"]:
        raise ValueError(f"{where}: faces index outside [0, {dims['V']})")


@contextlib.contextmanager
def atomic_write(path: str | Path, mode: str = "wb", tag: str = "") -> Iterator[IO[Any]]:
    """Open a hidden temporary file beside ``path``; rename it to ``path`` only on success.

    The parent folder is created. On any error the temporary file is removed and ``path`` is left
    as it was, so a reader never sees a partial file. ``tag`` (e.g. a writer's host and pid) goes
    into the temporary name, ``.<name>.<tag>.tmp``, so that two writers never share one.
    """
    path = Path(path)
    path.parent.mkdir(parents=True, exist_ok=True)
    tmp = path.with_name(f".{path.name}.{tag}.tmp" if tag else f".{path.name}.tmp")
    try:
        with open(tmp, mode) as fh:
            yield fh
            fh.flush()
            os.fsync(fh.fileno())
        os.replace(tmp, path)
    finally:
        tmp.unlink(missing_ok=True)


def sha256_file(path: str | Path) -> str:
    """SHA-256 of a file's bytes, as hex."""
    h = hashlib.sha256()
    with open(path, "rb") as fh:
        for block in iter(lambda: fh.read(1 << 20), b""):
            h.update(block)
    return h.hexdigest()


def read_npz(path: str | Path, what: str) -> dict[str, np.ndarray]:
    """All arrays of an ``.npz`` file (no pickles); errors name the file and say it is a ``what``."""
    path = Path(path)
    if not path.is_file():
        raise ValueError(f"{path}: no such {what} file")
    try:
        npz = np.load(path, allow_pickle=False)
        if not isinstance(npz, np.lib.npyio.NpzFile):  # a bare .npy array
            raise ValueError("a single .npy array, not an .npz archive")
        with npz:
            return {k: npz[k] for k in npz.files}
    except (OSError, ValueError, zipfile.BadZipFile, EOFError, zlib.error) as exc:
        msg = str(exc).splitlines()[0] if str(exc) else type(exc).__name__
        raise ValueError(f"{path}: not a readable .npz {what} file ({msg})") from None


def read_yaml(path: str | Path, what: str) -> Any:
    """Parse a YAML file; errors name the file and say it is a ``what``."""
    import yaml

    path = Path(path)
    try:
        # utf-8-sig: a leading byte-order mark (some Windows editors write one) is not content.
        return yaml.safe_load(path.read_bytes().decode("utf-8-sig"))
    except OSError as exc:
        raise ValueError(f"{path}: cannot read {what} ({exc.strerror})") from None
    except UnicodeDecodeError as exc:
        bad = exc.object[exc.start : exc.start + 1].hex()
        raise ValueError(f"{path}: not UTF-8 text (byte 0x{bad} at offset {exc.start}; save the {what} as UTF-8)") from None
    except yaml.YAMLError as exc:
        raise ValueError(f"{path}: not valid YAML ({str(exc).splitlines()[0]})") from None


def write_versioned_npz(path: str | Path, fmt: str, version: int, arrays: dict[str, np.ndarray]) -> Path:
    """Write a compressed ``.npz`` holding ``format``, ``format_version`` and ``arrays``, atomically.

    The one writer of every versioned file format of ``blsm`` (model, registration, scan, pose
    prior, SMPL-reimpl); :func:`read_versioned_npz` reads them back.

    Args:
        path: destination file; its folder is created if needed.
        fmt: the format name stored as ``format`` (e.g. ``"blsm-model"``).
        version: the format version stored as ``format_version``.
        arrays: the other entries, in the order they are written (strings as 0-d ``np.array``).

    Returns:
        The path written.
    """
    path = Path(path)
    with atomic_write(path) as fh:
        np.savez_compressed(fh, format=np.array(fmt), format_version=np.array(version), **arrays)
    return path


def read_versioned_npz(path: str | Path, fmt: str, version: int, what: str) -> dict[str, np.ndarray]:
    """All arrays of a file written by :func:`write_versioned_npz`, format and version checked.

    Args:
        path: the ``.npz`` file.
        fmt: the expected ``format``.
        version: the supported ``format_version``.
        what: what the file is, for messages (``"model"`` gives "not a BLSM model file").

    Raises:
        ValueError: one line naming the file: missing, unreadable, another format, another version.
    """
    path = Path(path)
    raw = read_npz(path, what)
    found = str(raw["format"]) if "format" in raw else None
    if found != fmt:
        raise ValueError(f"{path}: not a BLSM {what} file (format={found!r})")
    try:
        got = int(raw["format_version"])
    except (KeyError, TypeError, ValueError):
        raise ValueError(f"{path}: bad or missing format_version") from None
    if got != version:
        raise ValueError(f"{path}: format_version {got} is not supported (expected {version})")
    return raw


def save_model(data: ModelData, path: str | Path) -> Path:
    """Write a model file atomically (temporary file, then rename)."""
    path = Path(path)
    validate(data, str(path))
    entries = {
        "meta_json": np.array(json.dumps(data.meta, sort_keys=True)),
        "dof_table_yaml": np.array(data.dof_table_yaml),
        **data.arrays,
    }
    return write_versioned_npz(path, FORMAT, FORMAT_VERSION, entries)


def read_model(path: str | Path) -> ModelData:
    """Read and validate a model file; errors name the file and the problem."""
    path = Path(path)
    raw = read_versioned_npz(path, FORMAT, FORMAT_VERSION, "model")
    try:
        meta = json.loads(str(raw["meta_json"]))
    except (KeyError, json.JSONDecodeError) as exc:
        raise ValueError(f"{path}: bad or missing meta_json ({exc})") from None
    if not isinstance(meta, dict):
        raise ValueError(f"{path}: meta_json must hold a JSON object")
    if "dof_table_yaml" not in raw:
        raise ValueError(f"{path}: missing dof_table_yaml")
    arrays = {k: v for k, v in raw.items() if k in _ARRAYS or k.startswith(SHAPE_DECODER_PREFIX)}
    data = ModelData(arrays=arrays, meta=meta, dof_table_yaml=str(raw["dof_table_yaml"]), path=path)
    validate(data, str(path))
    return data
