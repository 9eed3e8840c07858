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
    lbs_loss: str = "ce"  # "l1" (Sec. 4.3) or "ce": cross-entropy against the nearest vertex's weights
    occupancy_loss: str = "bce"  # "mse" (Eq. 19) or "bce": binary cross-entropy of the logits
    canonical_points: int = 0  # of each body's batch_points, scored in the canonical space too (B.2)
    lbs_from: str = ""  # another run's last.pt: take its trained LBS networks and skip stage 1
    save_every: int = 250
    device: str = "cpu"  # where the networks train ("cuda" on a lent GPU); the data stay in host memory
    eval_every: int = 0  # the test sets' IoU every this many steps into the history (0: never), a curve
    seed: int = 0
    net: LeapConfig = field(default_factory=LeapConfig)

    def __post_init__(self) -> None:
        if self.eval_every < 0:
            raise ValueError(f"eval_every must be 0 or positive, got {self.eval_every}")
        for k in ("train_bodies", "test_bodies", "points", "batch_bodies", "batch_points", "held_out_every", "save_every"):
            if getattr(self, k) < 1:
                raise ValueError(f"{k} must be positive, got {getattr(self, k)}")
        if self.lbs_loss not in ("ce", "l1"):
            raise ValueError(f"lbs_loss must be ce or l1, got {self.lbs_loss!r}")
        if self.occupancy_loss not in ("bce", "mse"):
            raise ValueError(f"occupancy_loss must be bce or mse, got {self.occupancy_loss!r}")
        if not 0 <= self.canonical_points <= self.batch_points:
            raise ValueError(f"canonical_points must be in [0, batch_points], got {self.canonical_points}")
        if self.batch_points > self.points:
            raise ValueError(f"batch_points ({self.batch_points}) must be at most points ({self.points})")


def make_data(model: torch.nn.Module, cfg: LeapTrainConfig, path: Path, log: Any = print) -> dict[str, np.ndarray]:
    """The three sets of the module docstring, written to ``path`` (kept: a second call reads it)."""
    from blsm.leap.data import body_points, draw_bodies, load_clips, subject_split

    if path.is_file():
        with np.load(path) as d:
            data = {k: d[k] for k in d.files}
        if all(f"{s}_occ_c" in data for s in SPLITS3):
            return data
        from blsm.leap.data import canonical_occupancy  # a file made before occ_c was kept: completed once

        for s in SPLITS3:
            data[f"{s}_occ_c"] = canonical_occupancy(model, data[f"{s}_subject"], data[f"{s}_xc"])
        log(f"[leap] {path}: canonical occupancy added")
        _write(path, data)
        return data
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
        for k in ("x", "occ", "w", "xc", "wc", "occ_c"):
            out[f"{name}_{k}"] = np.stack([p[k] for p in pts])
        log(f"[leap] {name}: {n} bodies, {cfg.points} points each ({time.time() - t0:.0f} s)")
    out["held_out_clips"] = np.array(sorted(held))
    _write(path, out)
    return out


SPLITS3 = ("train", "unseen_poses", "unseen_subjects")


def _write(path: Path, data: dict[str, np.ndarray]) -> None:
    path.parent.mkdir(parents=True, exist_ok=True)
    tmp = path.with_name(path.name + ".tmp.npz")
    np.savez(tmp, **data)
    tmp.replace(path)


def _batch(data: dict[str, np.ndarray], split: str, rng: np.random.Generator, nb: int, npts: int,
           device: str = "cpu") -> dict[str, torch.Tensor]:
    n, m = data[f"{split}_x"].shape[:2]
    bi = rng.integers(n, size=nb)
    pi = np.stack([rng.choice(m, npts, replace=False) for _ in range(nb)])
    take = lambda k: torch.from_numpy(data[f"{split}_{k}"][bi[:, None], pi])  # noqa: E731
    b = {"B": torch.from_numpy(data[f"{split}_B"][bi]), "x": take("x"), "occ": take("occ"), "w": take("w"),
         "xc": take("xc"), "wc": take("wc"), "occ_c": take("occ_c")}
    return {k: v.to(device) for k, v in b.items()}


def lbs_loss(leap: Leap, b: dict[str, torch.Tensor], kind: str = "ce") -> torch.Tensor:
    """Stage 1: the inverse weights at posed points and the forward weights at canonical points
    against the nearest vertex's (Sec. 4.3): L1 as the paper, or cross-entropy, whose gradient does
    not vanish where the softmax is confidently wrong (it learnt 2-4x faster, docs/leap.md)."""
    body = leap.body(b["B"])
    c_inv, c_fwd = leap.lbs_conditions(body)
    li, lf = leap.inverse_logits(b["x"], b["B"], c_inv), leap.forward_logits(b["xc"], c_fwd)
    if kind == "l1":
        return (li.softmax(-1) - b["w"]).abs().sum(-1).mean() + (lf.softmax(-1) - b["wc"]).abs().sum(-1).mean()
    return -(b["w"] * li.log_softmax(-1)).sum(-1).mean() - (b["wc"] * lf.log_softmax(-1)).sum(-1).mean()


def occupancy_loss(leap: Leap, b: dict[str, torch.Tensor], kind: str = "bce", canonical: int = 0) -> torch.Tensor:
    """Stage 2: Eq. 19, the squared error of the occupancy probability, or the binary
    cross-entropy of its logits (ONet's own loss); the LBS networks fixed. With ``canonical``, as
    many of the batch's canonical points per body are scored too (B.2: their nearest template
    vertex's weights, a cycle distance of 0, the template's occupancy)."""
    can, target = None, b["occ"]
    if canonical:
        can = (b["xc"][:, :canonical], b["wc"][:, :canonical])
        target = torch.cat([b["occ"], b["occ_c"][:, :canonical]], 1)
    logits = leap(b["B"], b["x"], canonical=can, lbs_grad=False)["logits"]
    if kind == "mse":
        return (torch.sigmoid(logits) - target).pow(2).mean()
    return torch.nn.functional.binary_cross_entropy_with_logits(logits, target)


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
    leap = Leap(model, cfg.net).to(cfg.device)
    lbs = [p for n in LBS_PARTS for p in getattr(leap, n).parameters()]
    rest = [p for n, m in leap.named_children() if n not in LBS_PARTS for p in m.parameters()] + [leap.project, leap.project_bias]
    opt_lbs, opt_occ = torch.optim.Adam(lbs, cfg.lr), torch.optim.Adam(rest, cfg.lr)
    step, history = 0, []
    if resume and last.exists():
        ck = torch.load(last, weights_only=False, map_location=cfg.device)
        mine = json.loads(json.dumps(asdict(cfg)))
        # Keys added since the run was made hold their defaults; the device may change.
        theirs = {**json.loads(json.dumps(asdict(LeapTrainConfig()))), **ck["config"], "device": cfg.device}
        longer = mine["occupancy_steps"] > theirs["occupancy_steps"]  # a longer stage 2 extends the run
        if {**theirs, "occupancy_steps": mine["occupancy_steps"] if longer else theirs["occupancy_steps"]} != mine:
            raise ValueError(f"{last}: made with another config; resume it with that one (only a longer occupancy_steps may differ)")
        if longer:
            log(f"[leap] {last}: stage 2 extended from {ck['config']['occupancy_steps']} to {cfg.occupancy_steps} steps")
        leap.load_state_dict(ck["model"])
        opt_lbs.load_state_dict(ck["opt_lbs"])
        opt_occ.load_state_dict(ck["opt_occ"])
        step, history = ck["step"], ck["history"]
    elif cfg.lbs_from:  # stage 1 from another run (the same LBS networks): the ablations share it
        ck = torch.load(cfg.lbs_from, weights_only=False, map_location=cfg.device)
        free = ("occupancy_steps", "occupancy_loss", "canonical_points", "lbs_from", "eval_every", "save_every", "device")  # stage 2's own
        mine, theirs = json.loads(json.dumps(asdict(cfg))), ck["config"]
        differ = [k for k in mine if k not in free and k != "net" and mine[k] != theirs.get(k)]
        differ += [f"net.{k}" for k in mine["net"] if k != "cycle" and mine["net"][k] != theirs["net"].get(k)]
        if differ:
            raise ValueError(f"{cfg.lbs_from}: made with another stage 1 ({', '.join(differ)} differ)")
        if ck["step"] < ck["config"]["lbs_steps"]:
            raise ValueError(f"{cfg.lbs_from}: its stage 1 is not finished ({ck['step']} of {ck['config']['lbs_steps']} steps)")
        own = leap.state_dict()
        lbs_keys = [k for k in own if k.split(".")[0] in LBS_PARTS]
        leap.load_state_dict({**own, **{k: ck["model"][k] for k in lbs_keys}})
        step = cfg.lbs_steps
        history = [h for h in ck["history"] if h["stage"] == "lbs"]
    total = cfg.lbs_steps + cfg.occupancy_steps
    rng = np.random.default_rng([cfg.seed, step])
    t0 = time.time()
    while step < total:
        stage = "lbs" if step < cfg.lbs_steps else "occupancy"
        leap.train()
        if stage == "occupancy":  # the LBS networks fixed: deterministic functions (Sec. 4.3)
            for n in LBS_PARTS:
                getattr(leap, n).eval()
        b = _batch(data, "train", rng, cfg.batch_bodies, cfg.batch_points, cfg.device)
        opt = opt_lbs if stage == "lbs" else opt_occ
        loss = lbs_loss(leap, b, cfg.lbs_loss) if stage == "lbs" else occupancy_loss(leap, b, cfg.occupancy_loss, cfg.canonical_points)
        opt.zero_grad()
        loss.backward()
        opt.step()
        step += 1
        if step % 50 == 0:
            history.append({"step": step, "stage": stage, "loss": loss.item()})
            log(f"[leap] step {step}/{total} {stage} loss {loss.item():.4f} ({(time.time() - t0) / 50:.2f} s/step)")
            t0 = time.time()
        if cfg.eval_every and step % cfg.eval_every == 0:
            point = {"step": step, "stage": stage, "eval": {s: evaluate(leap, data, s) for s in ("unseen_poses", "unseen_subjects")}}
            history.append(point)
            log(f"[leap] step {step} " + ", ".join(f"{s} IoU {r['iou']} L1 {r['l1_inv']}/{r['l1_fwd']}" for s, r in point["eval"].items()))
            t0 = time.time()
        if step % cfg.save_every == 0 or step == total:
            _save(last, leap, opt_lbs, opt_occ, step, history, cfg)
    return last


def _save(path: Path, leap: Leap, opt_lbs: Any, opt_occ: Any, step: int, history: list, cfg: LeapTrainConfig) -> None:
    tmp = path.with_name(path.name + ".tmp")
    torch.save({"model": leap.state_dict(), "opt_lbs": opt_lbs.state_dict(), "opt_occ": opt_occ.state_dict(),
                "step": step, "history": history, "config": json.loads(json.dumps(asdict(cfg)))}, tmp)
    tmp.replace(path)


def load_run(path: str | Path, model: torch.nn.Module) -> tuple[Leap, LeapTrainConfig, dict]:
    """A run's checkpoint ``path`` (its ``last.pt``) loaded on the CPU, wherever it trained: the network
    in eval mode, its config (device ``cpu``) and the checkpoint."""
    from blsm.config import config_from_dict

    ck = torch.load(path, weights_only=False, map_location="cpu")
    cfg = config_from_dict(LeapTrainConfig, {**ck["config"], "device": "cpu"}, str(path))
    leap = Leap(model, cfg.net)
    leap.load_state_dict(ck["model"])
    return leap.eval(), cfg, ck


@torch.no_grad()
def evaluate(leap: Leap, data: dict[str, np.ndarray], split: str, chunk: int = 8) -> dict[str, float]:
    """Mean IoU (percent) over ``split``'s bodies of the predicted occupancy (probability >= 0.5,
    Eq. 14) against the exact one, and the mean L1 of the inverse and forward weights (Table D.2).

    ``iou`` is the paper's protocol: the authors' evaluation scores the uniform points only (a
    volumetric IoU, as ONet's); ``iou_near`` scores the points drawn around the surface
    (N(0, 1 cm) off it), a much harder test of the surface itself; ``iou_all`` both halves."""
    leap.eval()
    dev = next(leap.parameters()).device
    get = lambda k, s: torch.from_numpy(data[f"{split}_{k}"][s : s + chunk]).to(dev)  # noqa: E731
    ious: dict[str, list[float]] = {"iou": [], "iou_near": [], "iou_all": []}
    l1_inv, l1_fwd = [], []
    m = data[f"{split}_x"].shape[1]
    halves = {"iou_near": slice(0, m // 2), "iou": slice(m // 2, m), "iou_all": slice(0, m)}  # near first (sample_points)
    n = len(data[f"{split}_B"])
    for s in range(0, n, chunk):
        B, x = get("B", s), get("x", s)
        r = leap(B, x)
        pred = r["logits"] >= 0.0
        true = get("occ", s) > 0.5
        for key, sl in halves.items():
            inter, union = (pred & true)[:, sl].sum(1).float(), (pred | true)[:, sl].sum(1).float()
            ious[key] += (100.0 * inter / union.clamp(min=1)).tolist()
        l1_inv += (r["w_inv"] - get("w", s)).abs().sum(-1).mean(1).tolist()
        body = leap.body(B)
        wf = leap.forward_weights(get("xc", s), leap.lbs_conditions(body)[1])
        l1_fwd += (wf - get("wc", s)).abs().sum(-1).mean(1).tolist()
    return {**{k: round(float(np.mean(v)), 2) for k, v in ious.items()}, "l1_inv": round(float(np.mean(l1_inv)), 4),
            "l1_fwd": round(float(np.mean(l1_fwd)), 4), "bodies": n}
