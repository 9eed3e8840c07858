"""The transfer check: how much of a network's synthetic skill survives on real photographs.

``recovery transfer CHECKPOINT --real DIR --synthetic DATASET --out OUT`` (docs/transfer.md).

There are no labelled real images here, so both domains are scored against one **reference**, a 2D
pose estimator trained on photographs (MediaPipe Pose by default, run by
``blsm/pose2d/mediapipe_pose.py`` in an environment of its own, ``scripts/setup_reference.sh``), on the
17 COCO keypoints that BLSM and BlazePose both define (:data:`COCO_NAMES`).

For every person (a box of ``DIR/boxes.json``, or a person of the synthetic dataset, its label box):

1. the reference runs on the square around the given box (the box only says *which* person);
2. **one box rule for both domains**: the reference's visible joints (visibility >= ``VISIBILITY``,
   inside the image; at least ``MIN_JOINTS`` of them, else the person counts as a reference failure)
   give a joint box; the person box is that box's centre with side ``JOINT_BOX_GROWTH`` times its
   longer side (the median ratio of the silhouette box to the 17 joints' box on our labels, 1.18);
3. the network sees the crop of side ``1.2`` times the person box (its training crop, SPIN's rule),
   with the camera of ``recovery predict`` (focal length = the image's longer side; synthetic images
   use their true camera); its 17 keypoints are projected back into the image;
4. PCK@a: the share of the reference's visible joints within ``a`` times the person box's side of
   the network's (pooled over joints);
5. the **mean-pose floor**: each domain's median reference pose in person-box coordinates, put into
   every person's box, scored the same way: what knowing only the box is worth.

``gain = PCK(ours) - PCK(floor)`` per domain, and the **transfer ratio** ``gain(real) /
gain(synthetic)`` at PCK@0.1. A second reading uses one floor for both domains, the synthetic
images' median pose (what knowing the box and the training data's typical pose is worth):
``(PCK(ours, real) - PCK(synthetic median, real)) / gain(synthetic)``, reported beside the ratio.
A 90 % interval comes from a bootstrap over people (both domains resampled). On the synthetic side
the reference is also scored against the labels (how far the reference itself is from the truth).

``CHECKPOINT`` may also be ``movenet_lightning`` or ``movenet_thunder``: MoveNet's own 2D keypoints
(:class:`KeypointPredictor`, on the same crops at MoveNet's native size), scored the same way. No
network trained on our data can read photographs better than the backbone it reads them with: this
is the **ceiling row** of docs/transfer.md.

Writes ``OUT/report.json``, ``OUT/report.md`` and ``OUT/sheet_real.png`` / ``OUT/sheet_synthetic.png``
(each person's crop: the predicted mesh, the reference's joints in green, ours in red). Reference
answers are cached in ``OUT/reference.json`` (by image content, box and reference command).
"""

from __future__ import annotations

import hashlib
import json
import math
import os
import shlex
import sys
from dataclasses import dataclass
from pathlib import Path
from typing import Any

import numpy as np
import torch

from blsm.io import atomic_write
from blsm.pose2d.detectors import SCRIPT as MEDIAPIPE_SCRIPT
from blsm.pose2d.detectors import run_pose_script

COCO_NAMES: tuple[str, ...] = (
    "nose", "left_eye", "right_eye", "left_ear", "right_ear", "left_shoulder", "right_shoulder",
    "left_elbow", "right_elbow", "left_wrist", "right_wrist", "left_hip", "right_hip", "left_knee",
    "right_knee", "left_ankle", "right_ankle",
)
MEDIAPIPE_INDEX: tuple[int, ...] = (0, 2, 5, 7, 8, 11, 12, 13, 14, 15, 16, 23, 24, 25, 26, 27, 28)
"""BlazePose's landmark for each of :data:`COCO_NAMES` (its 33-landmark topology)."""
COCO_SKELETON = ((5, 7), (7, 9), (6, 8), (8, 10), (5, 6), (5, 11), (6, 12), (11, 12), (11, 13), (13, 15),
                 (12, 14), (14, 16), (0, 1), (0, 2), (1, 3), (2, 4))
VISIBILITY = 0.5
MIN_JOINTS = 6
JOINT_BOX_GROWTH = 1.18
CROP_SCALE = 1.2  # the network's crop side over the person box's (training: SynthDataset's box_scale)
THRESHOLDS = (0.1, 0.2)
BOOTSTRAP = 2000
REFERENCE_SCRIPT = MEDIAPIPE_SCRIPT  # blsm/pose2d/mediapipe_pose.py, stand-alone
REFERENCE_ENV = Path(__file__).resolve().parents[2] / ".venv-reference"  # the repository root's
IMAGE_EXT = (".jpg", ".jpeg", ".png")


@dataclass
class Person:
    """One person to score: the image file, the box naming them, and (synthetic) their true joints."""

    image: Path
    box: tuple[float, float, float, float]
    size: tuple[int, int]  # the image's (height, width)
    K: np.ndarray | None = None  # the true camera (synthetic); None: recovery predict's default
    truth: np.ndarray | None = None  # (17, 3) true 2D joints and in-frame flag (synthetic)


def read_boxes(folder: str | Path) -> list[Person]:
    """The people of a real-image folder: ``FOLDER/boxes.json`` maps image file names (relative to
    the folder, or to its ``images/`` sub-folder) to lists of ``[x0, y0, x1, y1]`` boxes in pixels. A ValueError names the file and the
    problem (no boxes.json, bad JSON, a missing or unreadable image, a box outside its image)."""
    from recovery.predict import read_image

    folder = Path(folder)
    path = folder / "boxes.json"
    if not path.is_file():
        raise ValueError(f"{path}: no such file (the real-image folder needs boxes.json: {{\"file\": [[x0, y0, x1, y1], ...]}})")
    try:
        boxes = json.loads(path.read_text())
    except (json.JSONDecodeError, UnicodeDecodeError) as exc:
        raise ValueError(f"{path}: not JSON ({exc})") from None
    if not isinstance(boxes, dict) or not boxes:
        raise ValueError(f"{path}: expected a non-empty object {{\"file\": [[x0, y0, x1, y1], ...]}}")
    people = []
    for name in sorted(boxes):
        image = folder / name
        if not image.exists() and (folder / "images" / name).exists():
            image = folder / "images" / name  # the layout of scripts/setup_transfer_devset.py
        h, w = read_image(image).shape[:2]
        entries = boxes[name]
        if not isinstance(entries, list) or not entries:
            raise ValueError(f"{path}: {name!r} needs a non-empty list of boxes")
        for box in entries:
            ok = isinstance(box, list) and len(box) == 4 and all(isinstance(v, (int, float)) for v in box)
            if not ok or not (0 <= box[0] < box[2] <= w and 0 <= box[1] < box[3] <= h):
                raise ValueError(f"{path}: box {box} of {name!r} is not [x0, y0, x1, y1] inside the {w} x {h} image")
            people.append(Person(image, tuple(float(v) for v in box), (h, w)))
    return people


def synthetic_people(dataset: str | Path, folder: Path, max_people: int) -> list[Person]:
    """Up to ``max_people`` people spread evenly over ``dataset`` (a ``synth`` dataset), their
    images written to ``folder`` as PNG files, with their label boxes, cameras and true joints."""
    from synth.dataset.index import DatasetIndex

    index = DatasetIndex(dataset)
    everyone = []
    for i in range(len(index)):
        meta = index.json(i)
        ids = [meta["keypoint_names"].index(n) for n in COCO_NAMES]
        for p in meta["people"]:
            if p.get("box") is None:  # out of frame: nobody to point at
                continue
            truth = np.concatenate([np.asarray(p["keypoints_2d"])[ids], np.asarray(p["in_frame"], float)[ids, None]], 1)
            everyone.append((i, meta, p["box_full"], truth))
    if not everyone:
        raise ValueError(f"{dataset}: the dataset holds no people")
    pick = np.unique(np.linspace(0, len(everyone) - 1, min(max_people, len(everyone))).round().astype(int))
    folder.mkdir(parents=True, exist_ok=True)
    people = []
    for j in pick:
        i, meta, box, truth = everyone[j]
        image = folder / f"{i:07d}.png"
        if not image.is_file():
            with atomic_write(image, "wb") as fh:
                fh.write(index.read(i, ["rgb.png"])["rgb.png"])
        size = (int(meta["image"]["height"]), int(meta["image"]["width"]))
        people.append(Person(image, tuple(float(v) for v in box), size, np.asarray(meta["camera"]["K"], float), truth))
    index.close()
    return people


def _file_hash(path: Path, memo: dict[Path, str]) -> str:
    if path not in memo:
        memo[path] = hashlib.sha256(path.read_bytes()).hexdigest()[:16]
    return memo[path]


def run_reference(people: list[Person], command: list[str], cache_path: Path) -> np.ndarray:
    """(N, 17, 3) the reference's joints (x, y, visibility) for each person, NaN where it found none.

    ``command`` is run as ``command + [JOB.json, OUT.json]`` (:mod:`blsm.pose2d.mediapipe_pose`'s
    interface) for the people not in the cache; a failing command is a ValueError with its last line.
    """
    memo: dict[Path, str] = {}
    tag = " ".join(command[1:]) if len(command) > 1 else command[0]
    cache: dict[str, Any] = json.loads(cache_path.read_text()) if cache_path.is_file() else {}
    keys = [f"{_file_hash(p.image, memo)}|{[round(v, 3) for v in p.box]}|{Path(tag).name}" for p in people]
    todo = [i for i, k in enumerate(keys) if k not in cache]
    if todo:
        job = [{"image": str(people[i].image.resolve()), "box": list(people[i].box)} for i in todo]
        answer = run_pose_script(command, job, f"reference {shlex.join(command)}:")
        items = answer["items"]
        for i, item in zip(todo, items, strict=True):
            cache[keys[i]] = {"landmarks": item["landmarks"], "reference": answer.get("reference", tag)}
        with atomic_write(cache_path, "w") as fh:
            fh.write(json.dumps(cache))
    ref = np.full((len(people), len(COCO_NAMES), 3), np.nan)
    for i, k in enumerate(keys):
        lms = cache[k]["landmarks"]
        if lms is not None:
            ref[i] = np.asarray(lms, float)[list(MEDIAPIPE_INDEX)]
    return ref


def visible_joints(ref: np.ndarray, sizes: list[tuple[int, int]]) -> np.ndarray:
    """(N, 17) the reference joints that count: visibility >= VISIBILITY and inside their image
    (``sizes``: each person's image (height, width))."""
    wh = np.asarray([(w, h) for h, w in sizes], float)[:, None]
    with np.errstate(invalid="ignore"):
        inside = (ref[..., :2] >= 0).all(-1) & (ref[..., :2] < wh).all(-1)
        return inside & (ref[..., 2] >= VISIBILITY)


def person_boxes(ref: np.ndarray, vis: np.ndarray) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    """The box rule: (N, 2) centres and (N,) sides of the person boxes from the visible reference
    joints, and (N,) which people have enough joints (``MIN_JOINTS``) to be scored."""
    ok = vis.sum(1) >= MIN_JOINTS
    centre, side = np.full((len(ref), 2), np.nan), np.full(len(ref), np.nan)
    for i in np.flatnonzero(ok):
        pts = ref[i, vis[i], :2]
        lo, hi = pts.min(0), pts.max(0)
        centre[i], side[i] = (lo + hi) / 2, JOINT_BOX_GROWTH * max(float((hi - lo).max()), 1.0)
    return centre, side, ok


def median_pose(ref: np.ndarray, vis: np.ndarray, centre: np.ndarray, side: np.ndarray, ok: np.ndarray) -> np.ndarray:
    """(17, 2) the per-joint median of the scored people's visible reference joints in person-box
    coordinates ``(x - centre) / side``."""
    norm = (ref[..., :2] - centre[:, None]) / side[:, None, None]
    use = vis & ok[:, None]
    med = np.zeros((len(COCO_NAMES), 2))
    for j in range(len(COCO_NAMES)):
        if use[:, j].any():
            med[j] = np.median(norm[use[:, j], j], axis=0)
    return med


def mean_pose_floor(ref: np.ndarray, vis: np.ndarray, centre: np.ndarray, side: np.ndarray, ok: np.ndarray,
                    pose: np.ndarray | None = None) -> np.ndarray:
    """(N, 17, 2) the floor's joints: :func:`median_pose` (or a given (17, 2) ``pose`` in box
    coordinates, e.g. the other domain's median) put into each person's box."""
    med = median_pose(ref, vis, centre, side, ok) if pose is None else pose
    return centre[:, None] + side[:, None, None] * med[None]


def correct(pred: np.ndarray, ref: np.ndarray, vis: np.ndarray, side: np.ndarray, alpha: float) -> np.ndarray:
    """(N, 17) the visible reference joints within ``alpha * side`` of ``pred``."""
    dist = np.linalg.norm(pred - ref[..., :2], axis=-1)
    with np.errstate(invalid="ignore"):
        return (dist < alpha * side[:, None]) & vis


def hits(pred: np.ndarray, ref: np.ndarray, vis: np.ndarray, side: np.ndarray, alpha: float) -> np.ndarray:
    """(N,) how many of :func:`correct`'s joints each person has."""
    return correct(pred, ref, vis, side, alpha).sum(1)


class KeypointPredictor:
    """MoveNet's own 2D keypoints behind the predictor interface :func:`predict_joints` uses (the
    ceiling row): ``crop`` is MoveNet's native input, ``keypoint_names`` its COCO order, and a call
    returns the keypoints (graph decoding, :meth:`recovery.models.backbones.movenet.MoveNet.keypoints`)
    in crop pixels, with no mesh."""

    def __init__(self, name: str) -> None:
        from recovery.models.backbones.movenet import COCO_KEYPOINTS, build_movenet

        self.net = build_movenet(name).eval()
        self.crop = self.net.input_size
        self.keypoint_names = COCO_KEYPOINTS
        self.path = name

    @torch.no_grad()
    def __call__(self, images: torch.Tensor, k_crop: torch.Tensor) -> Any:
        from types import SimpleNamespace

        kp = self.net.keypoints(self.net.run(self.net.normalize(images)))
        return SimpleNamespace(keypoints_2d=kp[..., :2], vertices=None, transl=None)


def predict_joints(pr: Any, people: list[Person], centre: np.ndarray, side: np.ndarray, ok: np.ndarray,
                   batch: int = 32, antialias: bool = True) -> tuple[np.ndarray, list[dict[str, Any]]]:
    """(N, 17, 2) the joints of predictor ``pr`` (:func:`recovery.predictor.load_predictor`) in
    image pixels (NaN where not scored) and, per scored person, what the sheet draws (crop, mesh,
    K_crop, affine). ``antialias``: :func:`synth.dataset.crops.warp_to_crop`'s prefilter (off: bilinear
    sampling alone, as before 2026-12-02)."""
    from recovery.predict import read_image
    from synth.dataset.crops import crop_affine, map_points, warp_to_crop

    names = list(getattr(pr, "keypoint_names", None) or pr.body.keypoint_names)
    ids = [names.index(n) for n in COCO_NAMES]
    out = np.full((len(people), len(COCO_NAMES), 2), np.nan)
    views: list[dict[str, Any]] = []
    todo = [int(i) for i in np.flatnonzero(ok)]
    images: dict[Path, np.ndarray] = {}
    for b0 in range(0, len(todo), batch):
        chunk = todo[b0:b0 + batch]
        crops, ks, affs = [], [], []
        for i in chunk:
            p = people[i]
            if p.image not in images:
                images.clear()
                images[p.image] = read_image(p.image)
            img = images[p.image]
            h, w = img.shape[:2]
            k = p.K if p.K is not None else np.array([[max(w, h), 0, w / 2], [0, max(w, h), h / 2], [0, 0, 1.0]])
            a = crop_affine(tuple(centre[i]), float(side[i]) * CROP_SCALE, pr.crop)
            crops.append(warp_to_crop(torch.from_numpy(img).permute(2, 0, 1).float() / 255.0, a, pr.crop,
                                      antialias=antialias))
            ks.append(torch.tensor(a @ k, dtype=torch.float32))
            affs.append(a)
        with torch.no_grad():
            res = pr(torch.stack(crops), torch.stack(ks))
        uv = res.keypoints_2d[:, ids].double().numpy()
        for n, i in enumerate(chunk):
            out[i] = map_points(uv[n], np.linalg.inv(affs[n]))
            views.append({"person": i, "crop": (crops[n].permute(1, 2, 0).numpy() * 255 + 0.5).astype(np.uint8),
                          "vertices": None if res.vertices is None else (res.vertices[n] + res.transl[n]).numpy(),
                          "K_crop": ks[n].double().numpy(),
                          "affine": affs[n], "uv": uv[n]})
    return out, views


@dataclass
class Domain:
    """One domain's people, reference, box rule and scores (for the report and the bootstrap)."""

    name: str
    people: list[Person]
    ref: np.ndarray
    vis: np.ndarray
    centre: np.ndarray
    side: np.ndarray
    ok: np.ndarray
    ours: np.ndarray
    floor: np.ndarray
    synthetic_floor: np.ndarray | None = None  # the synthetic images' median pose in these boxes

    def counts(self, alpha: float) -> dict[str, np.ndarray]:
        """Per scored person: visible joints, the network's and the floor's hits at ``alpha`` (and
        the synthetic median pose's, ``synthetic_floor``, where set)."""
        s = self.ok
        vis = self.vis[s]
        out = {"joints": vis.sum(1),
               "ours": hits(self.ours[s], self.ref[s], vis, self.side[s], alpha),
               "floor": hits(self.floor[s], self.ref[s], vis, self.side[s], alpha)}
        if self.synthetic_floor is not None:
            out["synthetic_floor"] = hits(self.synthetic_floor[s], self.ref[s], vis, self.side[s], alpha)
        return out

    def extent_ratio(self) -> list[float] | None:
        """Median over scored people of the width and height of the network's visible joints over
        the reference's (1: the right size; a network that shrinks the body reads below 1)."""
        out = []
        for i in np.flatnonzero(self.ok):
            v = self.vis[i]
            ref, ours = self.ref[i, v, :2], self.ours[i, v]
            span = ref.max(0) - ref.min(0)
            if (span > 0).all():
                out.append((ours.max(0) - ours.min(0)) / span)
        return np.median(np.asarray(out), 0).tolist() if out else None

    def per_joint(self, alpha: float) -> dict[str, dict[str, float]]:
        """PCK@alpha per COCO joint: the network's and the floor's, over the people it is visible in."""
        s = self.ok
        vis = self.vis[s]
        out = {name: correct(f[s], self.ref[s], vis, self.side[s], alpha).sum(0) / np.maximum(vis.sum(0), 1)
               for name, f in (("ours", self.ours), ("floor", self.floor))}
        return {n: {"ours": float(out["ours"][j]), "floor": float(out["floor"][j]), "people": int(vis[:, j].sum())}
                for j, n in enumerate(COCO_NAMES)}

    def truth_pck(self, alpha: float) -> float | None:
        """The reference against the labels (synthetic only): PCK over joints visible to both."""
        if self.people[0].truth is None:
            return None
        s = np.flatnonzero(self.ok)
        truth = np.stack([self.people[i].truth for i in s])
        vis = self.vis[s] & (truth[..., 2] > 0)
        h = hits(truth[..., :2], self.ref[s], vis, self.side[s], alpha)
        return float(h.sum() / max(vis.sum(), 1))


def pck_share(c: dict[str, np.ndarray], key: str, idx: np.ndarray | None = None) -> float:
    """PCK pooled over joints from :meth:`Domain.counts`: ``c[key]``'s hits over the visible joints
    (of the people ``idx``, all by default)."""
    j, h = (c[k] if idx is None else c[k][idx] for k in ("joints", key))
    return float(h.sum() / max(int(j.sum()), 1))


def _pck(c: dict[str, np.ndarray], idx: np.ndarray | None = None) -> tuple[float, float]:
    return pck_share(c, "ours", idx), pck_share(c, "floor", idx)


def summarise(real: Domain, synthetic: Domain, seed: int = 0) -> dict[str, Any]:
    """The report: PCK of the network and of the floor per domain and threshold, the gains, the
    transfer ratio at PCK@0.1 with its bootstrap interval, and the reference's own failures."""
    rep: dict[str, Any] = {"box_rule": {"visibility": VISIBILITY, "min_joints": MIN_JOINTS, "joint_box_growth": JOINT_BOX_GROWTH,
                                        "crop_scale": CROP_SCALE, "keypoints": list(COCO_NAMES)}, "domains": {}}
    for d in (real, synthetic):
        entry: dict[str, Any] = {"people": len(d.people), "images": len({p.image for p in d.people}),
                                 "scored": int(d.ok.sum()), "reference_failures": int((~d.ok).sum()),
                                 "joints": int(d.vis[d.ok].sum())}
        entry["extent_ratio"] = d.extent_ratio()
        entry["per_joint@0.1"] = d.per_joint(0.1)
        for a in THRESHOLDS:
            c = d.counts(a)
            ours, floor = _pck(c)
            entry[f"pck@{a}"] = {"ours": ours, "floor": floor, "gain": ours - floor}
            if "synthetic_floor" in c:
                entry[f"pck@{a}"]["synthetic_floor"] = pck_share(c, "synthetic_floor")
            truth = d.truth_pck(a)
            if truth is not None:
                entry[f"pck@{a}"]["reference_vs_labels"] = truth
        rep["domains"][d.name] = entry
    for a in THRESHOLDS:
        gr, gs = (rep["domains"][d.name][f"pck@{a}"]["gain"] for d in (real, synthetic))
        rep[f"transfer_ratio@{a}"] = gr / gs if gs > 0 else math.nan
        sf = rep["domains"][real.name][f"pck@{a}"].get("synthetic_floor")
        if sf is not None:  # the second reading: one floor for both domains, the synthetic median pose
            rep[f"transfer_ratio_synthetic_floor@{a}"] = (
                (rep["domains"][real.name][f"pck@{a}"]["ours"] - sf) / gs if gs > 0 else math.nan)
    rng = np.random.default_rng(seed)
    cr, cs = real.counts(THRESHOLDS[0]), synthetic.counts(THRESHOLDS[0])
    nr, ns = len(cr["joints"]), len(cs["joints"])
    ratios = []
    for _ in range(BOOTSTRAP if nr and ns else 0):
        o_r, f_r = _pck(cr, rng.integers(0, nr, nr))
        o_s, f_s = _pck(cs, rng.integers(0, ns, ns))
        ratios.append((o_r - f_r) / (o_s - f_s) if o_s > f_s else math.nan)
    ratios = np.asarray(ratios, float)
    ratios = ratios[np.isfinite(ratios)]
    rep["transfer_ratio_90"] = [float(np.percentile(ratios, 5)), float(np.percentile(ratios, 95))] if len(ratios) else None
    rep["bootstrap"] = BOOTSTRAP
    return rep


def format_report(rep: dict[str, Any]) -> str:
    """``report.md``: one table, the ratio and the settings."""
    rows = ["| domain | people (scored) | reference failures | PCK@0.1 ours | floor | gain | PCK@0.2 ours | floor | gain | "
            "reference vs labels @0.1 | size ours / reference (w, h) |",
            "|---|---:|---:|---:|---:|---:|---:|---:|---:|---:|---:|"]
    for name, d in rep["domains"].items():
        a, b = d["pck@0.1"], d["pck@0.2"]
        truth = f"{100 * a['reference_vs_labels']:.1f} %" if "reference_vs_labels" in a else "-"
        size = "{:.2f}, {:.2f}".format(*d["extent_ratio"]) if d.get("extent_ratio") else "-"
        rows.append(f"| {name} | {d['people']} ({d['scored']}) | {d['reference_failures']} | {100 * a['ours']:.1f} % | "
                    f"{100 * a['floor']:.1f} % | {100 * a['gain']:.1f} | {100 * b['ours']:.1f} % | {100 * b['floor']:.1f} % | "
                    f"{100 * b['gain']:.1f} | {truth} | {size} |")
    ci = rep.get("transfer_ratio_90")
    ci_text = f" (90 % bootstrap interval over people: {ci[0]:.2f} to {ci[1]:.2f})" if ci else ""
    lines = [f"# Transfer check: {rep.get('checkpoint', '')}", "",
             f"Reference: {rep.get('reference', '')}. Real: `{rep.get('real', '')}`; synthetic: `{rep.get('synthetic', '')}`.", "",
             *rows, "",
             f"**Transfer ratio** (gain on photos / gain on synthetic images, PCK@0.1): **{rep['transfer_ratio@0.1']:.2f}**{ci_text}; "
             f"at PCK@0.2: {rep['transfer_ratio@0.2']:.2f}.", ""]
    if "transfer_ratio_synthetic_floor@0.1" in rep:
        sf = rep["domains"]["real"]["pck@0.1"]["synthetic_floor"]
        lines += [f"Second reading, one floor for both domains (the synthetic images' median pose, {100 * sf:.1f} % on the "
                  f"photographs): ratio {rep['transfer_ratio_synthetic_floor@0.1']:.2f} at PCK@0.1, "
                  f"{rep['transfer_ratio_synthetic_floor@0.2']:.2f} at PCK@0.2.", ""]
    return "\n".join(lines)


def contact_sheet(domain: Domain, views: list[dict[str, Any]], faces: np.ndarray | None, path: Path, count: int = 48,
                  tile: int = 160) -> None:
    """A sheet of up to ``count`` people: the crop with the predicted mesh, the reference's joints
    (green) and the network's (red), both with the COCO skeleton (no mesh where ``faces`` or a view's
    vertices are None)."""
    from PIL import Image, ImageDraw

    from recovery.utils.viz import overlay
    from synth.dataset.crops import map_points

    views = views[:count]
    if not views:
        return
    cols = min(8, len(views))
    rows = math.ceil(len(views) / cols)
    sheet = Image.new("RGB", (cols * tile, rows * tile), (32, 32, 32))
    for n, v in enumerate(views):
        crop = v["crop"]
        img = crop if v["vertices"] is None or faces is None else overlay(crop, v["vertices"], faces, v["K_crop"], alpha=0.6)
        im = Image.fromarray(img).resize((tile, tile), Image.BILINEAR)
        draw = ImageDraw.Draw(im)
        sc = tile / crop.shape[0]
        i = v["person"]
        ref_uv = map_points(domain.ref[i, :, :2], v["affine"])
        for pts, vis, colour in ((ref_uv, domain.vis[i], (40, 220, 40)), (v["uv"], np.ones(len(COCO_NAMES), bool), (230, 40, 40))):
            for s, e in COCO_SKELETON:
                if vis[s] and vis[e]:
                    draw.line([tuple(pts[s] * sc), tuple(pts[e] * sc)], fill=colour, width=2)
        sheet.paste(im, ((n % cols) * tile, (n // cols) * tile))
    tmp = path.with_name(path.name + ".tmp.png")
    sheet.save(tmp)
    tmp.replace(path)


def reference_command(spec: str | None) -> list[str]:
    """The reference's command: ``spec`` split like a shell line, else MediaPipe in
    ``.venv-reference`` (``scripts/setup_reference.sh``); a ValueError when that is missing."""
    if spec:
        return shlex.split(spec)
    env = Path(os.environ.get("RECOVERY_REFERENCE_ENV", REFERENCE_ENV))
    python = env / "bin" / "python"
    if not python.is_file():
        raise ValueError(f"{env}: no reference environment (make it with scripts/setup_reference.sh, or pass --reference-command)")
    return [str(python), str(REFERENCE_SCRIPT)]


def reference_boxes(people: list[Person], command: list[str], cache_path: Path
                    ) -> tuple[np.ndarray, np.ndarray, np.ndarray, np.ndarray, np.ndarray]:
    """The reference's joints for ``people`` (:func:`run_reference`, answers cached at
    ``cache_path``), the ones that count (:func:`visible_joints`) and the box rule's person boxes
    (:func:`person_boxes`): ``(ref, vis, centre, side, ok)``."""
    ref = run_reference(people, command, cache_path)
    vis = visible_joints(ref, [p.size for p in people])
    return (ref, vis, *person_boxes(ref, vis))


def score_domain(name: str, people: list[Person], command: list[str], out: Path, pr: Any,
                 antialias: bool = True) -> tuple[Domain, list[dict[str, Any]]]:
    """One domain scored: the reference (answers cached in ``out/reference.json``), the box rule,
    the floor and predictor ``pr``'s joints; returns the :class:`Domain` and the sheet's views."""
    if not people:
        raise ValueError(f"{name}: no people to score")
    ref, vis, centre, side, ok = reference_boxes(people, command, out / "reference.json")
    floor = mean_pose_floor(ref, vis, centre, side, ok)
    ours, views = predict_joints(pr, people, centre, side, ok, antialias=antialias)
    return Domain(name, people, ref, vis, centre, side, ok, ours, floor), views


def scored_predictor(checkpoint: str | Path, flip: bool = False, fit: int | None = None) -> Any:
    """What the check scores: :class:`KeypointPredictor` for ``movenet_lightning`` / ``movenet_thunder``
    (the ceiling row), else the checkpoint's network (:func:`recovery.predictor.load_predictor`), with the
    test-time fit of ``fit`` iterations (None: the checkpoint's own setting)."""
    from recovery.models.backbones.movenet import VARIANTS as MOVENET
    from recovery.predictor import load_predictor

    if str(checkpoint) in MOVENET:
        if flip:
            raise ValueError(f"{checkpoint}: --flip averages HMR-BLSM parameters; MoveNet's keypoints have none")
        if fit:
            raise ValueError(f"{checkpoint}: --fit fits a body; MoveNet's keypoints have none")
        return KeypointPredictor(str(checkpoint))
    pr = load_predictor(checkpoint).use_flip(flip)
    return pr.use_fit(fit) if fit is not None else pr


def run_transfer(checkpoint: str | Path, real: str | Path, synthetic: str | Path, out: str | Path,
                 reference: str | None = None, synthetic_people_max: int = 400, flip: bool = False,
                 sheet_count: int = 48, antialias: bool = True, fit: int | None = None) -> dict[str, Any]:
    """The whole check (module docstring); returns the report written to ``OUT/report.json``.
    ``antialias``: the crops' prefilter (:func:`predict_joints`)."""
    out = Path(out)
    command = reference_command(reference)
    pr = scored_predictor(checkpoint, flip, fit)  # a bad checkpoint stops the run before any work
    real_people = read_boxes(real)
    out.mkdir(parents=True, exist_ok=True)
    syn_people = synthetic_people(synthetic, out / "synthetic_images", synthetic_people_max)
    d_real, v_real = score_domain("real", real_people, command, out, pr, antialias)
    d_syn, v_syn = score_domain("synthetic", syn_people, command, out, pr, antialias)
    d_real.synthetic_floor = mean_pose_floor(d_real.ref, d_real.vis, d_real.centre, d_real.side, d_real.ok,
                                             median_pose(d_syn.ref, d_syn.vis, d_syn.centre, d_syn.side, d_syn.ok))
    rep = summarise(d_real, d_syn)
    cache = json.loads((out / "reference.json").read_text())
    rep.update(checkpoint=str(checkpoint), real=str(real), synthetic=str(synthetic), flip_test=flip,
               reference=sorted({v["reference"] for v in cache.values()}), command=" ".join(sys.argv),
               antialias=antialias, fit=pr.fit.iterations if getattr(pr, "fit", None) is not None else 0)
    faces = pr.body.faces.numpy() if hasattr(pr, "body") else None
    contact_sheet(d_real, v_real, faces, out / "sheet_real.png", sheet_count)
    contact_sheet(d_syn, v_syn, faces, out / "sheet_synthetic.png", sheet_count)
    with atomic_write(out / "report.json", "w") as fh:
        fh.write(json.dumps(rep, indent=1))
    with atomic_write(out / "report.md", "w") as fh:
        fh.write(format_report(rep))
    return rep
