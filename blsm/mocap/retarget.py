"""Retargeting motion capture onto the 47 joint-limited BLSM atoms (paper 000 Sec. 3.1, Eq. 6).

For every frame we look for the unconstrained pose ``x`` (47,) and the global orientation that best
reproduce the DIRECTIONS of the source skeleton's segments,

    min_{x, R}  sum_i w_i (1 - <u_i(x, R), d_i>)  +  lambda * |theta(x)|^2,

where ``d_i`` is the unit direction between two source points, ``u_i`` the unit direction between the
corresponding BLSM points of the mean body posed with ``theta = Eq. 6(x)`` and root rotation ``R``, and
the small ridge on the angles settles what the directions leave open (how a bend is shared among the
spine joints, the twist of a straight limb). Because the angles go through Eq. 6 the limits hold by
construction: what the skeleton cannot do shows up in the residuals instead of in the pose.

The mapping from source points to BLSM points is a table per source skeleton
(``blsm/data/mocap_maps/*.yaml``, documented in ``cc_base.yaml``). The solve is batched with Adam:
every frame first starts at the rest pose, its global rotation at the Kabsch alignment of the
pelvis directions; then each frame is warm-started from its neighbouring frames (it takes the
previous or next frame's pose wherever that fits it better, repeated ``hops`` times so a good
solution travels along the clip) and all frames are refined. The root translation is the source
root position scaled by the leg-length ratio (BLSM mean leg / source leg); the clip is then moved
vertically so that the mean body's lowest vertex is on the floor y = 0 in the 5th percentile of
frames.

Residuals per frame: mean and max angle between source and BLSM segment directions (degrees), and
MPJPE (mm) between the BLSM points and the source chain rebuilt with the BLSM segment lengths from
the BLSM root.
"""

from __future__ import annotations

from dataclasses import dataclass
from pathlib import Path
from typing import Any

import numpy as np
import torch
from kornia.geometry.conversions import axis_angle_to_rotation_matrix

from blsm.io import read_yaml
from blsm.joint_limits import angles_from_unconstrained, unconstrained_from_angles
from blsm.kinematics import forward_kinematics, joint_rotations, local_scales
from blsm.mocap.bvh import BvhError, BvhMotion

MAPS_DIR = Path(__file__).resolve().parent.parent / "data" / "mocap_maps"
AXIS_POINT_DISTANCE = 0.05  # metres from the bone head for {bone, axis} points
_AXES = {"+x": (0, 1.0), "-x": (0, -1.0), "+y": (1, 1.0), "-y": (1, -1.0), "+z": (2, 1.0), "-z": (2, -1.0)}


# ------------------------------------------------------------------------------------------------
# Mapping tables


@dataclass(frozen=True)
class Pair:
    """A direction matched between the rigs: BLSM ``a -> b`` against source ``a -> b``."""

    blsm_from: Any
    blsm_to: Any
    source_from: tuple[str, ...]
    source_to: tuple[str, ...]
    weight: float

    @property
    def label(self) -> str:
        def name(p: Any) -> str:
            if isinstance(p, dict):
                return p["label"]
            return p if isinstance(p, str) else "+".join(p)

        return f"{name(self.blsm_from)}->{name(self.blsm_to)}"


@dataclass(frozen=True)
class SkeletonMap:
    """A source-skeleton -> BLSM mapping table (see ``blsm/data/mocap_maps/cc_base.yaml``)."""

    name: str
    description: str
    root_blsm: str
    root_source: str
    leg_blsm: tuple[str, ...]
    leg_source: tuple[str, ...]
    segments: tuple[Pair, ...]
    twist: tuple[Pair, ...]
    orient: tuple[str, ...]
    path: str

    def source_joints(self) -> list[str]:
        names = [self.root_source, *self.leg_source]
        for p in self.segments + self.twist:
            names += [*p.source_from, *p.source_to]
        return list(dict.fromkeys(names))


def _src_point(v: Any, where: str) -> tuple[str, ...]:
    if isinstance(v, str):
        return (v,)
    if isinstance(v, list) and v and all(isinstance(s, str) for s in v):
        return tuple(v)
    raise ValueError(f"{where}: a source point is a joint name or a list of names, got {v!r}")


def _blsm_point(v: Any, where: str) -> Any:
    if isinstance(v, str):
        return v
    if isinstance(v, list) and v and all(isinstance(s, str) for s in v):
        return tuple(v)
    if isinstance(v, dict) and set(v) == {"bone", "axis"} and v["axis"] in _AXES:
        ax, sign = _AXES[v["axis"]]
        off = [0.0, 0.0, 0.0]
        off[ax] = sign * AXIS_POINT_DISTANCE
        return {"bone": str(v["bone"]), "offset": tuple(off), "label": f"{v['bone']}{v['axis']}"}
    if (
        isinstance(v, dict)
        and set(v) == {"bone", "offset"}
        and isinstance(v["offset"], list)
        and len(v["offset"]) == 3
        and all(isinstance(c, (int, float)) for c in v["offset"])
    ):
        return {
            "bone": str(v["bone"]),
            "offset": tuple(float(c) for c in v["offset"]),
            "label": f"{v['bone']}{v['offset']}",
        }
    raise ValueError(
        f"{where}: a BLSM point is a name, a list of names, {{bone, axis}} or {{bone, offset}}, got {v!r}"
    )


def load_map(path: str | Path) -> SkeletonMap:
    """Read and validate a mapping table (YAML)."""
    path = Path(path)
    doc = read_yaml(path, "mapping table")
    if not isinstance(doc, dict):
        raise ValueError(f"{path}: a mapping table is a YAML mapping")
    for key in ("name", "root", "leg", "segments"):
        if key not in doc:
            raise ValueError(f"{path}: missing key {key!r}")

    def pairs(key: str) -> tuple[Pair, ...]:
        out = []
        for i, row in enumerate(doc.get(key) or []):
            where = f"{path}: {key}[{i}]"
            if not isinstance(row, list) or len(row) != 5:
                raise ValueError(f"{where}: expected [blsm_from, blsm_to, source_from, source_to, weight]")
            w = row[4]
            if not isinstance(w, (int, float)) or not w > 0:
                raise ValueError(f"{where}: weight must be a positive number, got {w!r}")
            out.append(
                Pair(
                    _blsm_point(row[0], where),
                    _blsm_point(row[1], where),
                    _src_point(row[2], where),
                    _src_point(row[3], where),
                    float(w),
                )
            )
        return tuple(out)

    segs = pairs("segments")
    root = doc["root"]
    if not isinstance(root, dict) or set(root) != {"blsm", "source"}:
        raise ValueError(f"{path}: root must be {{blsm: NAME, source: NAME}}")
    # The segments must form a tree over BLSM points rooted at root.blsm (for the MPJPE chain).
    seen = {root["blsm"]}
    for i, s in enumerate(segs):
        if not (isinstance(s.blsm_from, str) and isinstance(s.blsm_to, str)):
            raise ValueError(f"{path}: segments[{i}]: chain points must be single names")
        if s.blsm_from not in seen:
            raise ValueError(
                f"{path}: segments[{i}] starts at {s.blsm_from!r}, not yet reached from the root"
            )
        if s.blsm_to in seen:
            raise ValueError(f"{path}: segments[{i}] reaches {s.blsm_to!r} a second time")
        seen.add(s.blsm_to)
    twist = pairs("twist")
    labels = [p.label for p in segs + twist]
    orient = doc.get("orient") or []
    if len(orient) < 2 or any(o not in labels for o in orient):
        raise ValueError(
            f"{path}: orient must name at least two non-parallel pairs of segments/twist "
            f"(labels like 'pelvis->neck'), got {orient!r}"
        )
    leg = doc["leg"]
    if (
        not isinstance(leg, dict)
        or len(leg.get("blsm", [])) < 2
        or len(leg.get("source", [])) != len(leg.get("blsm", []))
    ):
        raise ValueError(f"{path}: leg must list the same number (>= 2) of blsm and source joints")
    return SkeletonMap(
        name=str(doc["name"]),
        description=str(doc.get("description", "")),
        root_blsm=str(root["blsm"]),
        root_source=str(root["source"]),
        leg_blsm=tuple(leg["blsm"]),
        leg_source=tuple(leg["source"]),
        segments=segs,
        twist=twist,
        orient=tuple(orient),
        path=str(path),
    )


def available_maps() -> dict[str, Path]:
    """The packaged mapping tables by name."""
    return {p.stem: p for p in sorted(MAPS_DIR.glob("*.yaml"))}


def select_map(motion: BvhMotion, name: str | None = None) -> SkeletonMap:
    """The mapping table for a clip: the named one, or the first whose source joints all exist.

    Raises:
        BvhError: ``"<file>:<line>: ..."`` naming the first required joint the skeleton lacks (line
            of the ROOT declaration).
    """
    maps = available_maps()
    if name is not None:
        if Path(name).suffix in (".yaml", ".yml"):
            candidates = [load_map(name)]
        elif name in maps:
            candidates = [load_map(maps[name])]
        else:
            raise ValueError(f"unknown mapping table {name!r} (packaged: {sorted(maps)})")
    else:
        candidates = [load_map(p) for p in maps.values()]
    have = set(motion.skeleton.names)
    best: tuple[int, SkeletonMap, list[str]] | None = None
    for m in candidates:
        missing = [j for j in m.source_joints() if j not in have]
        if not missing:
            return m
        if best is None or len(missing) < best[0]:
            best = (len(missing), m, missing)
    assert best is not None
    line = motion.skeleton.lines[0] if motion.skeleton.lines else 1
    raise BvhError(
        f"{motion.path}:{line}: unknown skeleton: no joint {best[2][0]!r} required by mapping "
        f"table {best[1].name!r} ({best[0]} of its joints missing)"
    )


# ------------------------------------------------------------------------------------------------
# Points of the two rigs


class _BlsmPoints:
    """Evaluates named BLSM points (joints, keypoints, bone-axis points) from the FK transforms."""

    def __init__(self, model: Any, specs: list[Any]) -> None:
        self.model = model
        bone_names = model.bone_names
        kp_names = model.keypoint_names
        base: list[tuple[str, Any]] = []  # ("joint", j) | ("vertex", (idx, w)) | ("axis", (j, p))
        index: dict[str, int] = {}

        def add(key: str, item: tuple[str, Any]) -> int:
            if key not in index:
                index[key] = len(base)
                base.append(item)
            return index[key]

        def one(name: str) -> int:
            if name in bone_names:
                return add(name, ("joint", bone_names.index(name)))
            if name in kp_names:
                k = kp_names.index(name)
                j = int(model.keypoint_joint[k])
                if j >= 0:
                    return add(name, ("joint", j))
                return add(name, ("kp", k))
            raise ValueError(f"unknown BLSM point {name!r} (not a bone or keypoint of the model)")

        rows: list[list[int]] = []
        for s in specs:
            if isinstance(s, str):
                rows.append([one(s)])
            elif isinstance(s, tuple):
                rows.append([one(n) for n in s])
            else:
                if s["bone"] not in bone_names:
                    raise ValueError(f"unknown bone {s['bone']!r} in an axis point")
                j = bone_names.index(s["bone"])
                off = torch.tensor(s["offset"], dtype=model.heads.dtype)
                p = model.heads[j] + model.frames[j] @ off
                rows.append([add(s["label"], ("axis", (j, p)))])
        self.base = base
        mix = torch.zeros(len(specs), len(base), dtype=model.template.dtype)
        for i, r in enumerate(rows):
            mix[i, r] = 1.0 / len(r)
        self.mix = mix
        self.joint_idx = [i for i, (k, _) in enumerate(base) if k == "joint"]
        self.joint_src = torch.tensor([v for k, v in base if k == "joint"], dtype=torch.long)
        self.kp_idx = [i for i, (k, _) in enumerate(base) if k == "kp"]
        kps = [v for k, v in base if k == "kp"]
        self.kp_vertices = model.keypoint_vertices[kps]  # (Kk, n)
        self.kp_weights = model.keypoint_weights[kps]  # (Kk, n)
        self.axis_idx = [i for i, (k, _) in enumerate(base) if k == "axis"]
        self.axis_bone = torch.tensor([v[0] for k, v in base if k == "axis"], dtype=torch.long)
        self.axis_rest = (
            torch.stack([v[1] for k, v in base if k == "axis"])
            if self.axis_idx
            else model.heads.new_zeros(0, 3)
        )
        flat = self.kp_vertices.reshape(-1)
        self.kp_template = model.template[flat]  # (Kk*n, 3) mean body, zero shape
        self.kp_skin = model.weights[flat]  # (Kk*n, J)

    def __call__(self, linear: torch.Tensor, offset: torch.Tensor, joints: torch.Tensor) -> torch.Tensor:
        """(B, P, 3) points for the specs, from FK ``linear`` (B,J,3,3), ``offset`` (B,J,3), joints."""
        batch = joints.shape[0]
        pts = joints.new_zeros(batch, len(self.base), 3)
        if self.joint_idx:
            pts[:, self.joint_idx] = joints[:, self.joint_src]
        if self.kp_idx:
            # LBS (Eq. 12) of the keypoints' own vertices only.
            lin = torch.einsum("vj,bjcd->bvcd", self.kp_skin, linear)
            off = torch.einsum("vj,bjc->bvc", self.kp_skin, offset)
            v = (lin @ self.kp_template[..., None])[..., 0] + off
            v = v.reshape(batch, *self.kp_vertices.shape, 3)
            pts[:, self.kp_idx] = (v * self.kp_weights[..., None]).sum(2)
        if self.axis_idx:
            lin = linear[:, self.axis_bone]
            pts[:, self.axis_idx] = (lin @ self.axis_rest[..., None])[..., 0] + offset[:, self.axis_bone]
        return torch.einsum("pq,bqc->bpc", self.mix.to(pts.dtype), pts)


def _source_mix(names: list[str], specs: list[tuple[str, ...]]) -> np.ndarray:
    mix = np.zeros((len(specs), len(names)))
    for i, s in enumerate(specs):
        for n in s:
            mix[i, names.index(n)] += 1.0 / len(s)
    return mix


def _unit(v: torch.Tensor) -> tuple[torch.Tensor, torch.Tensor]:
    n = v.norm(dim=-1, keepdim=True)
    return v / n.clamp(min=1e-9), n[..., 0]


def _matrix_to_rotvec(m: torch.Tensor) -> torch.Tensor:
    """(B, 3, 3) -> (B, 3) axis-angle, re-orthonormalised first (float32 products drift)."""
    from scipy.spatial.transform import Rotation

    u, _, vt = np.linalg.svd(m.double().numpy())
    return torch.as_tensor(Rotation.from_matrix(u @ vt).as_rotvec(), dtype=m.dtype)


def _blocks(n: int, size: int) -> list[slice]:
    return [slice(i, min(i + size, n)) for i in range(0, n, size)]


def _kabsch(src: torch.Tensor, dst: torch.Tensor, w: torch.Tensor) -> torch.Tensor:
    """Rotations R (B, 3, 3) minimising sum_i w_i |R src_i - dst_b,i|^2 for unit directions."""
    m = torch.einsum("i,bic,id->bcd", w, dst, src)  # sum w dst src^T
    u, _, vt = torch.linalg.svd(m)
    d = torch.sign(torch.linalg.det(u @ vt))
    fix = torch.ones_like(u[:, 0])
    fix[:, 2] = d
    return u @ torch.diag_embed(fix) @ vt


# ------------------------------------------------------------------------------------------------
# The solve


@dataclass
class Retargeted:
    """A retargeted clip (mean BLSM body) and its per-frame residuals.

    Attributes:
        pose: (T, 47) unconstrained atom values x of Eq. 6.
        angles: (T, 47) the atom angles, radians.
        global_orient: (T, 3) axis-angle root rotation.
        transl: (T, 3) translation in metres (``BLSM(transl=...)``; see the module docstring).
        dir_err_mean_deg, dir_err_max_deg: (T,) segment direction error over ``segments``.
        mpjpe_mm: (T,) MPJPE against the source chain rebuilt with BLSM segment lengths.
        leg_ratio: BLSM mean leg length / source leg length.
        segment_labels: the residual segments, in order.
        segment_err_deg: (T, S) per-segment direction error.
    """

    pose: np.ndarray
    angles: np.ndarray
    global_orient: np.ndarray
    transl: np.ndarray
    dir_err_mean_deg: np.ndarray
    dir_err_max_deg: np.ndarray
    mpjpe_mm: np.ndarray
    leg_ratio: float
    segment_labels: list[str]
    segment_err_deg: np.ndarray
    source_points: np.ndarray  # (T, S + 1, 3) rescaled source chain (root first), metres


def retarget(
    motion: BvhMotion,
    model: Any,
    skeleton_map: SkeletonMap | None = None,
    *,
    block: int = 512,
    first_iters: int = 300,
    sweeps: int = 1,
    hops: int = 8,
    iters: int = 100,
    lr: float = 0.05,
    ridge: float = 1e-4,
) -> Retargeted:
    """Retarget a BVH clip onto the model's mean body (see the module docstring).

    Args:
        motion: the clip (:func:`blsm.mocap.bvh.read_bvh`), already at the wanted frame rate.
        model: a :class:`blsm.BLSM` (float32 or float64, CPU).
        skeleton_map: the mapping table; None picks one with :func:`select_map`.
        block: frames solved together (memory bound; frames are independent problems).
        first_iters: Adam iterations of the first solve, every frame starting at rest.
        sweeps: rounds of warm starts from neighbouring frames, each followed by ``iters``
            iterations; ``hops`` is how many frames a better solution may travel per round.
        lr: Adam step size (cosine-decayed to 5 % within each solve).
        ridge: weight lambda of the ridge on the angles (radians^2).

    Returns:
        :class:`Retargeted`.
    """
    smap = skeleton_map if skeleton_map is not None else select_map(motion)
    names = motion.skeleton.names
    missing = [j for j in smap.source_joints() if j not in names]
    if missing:
        raise BvhError(
            f"{motion.path}:{motion.skeleton.lines[0]}: no joint {missing[0]!r} required by "
            f"mapping table {smap.name!r}"
        )
    _, src_pos = motion.global_transforms()  # (T, Js, 3) metres
    pairs = list(smap.segments) + list(smap.twist)
    src_dir = _source_directions(motion, smap, pairs, src_pos, model.template.dtype)
    if model.bone_names.index(smap.root_blsm) != 0:
        raise ValueError(f"{smap.path}: root.blsm must be the model's root bone {model.bone_names[0]!r}")
    fit = _DirectionFit(model, smap, pairs, src_dir, ridge=ridge, lr=lr, block=block)
    pose, g_out = fit.solve_clip(first_iters, sweeps, hops, iters)
    with torch.no_grad():
        pts, theta = fit.pose_points(pose, g_out)
    seg_err, mpjpe, source_points = _residuals(smap, pts, src_dir, len(pairs))
    transl, ratio = _root_translation(model, smap, names, src_pos, pose, g_out)
    rotvec = _matrix_to_rotvec(g_out).double().numpy()
    return Retargeted(
        pose=pose.double().numpy(),
        angles=theta.double().numpy(),
        global_orient=rotvec,
        transl=transl,
        dir_err_mean_deg=seg_err.mean(1),
        dir_err_max_deg=seg_err.max(1),
        mpjpe_mm=mpjpe.double().numpy(),
        leg_ratio=ratio,
        segment_labels=[s.label for s in smap.segments],
        segment_err_deg=seg_err,
        source_points=source_points.double().numpy(),
    )


def _source_directions(motion: BvhMotion, smap: SkeletonMap, pairs: list[Pair], src_pos: np.ndarray,
                       dtype: torch.dtype) -> torch.Tensor:
    """(T, P, 3) unit directions of the mapped source segments and twist pairs in every frame."""
    n_pair = len(pairs)
    smix = _source_mix(motion.skeleton.names, [p.source_from for p in pairs] + [p.source_to for p in pairs])
    sp = np.einsum("pj,tjc->tpc", smix, src_pos)
    src_dir_np = sp[:, n_pair:] - sp[:, :n_pair]
    src_len = np.linalg.norm(src_dir_np, axis=-1)
    if (src_len < 1e-6).any():
        t, i = np.argwhere(src_len < 1e-6)[0]
        raise BvhError(
            f"{motion.path}:{motion.first_frame_line + int(t)}: source points of {pairs[i].label} "
            f"coincide in frame {t + 1}; the mapping table {smap.name!r} does not fit this skeleton"
        )
    return torch.as_tensor(src_dir_np / src_len[..., None], dtype=dtype)


class _DirectionFit:
    """The per-frame problem: the mean body's segment and twist directions against the source's.

    The loss of a frame is ``sum_p w_p (1 - u_p . d_p) + ridge * |theta|^2`` over the pairs p, with
    u the BLSM directions and d the source's; the root rotation is a Kabsch start (on the
    ``orient`` pairs) times a free axis-angle correction.
    """

    def __init__(self, model: Any, smap: SkeletonMap, pairs: list[Pair], src_dir: torch.Tensor, *,
                 ridge: float, lr: float, block: int) -> None:
        dtype = model.template.dtype
        self.model, self.src_dir, self.ridge, self.lr, self.block = model, src_dir, ridge, lr, block
        self.n_pair = len(pairs)
        self.points = _BlsmPoints(model, [p.blsm_from for p in pairs] + [p.blsm_to for p in pairs])
        self.weights = torch.tensor([p.weight for p in pairs], dtype=dtype)
        self.scales = local_scales(model.bone_mean[None], model.parents_t)
        # Rest directions of the BLSM points, for the Kabsch initialisation of the root rotation.
        limits = model.dof_limits
        self.x_rest = unconstrained_from_angles(torch.zeros(1, len(limits), dtype=dtype), limits)
        rest_pts, _ = self.pose_points(self.x_rest, torch.eye(3, dtype=dtype)[None])
        rest_dir, _ = _unit(rest_pts[0, self.n_pair :] - rest_pts[0, : self.n_pair])
        orient_w = torch.tensor([1.0 if p.label in smap.orient else 0.0 for p in pairs], dtype=dtype)
        self.r0_all = _kabsch(rest_dir, src_dir, orient_w)  # (T, 3, 3)

    def pose_points(self, x: torch.Tensor, g_rot: torch.Tensor) -> tuple[torch.Tensor, torch.Tensor]:
        """(B, 2P, 3) BLSM points and (B, 47) angles of the unconstrained atoms ``x`` (B, 47), root
        rotation ``g_rot`` (B, 3, 3)."""
        m = self.model
        theta = angles_from_unconstrained(x, m.dof_limits)
        rot = joint_rotations(theta, m.dof_slots, m.dof_axis, m.dof_sign)
        lin, off, joints = forward_kinematics(
            rot, self.scales.expand(x.shape[0], -1), m.heads, m.frames, m.parents, g_rot
        )
        return self.points(lin, off, joints), theta

    def frame_loss(self, x: torch.Tensor, g_rot: torch.Tensor, target: torch.Tensor) -> torch.Tensor:
        pts, theta = self.pose_points(x, g_rot)
        u, _ = _unit(pts[:, self.n_pair :] - pts[:, : self.n_pair])
        return (1 - (u * target).sum(-1)) @ self.weights + self.ridge * (theta**2).sum(-1)

    def solve(
        self, x0: torch.Tensor, r0: torch.Tensor, sl: slice, steps: int
    ) -> tuple[torch.Tensor, torch.Tensor]:
        """Adam on the frames ``sl`` (cosine-decayed rate), from atoms ``x0`` and corrections ``r0``."""
        x = x0.clone().requires_grad_(True)
        r = r0.clone().requires_grad_(True)
        base, target = self.r0_all[sl], self.src_dir[sl]
        opt = torch.optim.Adam([x, r], lr=self.lr)
        sched = torch.optim.lr_scheduler.CosineAnnealingLR(opt, steps, eta_min=self.lr * 0.05)
        for _ in range(steps):
            opt.zero_grad(set_to_none=True)
            self.frame_loss(x, base @ axis_angle_to_rotation_matrix(r), target).sum().backward()
            opt.step()
            sched.step()
        return x.detach(), r.detach()

    def losses(self, x: torch.Tensor, r: torch.Tensor) -> torch.Tensor:
        """(T,) the loss of every frame."""
        with torch.no_grad():
            return torch.cat([
                self.frame_loss(x[s], self.r0_all[s] @ axis_angle_to_rotation_matrix(r[s]), self.src_dir[s])
                for s in _blocks(len(x), self.block)
            ])

    def solve_clip(
        self, first_iters: int, sweeps: int, hops: int, iters: int
    ) -> tuple[torch.Tensor, torch.Tensor]:
        """Atoms (T, 47) and root rotations (T, 3, 3) of every frame."""
        n_frames = self.src_dir.shape[0]
        # 1. Every frame from the rest pose, in blocks of frames solved together.
        x_all = self.x_rest.expand(n_frames, -1).clone()
        r_all = torch.zeros(n_frames, 3, dtype=x_all.dtype)
        for s in _blocks(n_frames, self.block):
            x_all[s], r_all[s] = self.solve(x_all[s], r_all[s], s, first_iters)
        # 2. Warm starts from the neighbouring frames: a frame takes its neighbour's pose where that
        #    fits it better (repeated, so a good solution travels along the clip), then all refine.
        for _ in range(sweeps):
            cur = self.losses(x_all, r_all)
            for _ in range(hops):
                for shift in (1, -1):
                    cand = torch.roll(x_all, shift, 0)
                    lc = self.losses(cand, r_all)
                    lc[0 if shift == 1 else -1] = float("inf")
                    better = lc < cur - 1e-7
                    x_all[better], cur[better] = cand[better], lc[better]
            for s in _blocks(n_frames, self.block):
                x_all[s], r_all[s] = self.solve(x_all[s], r_all[s], s, iters)
        return x_all, self.r0_all @ axis_angle_to_rotation_matrix(r_all)


def _residuals(smap: SkeletonMap, pts: torch.Tensor, src_dir: torch.Tensor,
               n_pair: int) -> tuple[np.ndarray, torch.Tensor, torch.Tensor]:
    """Per-segment direction errors (T, S) in degrees, MPJPE (T,) in mm against the source chain
    rebuilt from the BLSM root with the BLSM segment lengths, and that chain (T, S + 1, 3)."""
    n_seg = len(smap.segments)
    blsm_from, blsm_to = pts[:, :n_seg], pts[:, n_pair : n_pair + n_seg]
    u, seg_len = _unit(blsm_to - blsm_from)
    cos = (u * src_dir[:, :n_seg]).sum(-1).clamp(-1, 1)
    seg_err = torch.rad2deg(torch.acos(cos)).numpy()
    chain = {smap.root_blsm: blsm_from[:, 0]}  # load_map checked: segment 0 starts at the root
    for i, s in enumerate(smap.segments):
        chain[s.blsm_to] = chain[s.blsm_from] + seg_len[:, i, None] * src_dir[:, i]
    rebuilt = torch.stack([chain[s.blsm_to] for s in smap.segments], 1)
    mpjpe = (rebuilt - blsm_to).norm(dim=-1).mean(-1) * 1000.0
    return seg_err, mpjpe, torch.cat([blsm_from[:, :1], rebuilt], 1)


def _root_translation(
    model: Any, smap: SkeletonMap, names: list[str], src_pos: np.ndarray, pose: torch.Tensor,
    g_out: torch.Tensor,
) -> tuple[np.ndarray, float]:
    """Root translation (T, 3) in metres and the leg-length ratio BLSM / source.

    The source root scaled by the leg-length ratio; then the clip is moved vertically so that the
    mean body's lowest vertex is on the floor y = 0 in the 5th percentile of frames (robust to jumps
    and to source floors that are not at y = 0).
    """
    heads = model.heads
    li = [names.index(n) for n in smap.leg_source]
    src_leg = np.linalg.norm(np.diff(src_pos[:, li], axis=1), axis=-1).sum(1).mean()
    bi = [model.bone_names.index(n) for n in smap.leg_blsm]
    blsm_leg = float((heads[bi[1:]] - heads[bi[:-1]]).norm(dim=-1).sum())
    ratio = blsm_leg / float(src_leg)
    root_src = src_pos[:, names.index(smap.root_source)]
    transl = ratio * root_src - heads[0].double().numpy()
    lowest = []
    with torch.no_grad():
        for s in _blocks(len(pose), 256):
            out = model(pose=pose[s], global_orient=_matrix_to_rotvec(g_out[s]))
            lowest.append(out.vertices[..., 1].amin(-1).double().numpy())
    low = np.concatenate(lowest) + transl[:, 1]
    transl[:, 1] -= np.percentile(low, 5)
    return transl, ratio
