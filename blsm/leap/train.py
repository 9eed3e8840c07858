"""Training and evaluating LEAP on BLSM (Sec. 4.3, Table 2): ``blsm leap train CONFIG --out DIR``.

Two stages, as the paper's: first the inverse and forward LBS networks against the nearest-vertex
weights (L1), then, with them fixed, everything else against the exact occupancy (Eq. 19, squared
error of the occupancy probability). The data (:mod:`blsm.leap.data`) is made once into
``DIR/data.npz``: training bodies (training subjects in training clips), and two test sets, unseen
poses (training subjects in held-out clips) and unseen subjects (held-out subjects in training
clips). A checkpoint ``DIR/last.pt`` is written every ``save_every`` steps; ``--resume`` goes on
from it. :func:`evaluate` gives the mean IoU (percent) over each test set's bodies, on their query
points (half near the surface, half uniform in the grown box).
"""

from __future__ import annotations

import json
import time
from dataclasses import asdict, dataclass, field
from pathlib import Path
from typing import Any

import numpy as np
import torch

from blsm.leap.model import Leap, LeapConfig


@dataclass(frozen=True)
class LeapTrainConfig:
    """``configs/leap/*.yaml``: data sizes, the two stages' steps, the networks."""

    motions: str = "out/motions_train"  # an imported motion library (blsm mocap import)
    held_out_every: int = 8  # every 8th clip (sorted by name) is an unseen-pose clip
    train_bodies: int = 1000
    test_bodies: int = 100  # per test set
    points: int = 4096  # query points made per body
    batch_bodies: int = 8
    batch_points: int = 1024  # drawn from a body's points each step
    lbs_steps: int = 2000
    occupancy_steps: int = 4000
    lr: float = 5e-4
    save_every: int = 250
    seed: int = 0
    net: LeapConfig = field(default_factory=LeapConfig)

    def __post_init__(self) -> None:
        for k in ("train_bodies", "test_bodies", "points", "batch_bodies", "batch_points", "held_out_every", "save_every"):
            if getattr(self, k) < 1:
                raise ValueError(f"{k} must be positive, got {getattr(self, k)}")
        if self.batch_points > self.points:
            raise ValueError(f"batch_points ({self.batch_points}) must be at most points ({self.points})")


def make_data(model: torch.nn.Module, cfg: LeapTrainConfig, path: Path, log: Any = print) -> dict[str, np.ndarray]:
    """The three sets of the module docstring, written to ``path`` (kept: a second call reads it)."""
    from blsm.leap.data import body_points, draw_bodies, load_clips, subject_split

    if path.is_file():
        with np.load(path) as d:
            return {k: d[k] for k in d.files}
    clips = load_clips(cfg.motions)
    names = sorted(clips)
    held = set(names[cfg.held_out_every - 1 :: cfg.held_out_every])
    train_clips = {k: v for k, v in clips.items() if k not in held}
    test_clips = {k: v for k, v in clips.items() if k in held}
    if not test_clips:
        raise ValueError(f"{cfg.motions}: {len(names)} clips leave none out at held_out_every {cfg.held_out_every}")
    train_subj, unseen_subj = subject_split(len(model.population_bone))
    rng = np.random.default_rng(cfg.seed)
    out: dict[str, np.ndarray] = {}
    for name, n, cl, subj in (("train", cfg.train_bodies, train_clips, train_subj),
                              ("unseen_poses", cfg.test_bodies, test_clips, train_subj),
                              ("unseen_subjects", cfg.test_bodies, train_clips, unseen_subj)):  # fmt: skip
        t0 = time.time()
        bodies = draw_bodies(model, cl, subj, n, rng)
        pts = [body_points(model, bodies.vertices[i], bodies.template[i], cfg.points, rng) for i in range(n)]
        out[f"{name}_B"] = bodies.B.astype(np.float32)
        out[f"{name}_subject"] = bodies.subject
        for k in ("x", "occ", "w", "xc", "wc"):
            out[f"{name}_{k}"] = np.stack([p[k] for p in pts])
        log(f"[leap] {name}: {n} bodies, {cfg.points} points each ({time.time() - t0:.0f} s)")
    out["held_out_clips"] = np.array(sorted(held))
    path.parent.mkdir(parents=True, exist_ok=True)
    tmp = path.with_name(path.name + ".tmp.npz")
    np.savez(tmp, **out)
    tmp.replace(path)
    return out


def _batch(data: dict[str, np.ndarray], split: str, rng: np.random.Generator, nb: int, npts: int) -> dict[str, torch.Tensor]:
    n, m = data[f"{split}_x"].shape[:2]
    bi = rng.integers(n, size=nb)
    pi = np.stack([rng.choice(m, npts, replace=False) for _ in range(nb)])
    take = lambda k: torch.from_numpy(data[f"{split}_{k}"][bi[:, None], pi])  # noqa: E731
    return {"B": torch.from_numpy(data[f"{split}_B"][bi]), "x": take("x"), "occ": take("occ"), "w": take("w"),
            "xc": take("xc"), "wc": take("wc")}


def lbs_loss(leap: Leap, b: dict[str, torch.Tensor]) -> torch.Tensor:
    """Stage 1: L1 of the inverse weights at posed points and the forward weights at canonical
    points against the nearest vertex's (Sec. 4.3)."""
    body = leap.body(b["B"])
    c_inv, c_fwd = leap.lbs_conditions(body)
    w = leap.inverse_weights(b["x"], c_inv)
    wf = leap.forward_weights(b["xc"], c_fwd)
    return (w - b["w"]).abs().sum(-1).mean() + (wf - b["wc"]).abs().sum(-1).mean()


def occupancy_loss(leap: Leap, b: dict[str, torch.Tensor]) -> torch.Tensor:
    """Stage 2: Eq. 19, the squared error of the occupancy probability."""
    return (torch.sigmoid(leap(b["B"], b["x"])["logits"]) - b["occ"]).pow(2).mean()


LBS_PARTS = ("fwd_rest", "fwd_posed", "inv_rest", "inv_posed", "inv_pose", "inverse", "forward_lbs")


def train(cfg: LeapTrainConfig, out: Path, resume: bool = False, log: Any = print) -> Path:
    """Both stages into ``out`` (module docstring); returns the checkpoint's path."""
    import blsm

    out = Path(out)
    last = out / "last.pt"
    if last.exists() and not resume:
        raise ValueError(f"{last}: a run is already there (use --resume, or another --out)")
    torch.manual_seed(cfg.seed)
    model = blsm.load()
    data = make_data(model, cfg, out / "data.npz", log)
    leap = Leap(model, cfg.net)
    lbs = [p for n in LBS_PARTS for p in getattr(leap, n).parameters()]
    rest = [p for n, m in leap.named_children() if n not in LBS_PARTS for p in m.parameters()] + [leap.project, leap.project_bias]
    opt_lbs, opt_occ = torch.optim.Adam(lbs, cfg.lr), torch.optim.Adam(rest, cfg.lr)
    step, history = 0, []
    if resume and last.exists():
        ck = torch.load(last, weights_only=False)
        if ck["config"] != json.loads(json.dumps(asdict(cfg))):
            raise ValueError(f"{last}: made with another config; resume it with that one")
        leap.load_state_dict(ck["model"])
        opt_lbs.load_state_dict(ck["opt_lbs"])
        opt_occ.load_state_dict(ck["opt_occ"])
        step, history = ck["step"], ck["history"]
    total = cfg.lbs_steps + cfg.occupancy_steps
    rng = np.random.default_rng([cfg.seed, step])
    t0 = time.time()
    while step < total:
        stage = "lbs" if step < cfg.lbs_steps else "occupancy"
        leap.train()
        if stage == "occupancy":  # the LBS networks fixed: deterministic functions (Sec. 4.3)
            for n in LBS_PARTS:
                getattr(leap, n).eval()
        b = _batch(data, "train", rng, cfg.batch_bodies, cfg.batch_points)
        opt = opt_lbs if stage == "lbs" else opt_occ
        loss = lbs_loss(leap, b) if stage == "lbs" else occupancy_loss(leap, b)
        opt.zero_grad()
        loss.backward()
        opt.step()
        step += 1
        if step % 50 == 0:
            history.append({"step": step, "stage": stage, "loss": float(loss)})
            log(f"[leap] step {step}/{total} {stage} loss {float(loss):.4f} ({(time.time() - t0) / 50:.2f} s/step)")
            t0 = time.time()
        if step % cfg.save_every == 0 or step == total:
            _save(last, leap, opt_lbs, opt_occ, step, history, cfg)
    return last


def _save(path: Path, leap: Leap, opt_lbs: Any, opt_occ: Any, step: int, history: list, cfg: LeapTrainConfig) -> None:
    tmp = path.with_name(path.name + ".tmp")
    torch.save({"model": leap.state_dict(), "opt_lbs": opt_lbs.state_dict(), "opt_occ": opt_occ.state_dict(),
                "step": step, "history": history, "config": json.loads(json.dumps(asdict(cfg)))}, tmp)
    tmp.replace(path)


@torch.no_grad()
def evaluate(leap: Leap, data: dict[str, np.ndarray], split: str, chunk: int = 8) -> dict[str, float]:
    """Mean IoU (percent) over ``split``'s bodies of the predicted occupancy (probability >= 0.5,
    Eq. 14) against the exact one, on each body's query points; and the mean L1 of the inverse and
    forward weights (Table D.2)."""
    leap.eval()
    ious, l1_inv, l1_fwd = [], [], []
    n = len(data[f"{split}_B"])
    for s in range(0, n, chunk):
        B = torch.from_numpy(data[f"{split}_B"][s : s + chunk])
        x = torch.from_numpy(data[f"{split}_x"][s : s + chunk])
        r = leap(B, x)
        pred = r["logits"] >= 0.0
        true = torch.from_numpy(data[f"{split}_occ"][s : s + chunk]) > 0.5
        inter, union = (pred & true).sum(1).float(), (pred | true).sum(1).float()
        ious += (100.0 * inter / union.clamp(min=1)).tolist()
        l1_inv += (r["w_inv"] - torch.from_numpy(data[f"{split}_w"][s : s + chunk])).abs().sum(-1).mean(1).tolist()
        body = leap.body(B)
        wf = leap.forward_weights(torch.from_numpy(data[f"{split}_xc"][s : s + chunk]), leap.lbs_conditions(body)[1])
        l1_fwd += (wf - torch.from_numpy(data[f"{split}_wc"][s : s + chunk])).abs().sum(-1).mean(1).tolist()
    return {"iou": round(float(np.mean(ious)), 2), "l1_inv": round(float(np.mean(l1_inv)), 4),
            "l1_fwd": round(float(np.mean(l1_fwd)), 4), "bodies": n}
