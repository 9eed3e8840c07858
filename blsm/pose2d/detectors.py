"""2D pose detectors: the protocol, MediaPipe Pose (a subprocess), and a projecting stand-in.

A detector takes C images with one box each and returns per image the 33 landmarks of BlazePose's
topology (:data:`MEDIAPIPE_NAMES`) as a (33, 3) array ``(x, y, visibility)`` in pixels (pixel
centres at integer + 0.5) with visibility in [0, 1], or None where it finds no person.

* :class:`MediaPipeDetector`: MediaPipe Pose 0.10.9 ("full" BlazePose GHUM model from its wheel;
  nothing is downloaded) run by ``blsm/pose2d/mediapipe_pose.py`` in the environment that
  ``scripts/setup_reference.sh`` makes (``.venv-reference``; MediaPipe pins protobuf 3 and its own
  OpenCV, so it stays out of the project's environment). Optional: only this class needs it.
* :class:`ProjectedDetector`: projects given 3D points with each view's camera, with pixel noise,
  dropouts (low visibility), left/right flips and views without a person, all seeded: the test and
  oracle stand-in of a detector, no network involved.

Detectors are called as ``detector(images, boxes, cameras)``; an image detector ignores
``cameras`` (only the projecting stand-in uses them).
"""

from __future__ import annotations

import json
import os
import subprocess
import tempfile
from collections.abc import Sequence
from dataclasses import dataclass
from pathlib import Path
from typing import Protocol

import numpy as np

from blsm.camera import Camera

MEDIAPIPE_NAMES: tuple[str, ...] = (
    "nose", "left_eye_inner", "left_eye", "left_eye_outer", "right_eye_inner", "right_eye",
    "right_eye_outer", "left_ear", "right_ear", "mouth_left", "mouth_right", "left_shoulder",
    "right_shoulder", "left_elbow", "right_elbow", "left_wrist", "right_wrist", "left_pinky",
    "right_pinky", "left_index", "right_index", "left_thumb", "right_thumb", "left_hip", "right_hip",
    "left_knee", "right_knee", "left_ankle", "right_ankle", "left_heel", "right_heel",
    "left_foot_index", "right_foot_index",
)  # fmt: skip
"""BlazePose's 33 landmarks, in its order (left/right are the person's)."""


def _mirror(name: str) -> str:
    if name.startswith("left_"):
        return "right_" + name[5:]
    if name.startswith("right_"):
        return "left_" + name[6:]
    return name.replace("_left", "_X").replace("_right", "_left").replace("_X", "_right")


MEDIAPIPE_MIRROR: tuple[int, ...] = tuple(MEDIAPIPE_NAMES.index(_mirror(n)) for n in MEDIAPIPE_NAMES)
"""For each landmark, its left/right counterpart (itself for the nose)."""

SCRIPT = Path(__file__).with_name("mediapipe_pose.py")
DEFAULT_ENV = Path(__file__).resolve().parents[2] / ".venv-reference"  # the repository root's
ENV_VARIABLE = "BLSM_POSE_ENV"
"""Environment variable naming the MediaPipe environment folder (default ``.venv-reference``)."""


class PoseDetector(Protocol):
    """``detector(images, boxes, cameras) -> [(33, 3) or None] * C`` (see the module docstring)."""

    name: str

    def __call__(
        self, images: Sequence[np.ndarray], boxes: np.ndarray, cameras: Sequence[Camera]
    ) -> list[np.ndarray | None]: ...


@dataclass
class MediaPipeDetector:
    """MediaPipe Pose 0.10.9 in its own environment, one subprocess per call (all views at once).

    The script crops each image to the square of 1.25 times the box's longer side around the box
    (zero padding outside the image) and maps the 33 landmarks back to image pixels.

    Attributes:
        python: the environment's interpreter; default ``$BLSM_POSE_ENV/bin/python`` or
            ``.venv-reference/bin/python`` at the repository root.
        name: recorded with the results.
    """

    python: str | None = None
    name: str = "mediapipe-pose 0.10.9 full"

    def command(self) -> list[str]:
        """The command line (the job and output files are appended)."""
        if self.python is not None:
            python = Path(self.python)
        else:
            python = Path(os.environ.get(ENV_VARIABLE, DEFAULT_ENV)) / "bin" / "python"
        if not python.is_file():
            raise ValueError(
                f"{python}: no MediaPipe environment (run `bash scripts/setup_reference.sh`, or set ${ENV_VARIABLE})"
            )
        return [str(python), str(SCRIPT)]

    def __call__(
        self, images: Sequence[np.ndarray], boxes: np.ndarray, cameras: Sequence[Camera] = ()
    ) -> list[np.ndarray | None]:
        from PIL import Image

        cmd = self.command()
        with tempfile.TemporaryDirectory(prefix="blsm_pose_") as tmp:
            items = []
            for i, (img, box) in enumerate(zip(images, boxes, strict=True)):
                path = Path(tmp) / f"view_{i:03d}.png"
                Image.fromarray(np.ascontiguousarray(img)).save(path)
                items.append({"image": str(path), "box": [float(v) for v in box]})
            found = run_pose_script(cmd, items, f"{SCRIPT}: MediaPipe")["items"]
        return [None if it["landmarks"] is None else np.asarray(it["landmarks"], np.float64) for it in found]


def run_pose_script(command: Sequence[str], items: list[dict], what: str) -> dict:
    """Run a pose script of :mod:`blsm.pose2d.mediapipe_pose`'s interface on ``items``.

    ``command + [JOB.json, OUT.json]`` is run with ``JOB.json = {"items": items}`` (each ``{"image":
    PATH, "box": [x0, y0, x1, y1]}``); returns the answer (``{"items": [...], "reference": ...}``)
    with one item per job item. A failing command, or a wrong number of answers, is a ValueError
    starting with ``what`` and ending with the command's last line.
    """
    with tempfile.TemporaryDirectory(prefix="blsm_pose_job_") as tmp:
        job, out = Path(tmp) / "job.json", Path(tmp) / "out.json"
        job.write_text(json.dumps({"items": items}))
        res = subprocess.run([*command, str(job), str(out)], capture_output=True, text=True, check=False)
        if res.returncode != 0 or not out.is_file():
            last = (res.stderr.strip().splitlines() or [f"exit status {res.returncode}"])[-1]
            raise ValueError(f"{what} failed ({last})")
        answer = json.loads(out.read_text())
    if len(answer.get("items", [])) != len(items):
        raise ValueError(f"{what} answered {len(answer.get('items', []))} of {len(items)} images")
    return answer


@dataclass
class ProjectedDetector:
    """A stand-in detector: the projections of known 3D landmarks, with seeded imperfections.

    Attributes:
        points: (33, 3) world positions of the landmarks, metres; NaN rows are never detected.
        noise_px: standard deviation of Gaussian pixel noise.
        dropout: probability that a landmark is reported with low visibility (0.1) and a random
            position in its box.
        flip_rate: probability that a view's left and right landmarks are swapped.
        no_person: views (indices) that find no person; ``all_missing`` makes every view find none.
        visibility: visibility of a reported landmark.
        seed: the random stream.
    """

    points: np.ndarray
    noise_px: float = 1.0
    dropout: float = 0.0
    flip_rate: float = 0.0
    no_person: tuple[int, ...] = ()
    all_missing: bool = False
    visibility: float = 0.9
    seed: int = 0
    name: str = "projected"

    def __call__(
        self, images: Sequence[np.ndarray], boxes: np.ndarray, cameras: Sequence[Camera]
    ) -> list[np.ndarray | None]:
        rng = np.random.default_rng(self.seed)
        pts = np.asarray(self.points, np.float64)
        ok = np.isfinite(pts).all(1)
        out: list[np.ndarray | None] = []
        for i, (cam, box) in enumerate(zip(cameras, boxes, strict=True)):
            if self.all_missing or i in self.no_person:
                out.append(None)
                continue
            lm = np.zeros((len(pts), 3))
            lm[ok, :2] = cam.project(pts[ok]) + rng.normal(0.0, self.noise_px, size=(int(ok.sum()), 2))
            lm[ok, 2] = self.visibility
            drop = ok & (rng.random(len(pts)) < self.dropout)
            lm[drop, :2] = rng.uniform(box[:2], box[2:], size=(int(drop.sum()), 2))
            lm[drop, 2] = 0.1
            if rng.random() < self.flip_rate:
                lm = lm[list(MEDIAPIPE_MIRROR)]
            out.append(lm)
        return out
