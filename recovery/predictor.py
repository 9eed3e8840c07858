"""Load a trained network for inference: a run's ``best.pt`` / ``last.pt``, an exported file, or
``default`` (the packaged checkpoint, :data:`recovery.checkpoint.DEFAULT_CHECKPOINT`).

Both recovery networks answer with one :class:`Prediction` (camera frame, metres): HMR-BLSM through
the BLSM model on its parameters, the image-to-mesh network (``task: mesh``) through its decoded
vertices, its rotation and camera (``recovery.models.mesh_net``) and the keypoint regressor of its
mesh operators. A checkpoint names the BLSM model file it was trained with by its SHA-256; loading
it with another model file is an error (its parameters would mean other bodies), as is a file that
is not a checkpoint of either network or whose weights do not fit the network its config describes.
"""

from __future__ import annotations

from dataclasses import dataclass
from pathlib import Path
from typing import Any

import torch

import blsm
from blsm.io import sha256_file
from recovery.checkpoint import (
    CHECKPOINT_FORMAT,
    CHECKPOINT_VERSION,
    module_state,
    read_checkpoint,
    resolve,
    save_atomic,
)
from recovery.config import RecoveryConfig, config_from_json, model_file
from recovery.models.backbones.movenet import flip_coco
from recovery.models.hmr import HMROutput, body_outputs, flip_average, predict_body
from recovery.models.registry import build_network, inference_tasks
from recovery.utils.geometry import UPRIGHT_FACING_CAMERA, cam_to_translation, project

TASKS = inference_tasks()
"""The tasks whose checkpoints predict (``hmr_blsm``, ``mesh``)."""


@dataclass
class Prediction:
    """What either network predicts for a batch of crops (camera frame: OpenCV, metres).

    Attributes:
        vertices: (B, V, 3) the mesh relative to the pelvis, camera-frame orientation.
        keypoints_3d: (B, K, 3) the model's keypoints, relative to the pelvis, camera-frame orientation.
        transl: (B, 3) the pelvis' camera-frame position.
        keypoints_2d: (B, K, 2) projected with ``K_crop`` (pixels).
        body_vertices: (B, V, 3) the mesh in the body frame (no global rotation, pelvis at 0; thesis Sec. 4.5.2).
        params: HMR-BLSM's parameters (None for the mesh network).
        pose: (B, 47) the unconstrained pose x (None for the mesh network).
    """

    vertices: torch.Tensor
    keypoints_3d: torch.Tensor
    transl: torch.Tensor
    keypoints_2d: torch.Tensor
    body_vertices: torch.Tensor
    params: HMROutput | None = None
    pose: torch.Tensor | None = None


@dataclass
class Predictor:
    """A network ready for inference (eval mode) with its BLSM model and settings."""

    model: torch.nn.Module
    body: torch.nn.Module
    config: RecoveryConfig
    path: Path
    info: dict[str, Any]
    regressor: torch.Tensor | None = None  # (K, V) keypoints from vertices (mesh network)
    flip: bool = False  # HMR-BLSM: average with the mirrored prediction on the flipped crop
    fit: Any = None  # HMR-BLSM on MoveNet keypoints: recovery.models.fit2d.FitSettings, the test-time fit

    @property
    def crop(self) -> int:
        return self.config.data.crop

    @property
    def task(self) -> str:
        return self.config.task

    def to(self, device: torch.device | str) -> Predictor:
        self.model.to(device)
        self.body.to(device)
        if self.regressor is not None:
            self.regressor = self.regressor.to(device)
        return self

    def use_flip(self, flip: bool) -> Predictor:
        """Switch flip test-time augmentation (:func:`recovery.models.hmr.flip_average`); HMR-BLSM only."""
        if flip and self.task != "hmr_blsm":
            raise ValueError(f"{self.path}: --flip averages HMR-BLSM parameters; this is a {self.task!r} checkpoint")
        self.flip = flip
        return self

    def use_fit(self, iterations: int) -> Predictor:
        """Fit each prediction to the network's own MoveNet keypoints for ``iterations`` steps
        (:func:`recovery.models.fit2d.fit_to_keypoints`; 0: off). Needs a checkpoint whose regressor
        reads MoveNet keypoints (``model.head_input`` keypoints or keypoints+pooled)."""
        from recovery.models.fit2d import FitSettings

        if iterations < 0:
            raise ValueError(f"--fit must be >= 0, got {iterations}")
        if iterations and (self.task != "hmr_blsm" or getattr(self.model, "encoder", None) is None):
            raise ValueError(f"{self.path}: --fit fits to the network's MoveNet keypoints; this checkpoint reads none "
                             "(model.head_input pooled, or not HMR-BLSM)")
        self.fit = FitSettings(iterations=iterations) if iterations else None
        return self

    def _pelvis(self) -> int:
        return self.body.keypoint_names.index("pelvis")

    @torch.no_grad()
    def __call__(self, images: torch.Tensor, k_crop: torch.Tensor, guide: torch.Tensor | None = None) -> Prediction:
        """(B, 3, crop, crop) RGB in [0, 1] and (B, 3, 3) ``K_crop`` -> :class:`Prediction`.

        ``guide`` (B, 17, 3): a person detector's COCO keypoints ``(x, y, score)`` of each crop's person
        in crop pixels; a network that reads MoveNet's keypoints then reads that person's
        (:meth:`recovery.models.backbones.movenet.MoveNet.keypoints`), not a neighbour's."""
        dev = next(self.model.parameters()).device
        k_crop = k_crop.to(dev)
        images = images.to(dev)
        if self.task == "hmr_blsm":
            guide = guide.to(dev) if guide is not None and self.model.encoder is not None else None
            out, kp = self.model.forward_keypoints(images, guide)
            if self.flip:
                mirrored = None if guide is None else flip_coco(guide, images.shape[-1])
                out = flip_average(self.body, out, self.model.forward_keypoints(images.flip(-1), mirrored)[0])
            if self.fit is not None:
                from recovery.models.backbones.movenet import COCO_KEYPOINTS
                from recovery.models.fit2d import fit_to_keypoints

                ids = [self.body.keypoint_names.index(n) for n in COCO_KEYPOINTS]
                out = fit_to_keypoints(self.body, out, k_crop, self.crop, kp, ids, self.fit)
            b = predict_body(self.body, out, k_crop, self.crop)
            rest = self.body(pose=out.pose, bone=out.bone, shape=out.shape)
            return Prediction(vertices=b.vertices, keypoints_3d=b.keypoints_3d, transl=b.transl,
                              keypoints_2d=b.keypoints_2d, body_vertices=rest.vertices - rest.joints[:, :1],
                              params=out, pose=out.pose)
        out = self.model(images)
        kp = torch.einsum("kv,bvc->bkc", self.regressor, out.vertices)
        pelvis = kp[:, self._pelvis(): self._pelvis() + 1]
        v, kp = out.vertices - pelvis, kp - pelvis
        rt = out.rotation.transpose(1, 2)
        transl = cam_to_translation(out.cam, k_crop, self.crop)
        kp_cam = kp @ rt
        return Prediction(vertices=v @ rt, keypoints_3d=kp_cam, transl=transl, keypoints_2d=project(kp_cam + transl[:, None], k_crop),
                          body_vertices=v)

    @torch.no_grad()
    def mean_keypoints(self) -> torch.Tensor:
        """(K, 3) the network's starting point, pelvis-relative, upright and facing the camera: HMR's
        Theta_0 (the training means) or the mesh network's mean training mesh."""
        if self.task == "hmr_blsm":
            mean = self.model.decode(self.model.regressor.init.detach()[None, None].expand(1, 1, -1))
            return body_outputs(self.body, mean.pose, mean.orient, mean.bone, mean.shape).keypoints_3d[0]
        v = self.model.normalizer.mean
        kp = self.regressor.to(v.dtype) @ v
        kp = kp - kp[self._pelvis()]
        return kp @ UPRIGHT_FACING_CAMERA.to(kp).T


def load_predictor(checkpoint: str | Path, model_path: str | Path | None = None, log: Any = print) -> Predictor:
    """The network of a checkpoint (``default`` for the packaged one), in eval mode on the CPU.

    Args:
        checkpoint: a checkpoint file or ``default``.
        model_path: the BLSM model file (default: the one in the checkpoint's config, else the packaged one).

    Raises:
        ValueError: one line naming the file: missing, corrupt, another task, made for another
            model file, or weights that do not fit its config.
    """
    path = resolve(checkpoint)
    ck = read_checkpoint(path)
    if ck.get("task") not in TASKS:
        raise ValueError(f"{path}: a checkpoint of task {ck.get('task')!r}; this command reads {' or '.join(TASKS)}")
    cfg = config_from_json({"task": ck["task"], **ck["config"]}, str(path))
    mpath = Path(model_path) if model_path else model_file(cfg)
    if not mpath.is_file():
        raise ValueError(f"{mpath}: the BLSM model file of {path} is missing")
    if sha256_file(mpath) != ck.get("blsm_model_sha256"):
        raise ValueError(f"{path}: made for another BLSM model file than {mpath} (SHA-256 differs)")
    body = blsm.load(mpath)
    state = module_state(ck)
    model, regressor = build_network(cfg, body, mpath, log)
    try:
        model.load_state_dict(state)
    except RuntimeError as exc:
        raise ValueError(f"{path}: weights do not fit the network of its config ({str(exc).splitlines()[0][:160]})") from None
    model.backbone.use_channels_last(cfg.train.channels_last)
    model.eval()
    info = {k: ck.get(k) for k in ("step", "saved", "best", "train_summary", "inference")}
    pr = Predictor(model=model, body=body, config=cfg, path=path, info=info, regressor=regressor)
    inference = ck.get("inference") or {}  # what an exported checkpoint asks of inference (recovery export --fit)
    return pr.use_fit(int(inference.get("fit", 0)))


def export(src: str | Path, dst: str | Path, half: bool = True, summary: dict[str, Any] | None = None,
           fit: int = 0) -> Path:
    """Write an inference-only copy of a run's checkpoint (the network's weights, float16 when
    ``half``, its config and model hash; no optimiser or discriminator state). ``fit``: the test-time
    fit's iterations that :func:`load_predictor` applies by default (``inference.fit``; 0: none)."""
    src, dst = Path(src), Path(dst)
    ck = read_checkpoint(src)
    weights = {k: (v.half() if half and v.is_floating_point() else v) for k, v in ck["modules"]["model"].items()}
    out = {
        "format": CHECKPOINT_FORMAT, "version": CHECKPOINT_VERSION, "task": ck["task"], "config": ck["config"],
        "blsm_model_sha256": ck["blsm_model_sha256"], "model_hash": ck.get("model_hash"),
        "step": ck["step"], "best": ck.get("best"), "saved": ck.get("saved"), "source": str(src),
        "modules": {"model": weights}, "train_summary": summary or {},
    }
    if fit:
        if ck["task"] != "hmr_blsm" or ck["config"].get("model", {}).get("head_input", "pooled") == "pooled":
            raise ValueError(f"{src}: --fit needs an HMR-BLSM checkpoint whose regressor reads MoveNet keypoints")
        out["inference"] = {"fit": int(fit)}
    save_atomic(out, dst)
    return dst
