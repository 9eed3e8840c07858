"""LEAP on BLSM's bones: learned inverse and forward LBS, the cycle distance and a canonical
occupancy network (Mihajlovic et al., CVPR 2021; ``../shared/papers/004_...``).

A body is given by BLSM's ``K`` = 20 bone transforms. The **local** transforms ``B_k`` (3 x 4,
Eq. 8) map the canonical space (the model's template space: the mean skeleton at rest) to the
posed space; for BLSM they are the skinning transforms ``A_j`` of its Eq. 12, which also carry the
bones' scales. The **world** transforms ``G_k`` (Eq. 7) and the rest joints follow from them and
the skeleton (:func:`bone_inputs`).

- Encoders (Sec. 4.1): the **structure** encoder, a tree of per-bone two-layer perceptrons fed the
  bone's relative rotation, joint, length and its parent's code (Eqs. 16-17); the **shape**
  encoder, which inverts the model: the bone coefficients that best explain the bones' scales
  (the analogue of Eqs. 5-6), the canonical vertices they give and those vertices posed (Eq. 15),
  each encoded by a PointNet; the **pose** encoder, the root's location in every bone's frame
  (Eq. 18). Their concatenation ``z`` is projected per bone to ``z_k`` (Sec. 4, ``Pi_k``).
- LBS networks (Sec. 4.2): the inverse network predicts weights ``w_x`` for a posed point, the
  point's canonical position is ``(sum_k w_x[k] B_k)^-1 x`` (Eq. 10) and its code
  ``z_x = sum_k w_x[k] z_k`` (Eq. 11); the forward network predicts weights for the canonical
  point, which map it back (Eq. 12); the **cycle distance** ``d_x = sum_k |w_x[k] - w_fwd[k]|``
  (Eq. 13).
- The occupancy network ``O`` (ONet with conditional batch normalisation, Fig. B.2) takes the
  canonical point conditioned on ``(z_x, d_x)`` and gives the occupancy probability (Eq. 14).

Sizes follow the supplement (B.1-B.5) scaled for 2 CPU cores by :class:`LeapConfig`; the paper's are
the ``paper`` preset. Two input choices differ from the paper, both switchable and measured in
docs/leap.md: every point input is given with sin/cos features (``fourier``), and the inverse LBS
network reads the point in every bone's frame (``bone_frames``). Without them the networks learnt
the nearest-vertex weights several times slower on 2 cores.
"""

from __future__ import annotations

from dataclasses import dataclass

import torch
from torch import nn

from blsm.kinematics import rest_joints


@dataclass(frozen=True)
class LeapConfig:
    """Network sizes. ``paper``: the supplement's (PointNet 128 / 100, structure codes 6, bone codes
    12, ONet and LBS widths 256 with 5 blocks)."""

    shape_dim: int = 64  # each PointNet's output (the supplement: 128 for the shape feature)
    lbs_feature: int = 48  # each PointNet feature of the LBS networks (the supplement: 100)
    pose_feature: int = 32  # the inverse LBS network's pose and joints feature (the supplement: 80)
    bone_code: int = 6  # structure encoder per bone (B.1)
    point_code: int = 12  # z_k (B.3)
    width: int = 128  # ONet and LBS hidden width (the supplement: 256)
    blocks: int = 3  # ONet and LBS residual blocks (the supplement: 5)
    mesh_points: int = 512  # template vertices the PointNets see (a fixed subset)
    cycle: bool = True  # the cycle-distance feature (Eq. 13; off: the Fig. 4 ablation)
    fourier: int = 4  # octaves of sin/cos features of every point input (0: raw coordinates, as the paper)
    bone_frames: bool = True  # the inverse LBS network reads x in every bone's frame, B_k^-1 x (else x)

    @staticmethod
    def paper() -> LeapConfig:
        return LeapConfig(shape_dim=128, lbs_feature=100, pose_feature=80, width=256, blocks=5)


def encode(x: torch.Tensor, octaves: int) -> torch.Tensor:
    """``x`` (..., C) with ``sin`` and ``cos`` of ``2^i pi x``, ``i < octaves`` (..., C (1 + 2 octaves)):
    a ReLU network on raw coordinates learns the skinning weights' sharp borders slowly (measured in
    docs/leap.md); these features are NeRF's positional encoding."""
    if octaves == 0:
        return x
    a = x[..., None] * (torch.pi * 2.0 ** torch.arange(octaves, dtype=x.dtype, device=x.device))
    return torch.cat([x, a.sin().flatten(-2), a.cos().flatten(-2)], -1)


class PointNet(nn.Module):
    """A point set to a fixed-size feature (Fig. B.1): shared per-point layers with residual blocks,
    max-pooled, then linear."""

    def __init__(self, out: int, hidden: int = 64) -> None:
        super().__init__()
        self.inp = nn.Linear(3, 2 * hidden)
        self.blocks = nn.ModuleList([nn.Linear(2 * hidden, hidden) for _ in range(3)])
        self.out = nn.Linear(hidden, out)
        self.act = nn.ReLU()

    def forward(self, pts: torch.Tensor) -> torch.Tensor:  # (B, N, 3) -> (B, out)
        h = self.blocks[0](self.act(self.inp(pts)))
        for blk in self.blocks[1:]:  # each block sees its input and the pooled feature
            pooled = h.max(1, keepdim=True)[0].expand_as(h)
            h = blk(self.act(torch.cat([h, pooled], -1)))
        return self.out(self.act(h.max(1)[0]))


class StructureEncoder(nn.Module):
    """Eqs. 16-17: per bone, ``m_k(vec(r_k) + j_k + l_k [+ v_parent])`` in kinematic order; the root's
    code from one linear layer of all rotations and joints (B.1)."""

    def __init__(self, parents: list[int], code: int) -> None:
        super().__init__()
        self.parents, k = list(parents), len(parents)
        self.root = nn.Linear(k * 12, code)
        self.mlps = nn.ModuleList(
            [nn.Sequential(nn.Linear(13 + code, 13 + code), nn.ReLU(), nn.Linear(13 + code, code), nn.ReLU())
             for _ in range(k)])  # fmt: skip

    def forward(self, rel_rot: torch.Tensor, joints: torch.Tensor, lengths: torch.Tensor) -> torch.Tensor:
        """``rel_rot`` (B, K, 3, 3) rotations relative to the parent, ``joints`` (B, K, 3) rest
        joints, ``lengths`` (B, K); returns (B, K * code)."""
        b = rel_rot.shape[0]
        codes: list[torch.Tensor | None] = [None] * len(self.parents)
        feats = torch.cat([rel_rot.reshape(b, -1, 9), joints, lengths[..., None]], -1)  # (B, K, 13)
        for k, p in enumerate(self.parents):  # parents come before their children
            parent = self.root(torch.cat([rel_rot.reshape(b, -1), joints.reshape(b, -1)], -1)) if p < 0 else codes[p]
            codes[k] = self.mlps[k](torch.cat([feats[:, k], parent], -1))
        return torch.cat(codes, -1)


class ResBlock(nn.Module):
    """A residual block, with conditional batch normalisation where ``cond`` is given (Fig. B.2)."""

    def __init__(self, width: int, cond: int = 0) -> None:
        super().__init__()
        self.fc0, self.fc1 = nn.Linear(width, width), nn.Linear(width, width)
        self.cond = cond
        if cond:
            self.bn0, self.bn1 = nn.BatchNorm1d(width, affine=False), nn.BatchNorm1d(width, affine=False)
            self.film0, self.film1 = nn.Linear(cond, 2 * width), nn.Linear(cond, 2 * width)
        self.act = nn.ReLU()

    def _cbn(self, h: torch.Tensor, bn: nn.Module, film: nn.Module, c: torch.Tensor) -> torch.Tensor:
        gamma, beta = film(c).chunk(2, -1)
        return (1.0 + gamma) * bn(h) + beta

    def forward(self, h: torch.Tensor, c: torch.Tensor | None = None) -> torch.Tensor:
        x = h
        if self.cond:
            h = self._cbn(h, self.bn0, self.film0, c)
        h = self.fc0(self.act(h))
        if self.cond:
            h = self._cbn(h, self.bn1, self.film1, c)
        return x + self.fc1(self.act(h))


class ConditionedMLP(nn.Module):
    """``f(x | c)``: the point and a per-body condition, residual blocks, one output layer (the LBS
    networks of Fig. B.3 with ``cond_points=False``; ONet with per-point conditions)."""

    def __init__(self, cond: int, out: int, width: int, blocks: int, cbn: bool, inp: int = 3) -> None:
        super().__init__()
        self.cbn = cbn
        self.inp = nn.Linear(inp if cbn else inp + cond, width)
        self.blocks = nn.ModuleList([ResBlock(width, cond if cbn else 0) for _ in range(blocks)])
        self.out = nn.Linear(width, out)
        self.act = nn.ReLU()

    def forward(self, x: torch.Tensor, c: torch.Tensor) -> torch.Tensor:
        """``x`` (N, inp) points' features, ``c`` (N, cond) their conditions; (N, out)."""
        h = self.inp(x if self.cbn else torch.cat([x, c], -1))
        for blk in self.blocks:
            h = blk(h, c if self.cbn else None)
        return self.out(self.act(h))


def blend_inverse(w: torch.Tensor, B: torch.Tensor, x: torch.Tensor) -> torch.Tensor:
    """Eq. 10: ``(sum_k w[k] B_k)^-1 x`` for points ``x`` (N, 3), weights ``w`` (N, K) and their
    bodies' transforms ``B`` (N, K, 3, 4)."""
    m = torch.einsum("nk,nkij->nij", w, B)
    return torch.linalg.solve(m[..., :3], (x - m[..., 3])[..., None])[..., 0]


def blend_forward(w: torch.Tensor, B: torch.Tensor, xc: torch.Tensor) -> torch.Tensor:
    """Eq. 12 (and Eq. 9 for one point): ``(sum_k w[k] B_k) x_c``."""
    m = torch.einsum("nk,nkij->nij", w, B)
    return torch.einsum("nij,nj->ni", m[..., :3], xc) + m[..., 3]


class Leap(nn.Module):
    """LEAP for a BLSM model (module docstring).

    Args:
        model: the :class:`blsm.model.BLSM` whose bones, template, bone correctives and skinning
            weights define the encoders' inverse model and the canonical space.
        cfg: network sizes.
    """

    def __init__(self, model: nn.Module, cfg: LeapConfig | None = None) -> None:
        super().__init__()
        cfg = cfg or LeapConfig()
        self.cfg = cfg
        k = model.num_joints
        self.parents = list(model.parents)
        g = torch.Generator().manual_seed(0)
        sub = torch.randperm(model.num_vertices, generator=g)[: cfg.mesh_points].sort()[0]
        self.register_buffer("sub", sub, persistent=False)
        self.register_buffer("template", model.template[sub].clone(), persistent=False)
        self.register_buffer("correctives", model.bone_correctives[:, sub].clone(), persistent=False)
        self.register_buffer("weights", model.weights[sub].clone(), persistent=False)
        self.register_buffer("bone_mean", model.bone_mean.clone(), persistent=False)
        self.register_buffer("bone_basis", model.bone_basis.clone(), persistent=False)
        self.register_buffer("heads", model.heads.clone(), persistent=False)
        self.register_buffer("chain", model.chain.clone(), persistent=False)
        self.register_buffer("parents_t", model.parents_t.clone(), persistent=False)
        # Encoders (Sec. 4.1) and the per-bone projections Pi_k (B.3).
        self.structure = StructureEncoder(self.parents, cfg.bone_code)
        self.shape_rest, self.shape_posed = PointNet(cfg.shape_dim), PointNet(cfg.shape_dim)
        zdim = k * cfg.bone_code + 2 * cfg.shape_dim + k * 3
        self.project = nn.Parameter(torch.randn(k, zdim, cfg.point_code) * zdim**-0.5)
        self.project_bias = nn.Parameter(torch.zeros(k, cfg.point_code))
        # LBS networks (Sec. 4.2, B.5), each with encoders of its own (trained apart, Sec. 4.3).
        self.fwd_rest, self.fwd_posed = PointNet(cfg.lbs_feature), PointNet(cfg.lbs_feature)
        self.inv_rest, self.inv_posed = PointNet(cfg.lbs_feature), PointNet(cfg.lbs_feature)
        self.inv_pose = nn.Linear(k * 12, cfg.pose_feature)
        enc = 1 + 2 * cfg.fourier  # features per coordinate (encode)
        inv_in = 3 * enc * (k if cfg.bone_frames else 1)
        self.inverse = ConditionedMLP(2 * cfg.lbs_feature + cfg.pose_feature, k, cfg.width, cfg.blocks, cbn=False, inp=inv_in)
        self.forward_lbs = ConditionedMLP(2 * cfg.lbs_feature, k, cfg.width, cfg.blocks, cbn=False, inp=3 * enc)
        # The occupancy network (Fig. B.2): conditioned on z_x and d_x.
        self.onet = ConditionedMLP(cfg.point_code + 1, 1, cfg.width, cfg.blocks, cbn=True, inp=3 * enc)

    # -- the body's features -------------------------------------------------------------------

    def body(self, B: torch.Tensor) -> dict[str, torch.Tensor]:
        """What the encoders read of bodies given by their local transforms ``B`` (n, K, 3, 4):
        bone scales and world rotations (``L_k = b_k R_k``), relative rotations, the person's
        rest joints and bone lengths, the estimated bone coefficients and canonical and posed
        vertices (the shape encoder's inversion), the root's place in every bone's frame (Eq. 18)."""
        lin = B[..., :3]
        b = torch.linalg.det(lin).clamp(min=1e-9) ** (1.0 / 3.0)  # (n, K) global bone scales
        R = lin / b[..., None, None]
        par = self.parents_t.clamp(min=0)
        rel = torch.where((self.parents_t < 0)[None, :, None, None], R, R[:, par].transpose(-1, -2) @ R)
        joints = rest_joints(b, self.heads, self.parents_t, self.chain)  # as BLSM's forward
        lengths = (joints - joints[:, par]).norm(dim=-1) * (self.parents_t >= 0)
        # Eq. 4 inverted (Eqs. 5-6 for BLSM): the bone coefficients whose scales are closest.
        coeffs = torch.linalg.lstsq(self.bone_basis.T.expand(len(b), -1, -1), (b - self.bone_mean)[..., None]).solution[..., 0]
        rest = self.template + torch.einsum("bk,kvc->bvc", coeffs, self.correctives)  # Eq. 15 without shape
        posed = torch.einsum("vk,bkij,bvj->bvi", self.weights, lin, rest) + torch.einsum("vk,bki->bvi", self.weights, B[..., 3])
        root = B[:, 0, :, :3] @ self.heads[0] + B[:, 0, :, 3]  # the posed root joint, t_0
        local = torch.linalg.solve(lin, (root[:, None] - B[..., 3])[..., None])[..., 0]  # B_k^-1 t_0 (Eq. 18)
        return {"R": R, "rel": rel, "joints": joints, "lengths": lengths, "rest": rest, "posed": posed, "root_local": local}

    def codes(self, body: dict[str, torch.Tensor]) -> torch.Tensor:
        """(n, K, point_code) the per-bone codes ``z_k = Pi_k(z)``, ``z`` the three encoders' features."""
        z = torch.cat([self.structure(body["rel"], body["joints"], body["lengths"]),
                       self.shape_rest(body["rest"]), self.shape_posed(body["posed"]),
                       body["root_local"].flatten(1)], -1)  # fmt: skip
        return torch.einsum("nz,kzc->nkc", z, self.project) + self.project_bias

    def lbs_conditions(self, body: dict[str, torch.Tensor]) -> tuple[torch.Tensor, torch.Tensor]:
        """(c_inv, c_fwd) of B.5: the LBS networks' PointNet features (and the inverse one's pose)."""
        c_fwd = torch.cat([self.fwd_rest(body["rest"]), self.fwd_posed(body["posed"])], -1)
        pose = torch.cat([body["R"].flatten(1), body["joints"].flatten(1)], -1)
        c_inv = torch.cat([self.inv_rest(body["rest"]), self.inv_posed(body["posed"]), self.inv_pose(pose)], -1)
        return c_inv, c_fwd

    # -- points ----------------------------------------------------------------------------------

    def inverse_logits(self, x: torch.Tensor, B: torch.Tensor, c_inv: torch.Tensor) -> torch.Tensor:
        """(n, N, K) the inverse LBS network's logits for posed points ``x`` (n, N, 3) of bodies ``B``
        (n, K, 3, 4); with ``cfg.bone_frames`` it reads ``B_k^-1 x`` for every bone ``k``, the
        canonical point each bone alone would give (Eq. 10 with one-hot weights)."""
        n, m, _ = x.shape
        if self.cfg.bone_frames:
            lin, t = B[:, None, :, :, :3], B[:, None, :, :, 3]
            x = torch.linalg.solve(lin, (x[:, :, None] - t)[..., None])[..., 0]  # (n, N, K, 3)
        f = encode(x, self.cfg.fourier).reshape(n * m, -1)
        c = c_inv[:, None].expand(-1, m, -1).reshape(n * m, -1)
        return self.inverse(f, c).reshape(n, m, -1)

    def inverse_weights(self, x: torch.Tensor, B: torch.Tensor, c_inv: torch.Tensor) -> torch.Tensor:
        """(n, N, K) ``w_x``: the inverse LBS network's weights for posed points ``x`` (n, N, 3)."""
        return self.inverse_logits(x, B, c_inv).softmax(-1)

    def forward_logits(self, xc: torch.Tensor, c_fwd: torch.Tensor) -> torch.Tensor:
        """(n, N, K) the forward LBS network's logits for canonical points ``xc`` (n, N, 3)."""
        n, m, _ = xc.shape
        c = c_fwd[:, None].expand(-1, m, -1).reshape(n * m, -1)
        return self.forward_lbs(encode(xc.reshape(-1, 3), self.cfg.fourier), c).reshape(n, m, -1)

    def forward_weights(self, xc: torch.Tensor, c_fwd: torch.Tensor) -> torch.Tensor:
        """(n, N, K) the forward LBS network's weights for canonical points ``xc`` (n, N, 3)."""
        return self.forward_logits(xc, c_fwd).softmax(-1)

    def forward(self, B: torch.Tensor, x: torch.Tensor, weights: torch.Tensor | None = None,
                canonical: tuple[torch.Tensor, torch.Tensor] | None = None, lbs_grad: bool = True) -> dict[str, torch.Tensor]:
        """Occupancy logits of posed points ``x`` (n, N, 3) for bodies ``B`` (n, K, 3, 4).

        ``weights`` (n, N, K): given weights instead of the inverse network's (the deterministic
        nearest-vertex weights of Sec. 6.1's ablation). ``canonical``: points drawn in the canonical
        space itself, ``(xc (n, M, 3), w (n, M, K))`` with their nearest vertices' weights and a
        cycle distance of 0, scored in the same ONet pass (B.2's occupancy training); their logits
        follow the posed points'. ``lbs_grad=False``: no gradient through the LBS networks (fixed
        in stage 2; keep it for gradients w.r.t. the points, Eq. 20). Returns ``logits`` (n, N [+ M]),
        the inverse and forward weights, the canonical points ``xc`` (Eq. 10), the cycle's points
        (Eq. 12) and the cycle distance ``d`` (Eq. 13; zeros when ``cfg.cycle`` is off)."""
        n, m, _ = x.shape
        body = self.body(B)
        with torch.set_grad_enabled(lbs_grad and torch.is_grad_enabled()):
            c_inv, c_fwd = self.lbs_conditions(body)
            w = self.inverse_weights(x, B, c_inv) if weights is None else weights
            Bp = B[:, None].expand(-1, m, -1, -1, -1).reshape(n * m, *B.shape[1:])
            xc = blend_inverse(w.reshape(n * m, -1), Bp, x.reshape(-1, 3)).reshape(n, m, 3)  # Eq. 10
            if self.cfg.cycle:
                wf = self.forward_weights(xc, c_fwd)
                cyc = blend_forward(wf.reshape(n * m, -1), Bp, xc.reshape(-1, 3)).reshape(n, m, 3)  # Eq. 12
                d = (w - wf).abs().sum(-1, keepdim=True)  # Eq. 13
            else:
                wf, cyc, d = w, x, torch.zeros_like(x[..., :1])
        pts, ws, ds = xc, w, d
        if canonical is not None:
            pts, ws = torch.cat([xc, canonical[0]], 1), torch.cat([w, canonical[1]], 1)
            ds = torch.cat([d, torch.zeros_like(canonical[0][..., :1])], 1)
        zx = torch.einsum("nmk,nkc->nmc", ws, self.codes(body))  # Eq. 11
        total = pts.shape[1]
        cond = torch.cat([zx, ds], -1).reshape(n * total, -1)
        logits = self.onet(encode(pts.reshape(-1, 3), self.cfg.fourier), cond).reshape(n, total)
        return {"logits": logits, "w_inv": w, "w_fwd": wf, "xc": xc, "x_cycle": cyc, "d": d[..., 0]}
