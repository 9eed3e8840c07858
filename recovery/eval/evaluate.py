"""``recovery evaluate CHECKPOINT DATASET --out DIR``: metrics, baselines, splits and a results sheet.

Every person of a ``synth`` dataset is cropped as in training (:class:`synth.dataset.images.SynthDataset`, SPIN's
1.2 times the visible box, no augmentation) and predicted. Metrics (``DIR/metrics.json``):

- ``mpjpe_mm``: mean joint error after aligning the pelvis, on :data:`recovery.eval.joints.EVAL_JOINTS`;
- ``pa_mpjpe_mm``: after a similarity Procrustes alignment (scale, rotation, translation) on the same joints;
- ``pve_mm``: mean vertex error of the predicted BLSM mesh against the BLSM mesh of the labels, both
  pelvis-aligned;
- ``pck_0.05``, ``pck_0.1``: fraction of the visible joints whose projection lies within 0.05 / 0.1 of
  the crop side of the label;
- segmentation (thesis Table 6.4): the predicted mesh's six parts rasterised into the crop with
  ``K_crop`` (z-buffer) against the dataset's mask and parts of that person: foreground/background
  accuracy and foreground F1, 7-class (6 parts + background) accuracy and macro F1;
- ``body_frame`` (thesis Sec. 4.5.2, Table 4.3): errors with the global rotation removed, as the
  mesh network is trained: ``vertex_mm`` (mesh, pelvis-aligned), ``joint_mm`` and ``pa_joint_mm``
  on the evaluation joints regressed from the predicted and the labels' meshes by the same keypoint
  regressor (:mod:`recovery.mesh.operators`), and ``roughness_mm`` / ``label_roughness_mm``: the mean
  length of the uniform Laplacian (a vertex minus the mean of its neighbours) of the predicted and
  the labels' meshes (spiky surfaces raise it);
- baselines on the same people: the **fixed skeleton** (one 3D skeleton for everyone, the
  generalised Procrustes mean of the people's joints, similarity-aligned to each person: the best a
  constant prediction does in PA-MPJPE) and the **mean pose** (the training set's mean parameters
  Theta_0 of the network, translated to the best position, i.e. centroid-aligned);
- the same metrics split by view (normal, rare), truncation and people per image;
- on a sequence dataset (docs/video.md), ``temporal`` (:mod:`recovery.eval.temporal`): each person's
  predictions over runs of consecutive in-view frames, ``accel_error_mm`` (mm/frame^2, VIBE's
  acceleration error), ``accel_mm`` / ``label_accel_mm`` and ``jitter_km_s3`` / ``label_jitter_km_s3``,
  on the pelvis-aligned camera-frame evaluation joints.

``DIR/sheet.png`` shows people by PA-MPJPE quartile (thesis Fig. 4.7): crop, mesh overlay, parts
overlay and a side view (prediction blue, labels grey).
"""

from __future__ import annotations

import json
import time
from pathlib import Path
from typing import Any

import numpy as np
import torch

from blsm.io import atomic_write
from blsm.mesh import uniform_laplacian_matrix
from recovery.datasets.cache import VIEWS, person_info
from recovery.datasets.meshes import body_frame_vertices
from recovery.datasets.sampling import spread_indices
from recovery.eval import metrics as M
from recovery.eval.joints import EVAL_JOINTS, PELVIS, indices
from recovery.eval.temporal import format_temporal, sequence_items, temporal_metrics
from recovery.models.hmr import body_outputs
from recovery.predictor import Predictor, load_predictor
from recovery.utils.raster import rasterize_labels
from recovery.utils.viz import face_parts, label_image, overlay, parts_overlay, side_view
from synth.dataset.images import SynthDataset


def fixed_skeleton(joints: torch.Tensor, iterations: int = 20) -> torch.Tensor:
    """The generalised Procrustes mean (J, 3) of skeletons (N, J, 3): the single skeleton that,
    similarity-aligned to each person, is nearest all of them (least squares)."""
    s = joints[0].clone()
    for _ in range(iterations):
        aligned = M.similarity_procrustes(joints, s.expand_as(joints))
        new = aligned.mean(0)
        new = new - new.mean(0)
        new = new / new.norm() * (joints - joints.mean(1, keepdim=True)).norm(dim=(1, 2)).mean()
        if torch.allclose(new, s, atol=1e-9):
            break
        s = new
    return s


def pose_prior_outliers(pred: torch.Tensor, label: torch.Tensor, prior_path: str | Path | None = None) -> dict[str, Any]:
    """The fraction of predicted poses whose log-probability under the packaged CMU pose prior is
    below the 1st percentile of the labels' (real mocap frames: on the test set, the two clips held
    out of the prior). Unconstrained values are clipped to ``|x| <= X_CLIP`` first, as the prior's
    own training values were.

    Args:
        pred: (N, 47) predicted unconstrained values. label: (M, 47) the labels' values.
    """
    from blsm.mocap.prior import DEFAULT_PRIOR, X_CLIP, load_prior

    path = prior_path or DEFAULT_PRIOR
    prior = load_prior(path)
    with torch.no_grad():
        lp_real = prior.log_prob(label.double().clamp(-X_CLIP, X_CLIP))
        lp_pred = prior.log_prob(pred.double().clamp(-X_CLIP, X_CLIP))
    threshold = float(torch.quantile(lp_real, 0.01))
    return {"threshold_log_prob": threshold, "fraction_below": float((lp_pred < threshold).double().mean()),
            "labels_below": float((lp_real < threshold).double().mean()),
            "prior": str(Path(path).name),
            "note": "threshold: 1st percentile of the labels' log-probability (real mocap frames)"}


def roughness_mm(lap: torch.Tensor, vertices: torch.Tensor) -> torch.Tensor:
    """(B,) mean length of the uniform Laplacian of (B, V, 3) meshes, millimetres."""
    out = torch.stack([torch.sparse.mm(lap, v) for v in vertices.float()])
    return out.norm(dim=-1).mean(-1) * 1000.0


def keypoint_regressor(pr: Predictor) -> torch.Tensor:
    """(K, V) the keypoint regressor of the predictor's BLSM model (the mesh network's own)."""
    if pr.regressor is not None:
        return pr.regressor
    from recovery.config import MeshConfig, model_file
    from recovery.mesh.operators import mesh_operators

    return torch.as_tensor(mesh_operators(model_file(pr.config), MeshConfig().cache, MeshConfig().ops_settings()).regressor)


def _segmentation(pred_labels: np.ndarray, gt_parts: np.ndarray, gt_mask: np.ndarray) -> np.ndarray:
    gt = np.where(gt_mask, gt_parts, 0)
    return M.confusion_matrix(torch.from_numpy(pred_labels), torch.from_numpy(gt), 7).numpy()


def _summary(rows: dict[str, np.ndarray], conf: np.ndarray, sel: np.ndarray) -> dict[str, Any]:
    out: dict[str, Any] = {"people": int(sel.sum())}
    if not sel.any():
        return out
    for k in ("mpjpe_mm", "pa_mpjpe_mm", "pve_mm", "pck_0.05", "pck_0.1"):
        out[k] = float(np.nanmean(rows[k][sel]))
    c = conf[sel].sum(0)
    fg = M.foreground_scores(c)
    seg = M.segmentation_scores(c)
    out["segmentation"] = {"fg_accuracy": float(fg["accuracy"]), "fg_f1": float(fg["f1"]),
                           "parts_accuracy": float(seg["accuracy"]), "parts_macro_f1": float(seg["macro_f1"])}
    return out


class Scores:
    """Every person's scores of one evaluation, gathered batch by batch (module docstring), and what
    the results sheet shows of them."""

    ROWS = ("mpjpe_mm", "pa_mpjpe_mm", "pve_mm", "pck_0.05", "pck_0.1", "mean_pose_mpjpe_mm", "mean_pose_pa_mpjpe_mm",
            "bf_joint_mm", "bf_pa_joint_mm", "bf_vertex_mm", "roughness_mm", "label_roughness_mm")

    def __init__(self, pr: Predictor) -> None:
        self.pr, self.crop = pr, pr.crop
        self.ev = torch.tensor(indices(pr.body.keypoint_names))
        self.faces = pr.body.faces.numpy()
        self.flabels = face_parts(self.faces, pr.body.vertex_parts.numpy())
        self.mean_kp = pr.mean_keypoints()[self.ev]
        self.reg = keypoint_regressor(pr)
        self.lap = uniform_laplacian_matrix(self.faces, pr.body.num_vertices)
        self.pel = self.ev[PELVIS]
        self.poses: dict[str, list[torch.Tensor]] = {"pred": [], "label": []}
        self.rows: dict[str, list[float]] = {k: [] for k in self.ROWS}
        self.confs: list[np.ndarray] = []
        self.gt_joints: list[torch.Tensor] = []
        self.pred_joints: list[torch.Tensor] = []
        self.keep: dict[str, list[Any]] = {"image": [], "pred_v": [], "gt_v": [], "K": [], "transl": [], "gt_parts": [],
                                           "gt_mask": []}

    def regressed(self, v: torch.Tensor) -> tuple[torch.Tensor, torch.Tensor]:
        """(B, V, 3) body-frame meshes -> the evaluation joints regressed from them and the meshes,
        both relative to the regressed pelvis."""
        kp = torch.einsum("kv,bvc->bkc", self.reg, v)
        pelvis = kp[:, self.pel: self.pel + 1]
        return kp[:, self.ev] - pelvis, v - pelvis

    def add(self, b: dict[str, torch.Tensor]) -> int:
        """Predict and score one batch of dataset items; returns its size."""
        pr, ev, rows, crop = self.pr, self.ev, self.rows, self.crop
        po = pr(b["image"], b["K_crop"])
        gt = body_outputs(pr.body, b["pose"], b["global_orient"], b["bone"], b["shape"])
        p3, g3 = po.keypoints_3d[:, ev], b["keypoints_3d"][:, ev]
        rows["mpjpe_mm"] += (M.mpjpe(M.pelvis_aligned(p3, PELVIS), M.pelvis_aligned(g3, PELVIS)) * 1000).tolist()
        rows["pa_mpjpe_mm"] += (M.pa_mpjpe(p3, g3) * 1000).tolist()
        rows["pve_mm"] += (M.mpjpe(po.vertices, gt.vertices) * 1000).tolist()
        vis = b["keypoints_2d"][:, ev, 2] > 0
        for thr, key in ((0.05, "pck_0.05"), (0.1, "pck_0.1")):
            rows[key] += M.pck(po.keypoints_2d[:, ev], b["keypoints_2d"][:, ev, :2], vis, thr * crop).tolist()
        with torch.no_grad():
            pk, pv = self.regressed(po.body_vertices)
            gk, gv = self.regressed(body_frame_vertices(pr.body, b["pose"], b["bone"], b["shape"]))
        rows["bf_joint_mm"] += (M.mpjpe(pk, gk) * 1000).tolist()
        rows["bf_pa_joint_mm"] += (M.pa_mpjpe(pk, gk) * 1000).tolist()
        rows["bf_vertex_mm"] += (M.mpjpe(pv, gv) * 1000).tolist()
        rows["roughness_mm"] += roughness_mm(self.lap, po.body_vertices).tolist()
        rows["label_roughness_mm"] += roughness_mm(self.lap, gv).tolist()
        mk = self.mean_kp.expand_as(g3)
        rows["mean_pose_mpjpe_mm"] += (M.mpjpe(mk - mk.mean(1, keepdim=True) + g3.mean(1, keepdim=True), g3) * 1000).tolist()
        rows["mean_pose_pa_mpjpe_mm"] += (M.pa_mpjpe(mk, g3) * 1000).tolist()
        self.gt_joints.append(g3.double())
        self.pred_joints.append(p3.detach().double())
        if po.pose is not None:
            self.poses["pred"].append(po.pose)
            self.poses["label"].append(b["pose"])
        verts = (po.vertices + po.transl[:, None]).numpy()
        for i in range(len(verts)):
            lab = rasterize_labels(verts[i], self.faces, b["K_crop"][i].numpy(), crop, crop, self.flabels)
            self.confs.append(_segmentation(lab, b["parts"][i].numpy(), b["mask"][i].numpy()))
        keep = self.keep
        keep["image"].append((b["image"].permute(0, 2, 3, 1).numpy() * 255 + 0.5).clip(0, 255).astype(np.uint8))
        keep["pred_v"].append(verts.astype(np.float32))
        keep["gt_v"].append((gt.vertices + b["transl_cam"][:, None]).numpy().astype(np.float32))
        keep["K"].append(b["K_crop"].numpy())
        keep["gt_parts"].append(np.where(b["mask"].numpy(), b["parts"].numpy(), 0).astype(np.uint8))
        return len(verts)


PER_PERSON = ("mpjpe_mm", "pa_mpjpe_mm", "pve_mm")
"""The errors ``people.npz`` keeps per person (with ``index``, the person's item in the dataset, and ``subject``)."""


def evaluate(checkpoint: str | Path, dataset: str | Path, out: str | Path, batch: int = 32, max_people: int = 0,
             log: Any = print, flip: bool = False, antialias: bool = True, fit: int | None = None) -> dict[str, Any]:
    """Evaluate a checkpoint on a dataset folder; writes ``metrics.json``, ``people.npz`` (each
    person's errors, :data:`PER_PERSON`) and ``sheet.png`` into ``out``.

    ``flip``: HMR-BLSM with flip test-time augmentation (:func:`recovery.models.hmr.flip_average`);
    recorded as ``flip_test`` in the metrics. ``antialias``: the crops' prefilter
    (:class:`synth.dataset.images.SynthDataset`), recorded as ``antialias`` where off. ``fit``: the test-time fit's
    iterations (:meth:`recovery.predictor.Predictor.use_fit`; None: the checkpoint's own), recorded as ``fit``.
    """
    t0 = time.perf_counter()
    pr = load_predictor(checkpoint).use_flip(flip)
    if fit is not None:
        pr.use_fit(fit)
    ds = SynthDataset(dataset, crop=pr.crop, box_scale=1.2, antialias=antialias)
    if list(ds.keypoint_names) != list(pr.body.keypoint_names):
        raise ValueError(f"{dataset}: its keypoint_names are not the checkpoint's BLSM model's")
    info = person_info(ds)
    seq_info = sequence_items(ds)
    n = len(ds) if not max_people else min(max_people, len(ds))
    chosen = spread_indices(len(ds), n)
    sub = torch.utils.data.Subset(ds, chosen.tolist())
    loader = torch.utils.data.DataLoader(sub, batch_size=batch, num_workers=1)
    scores = Scores(pr)
    done = 0
    for b in loader:
        done += scores.add(b)
        if done % (batch * 8) < batch:
            log(f"[evaluate] {done}/{n} people")
    res = results(scores, info, chosen, str(dataset), flip)
    res["seconds"] = round(time.perf_counter() - t0, 1)
    res["fit"] = pr.fit.iterations if pr.fit is not None else 0
    if not antialias:
        res["antialias"] = False
    if seq_info is not None:
        cols = (seq_info[k][chosen] for k in ("sequence", "track", "frame", "fps"))
        res["temporal"] = temporal_metrics(torch.cat(scores.pred_joints), torch.cat(scores.gt_joints), *cols,
                                           pelvis=PELVIS).to_dict()
    res["relative"] = {
        "pa_mpjpe_vs_fixed_skeleton": res["pa_mpjpe_mm"] / res["baselines"]["fixed_skeleton"]["pa_mpjpe_mm"] - 1,
        "mpjpe_vs_mean_pose": res["mpjpe_mm"] / res["baselines"]["mean_pose"]["mpjpe_mm"] - 1,
    }
    out = Path(out)
    out.mkdir(parents=True, exist_ok=True)
    with atomic_write(out / "metrics.json", "w") as fh:
        fh.write(json.dumps(res, indent=1))
    with atomic_write(out / "people.npz") as fh:  # per person, for paired comparisons of checkpoints
        np.savez(fh, index=chosen, subject=info["subject"][chosen],
                 **{k: np.asarray(scores.rows[k], np.float64) for k in PER_PERSON})
    arrays = {k: np.concatenate(v) for k, v in scores.keep.items() if v}
    results_sheet(arrays, np.asarray(scores.rows["pa_mpjpe_mm"], np.float64), scores.faces, scores.flabels,
                  out / "sheet.png")
    return res


def results(scores: Scores, info: dict[str, np.ndarray], chosen: np.ndarray, dataset: str, flip: bool) -> dict[str, Any]:
    """The metrics of ``metrics.json`` but the temporal and relative ones: the summary, the body-frame
    errors, the baselines, the splits and the pose-prior check (module docstring)."""
    rows_np = {k: np.asarray(v, np.float64) for k, v in scores.rows.items()}
    conf = np.stack(scores.confs)
    joints = torch.cat(scores.gt_joints)
    skel = fixed_skeleton(joints)
    fixed_pa = (M.pa_mpjpe(skel.expand_as(joints), joints) * 1000).numpy()
    fixed_mp = (M.mpjpe(M.pelvis_aligned(skel.expand_as(joints), PELVIS), M.pelvis_aligned(joints, PELVIS)) * 1000).numpy()
    poses = scores.poses
    prior_check = pose_prior_outliers(torch.cat(poses["pred"]), torch.cat(poses["label"])) if poses["pred"] else None
    view, trunc, people = info["view"][chosen], info["truncated"][chosen], info["people"][chosen]
    all_sel = np.ones(len(chosen), bool)
    pr = scores.pr
    return {
        "checkpoint": str(pr.path), "task": pr.task, "dataset": dataset, "crop": pr.crop, "flip_test": flip,
        "joint_set": list(EVAL_JOINTS),
        **_summary(rows_np, conf, all_sel),
        "body_frame": {"joint_mm": float(rows_np["bf_joint_mm"].mean()), "pa_joint_mm": float(rows_np["bf_pa_joint_mm"].mean()),
                       "vertex_mm": float(rows_np["bf_vertex_mm"].mean()), "roughness_mm": float(rows_np["roughness_mm"].mean()),
                       "label_roughness_mm": float(rows_np["label_roughness_mm"].mean()),
                       "note": "global rotation removed, pelvis-aligned; joints regressed from the meshes (thesis Table 4.3 setting)"},
        "baselines": {
            "fixed_skeleton": {"pa_mpjpe_mm": float(fixed_pa.mean()), "mpjpe_mm": float(fixed_mp.mean()),
                               "note": "one skeleton for everyone: the generalised Procrustes mean of the test people's joints"},
            "mean_pose": {"mpjpe_mm": float(rows_np["mean_pose_mpjpe_mm"].mean()),
                          "pa_mpjpe_mm": float(rows_np["mean_pose_pa_mpjpe_mm"].mean()),
                          "note": "the network's Theta_0 (training means, upright and facing the camera), centroid-aligned"},
        },
        "splits": {
            "view": {v: _summary(rows_np, conf, view == i) for i, v in enumerate(VIEWS)},
            "truncated": {"no": _summary(rows_np, conf, ~trunc), "yes": _summary(rows_np, conf, trunc)},
            "people_per_image": {str(k): _summary(rows_np, conf, people == k) for k in sorted(set(people.tolist()))},
        },
        "pose_prior": prior_check,
        "subjects": int(len(set(info["subject"][chosen].tolist()))),
    }


def results_sheet(a: dict[str, np.ndarray], err: np.ndarray, faces: np.ndarray, flabels: np.ndarray, png: Path,
                  per_quartile: int = 3) -> None:
    """Rows by PA-MPJPE quartile (best first): crop, mesh overlay, parts overlay (prediction), labels'
    parts, side view (prediction blue, labels grey)."""
    from PIL import Image, ImageDraw

    order = np.argsort(err)
    q = np.array_split(order, 4)
    picks = [(qi, int(i)) for qi, part in enumerate(q) for i in part[np.linspace(0, len(part) - 1, per_quartile).astype(int)]] if len(order) >= 4 else [(0, int(i)) for i in order]
    s = a["image"].shape[1]
    cell = max(s, 128)
    rows = []
    for qi, i in picks:
        img = a["image"][i]
        cols = [img, overlay(img, a["pred_v"][i], faces, a["K"][i]), parts_overlay(img, a["pred_v"][i], faces, a["K"][i], flabels),
                label_image(a["gt_parts"][i]),
                side_view([(a["pred_v"][i], (0.35, 0.55, 0.95)), (a["gt_v"][i], (0.7, 0.7, 0.7))], faces, s)]
        row = Image.new("RGB", (cell * len(cols), cell + 14), "white")
        for c, im in enumerate(cols):
            row.paste(Image.fromarray(im).resize((cell, cell), Image.NEAREST), (c * cell, 14))
        ImageDraw.Draw(row).text((3, 1), f"quartile {qi + 1}  PA-MPJPE {err[i]:.0f} mm", fill="black")
        rows.append(row)
    head = Image.new("RGB", (rows[0].width, 16), "white")
    ImageDraw.Draw(head).text((3, 2), "crop | mesh | predicted parts | label parts | side (pred blue, label grey)", fill="black")
    sheet = Image.new("RGB", (rows[0].width, 16 + sum(r.height for r in rows)), "white")
    sheet.paste(head, (0, 0))
    y = 16
    for r in rows:
        sheet.paste(r, (0, y))
        y += r.height
    tmp = png.with_name(f".{png.name}.tmp.png")
    sheet.save(tmp)
    tmp.replace(png)


def format_report(res: dict[str, Any]) -> str:
    """The headline numbers as text (what ``recovery evaluate`` prints)."""
    b = res["baselines"]
    seg = res.get("segmentation", {})
    lines = [
        f"{res['dataset']}: {res['people']} people ({res['subjects']} subjects), crop {res['crop']} px, checkpoint {res['checkpoint']}"
        + (", flip test" if res.get("flip_test") else ""),
        f"  MPJPE {res['mpjpe_mm']:.1f} mm  PA-MPJPE {res['pa_mpjpe_mm']:.1f} mm  PVE {res['pve_mm']:.1f} mm  "
        f"PCK@0.05 {res['pck_0.05']:.3f}  PCK@0.1 {res['pck_0.1']:.3f}",
        f"  segmentation: fg acc {seg.get('fg_accuracy', float('nan')):.3f} F1 {seg.get('fg_f1', float('nan')):.3f}; "
        f"parts acc {seg.get('parts_accuracy', float('nan')):.3f} macro F1 {seg.get('parts_macro_f1', float('nan')):.3f}",
        f"  body frame (rotation removed): joints {res['body_frame']['joint_mm']:.1f} mm, PA {res['body_frame']['pa_joint_mm']:.1f} mm, "
        f"vertices {res['body_frame']['vertex_mm']:.1f} mm; roughness {res['body_frame']['roughness_mm']:.2f} mm (labels {res['body_frame']['label_roughness_mm']:.2f})",
        *([f"  poses below the prior's 1st percentile of real frames: {100 * res['pose_prior']['fraction_below']:.1f} %"] if res.get("pose_prior") else []),
        f"  fixed skeleton PA-MPJPE {b['fixed_skeleton']['pa_mpjpe_mm']:.1f} mm ({100 * res['relative']['pa_mpjpe_vs_fixed_skeleton']:+.1f} %); "
        f"mean pose MPJPE {b['mean_pose']['mpjpe_mm']:.1f} mm ({100 * res['relative']['mpjpe_vs_mean_pose']:+.1f} %)",
    ]
    for name, groups in res["splits"].items():
        parts = [f"{g}: {v['people']} people" + (f", PA-MPJPE {v['pa_mpjpe_mm']:.1f}" if v["people"] else "") for g, v in groups.items()]
        lines.append(f"  by {name}: " + "; ".join(parts))
    if res.get("temporal"):
        lines.append(format_temporal(res["temporal"]))
    return "\n".join(lines)
