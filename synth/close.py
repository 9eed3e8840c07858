"""Close placement (``people.placement: close``): people within reach of each other, touching
without interpenetrating.

The default placement (:func:`synth.people.place_people`) keeps the people's enclosing footprint
discs ``people.gap`` apart: no interpenetration, but never two people closer than their discs. Here
each image draws one **arrangement** by the weights of ``people.close``, and every person after the
first is placed against a partner (the person placed just before, so three make a row):

- ``side``: side by side, facing the partner's way (within ``yaw_deg``);
- ``facing``: facing the partner (the second person; a third stands side by side);
- ``hands``: side by side, the near hands meeting (hand in hand where the arms hang or reach
  sideways; the hands' heights must be within ``HAND_HEIGHT_M``, else the pair stands ``side``);
- ``shoulder``: side by side, the partner's hand on the near shoulder, where a hand of the partner is
  at that shoulder's height (``SHOULDER_BAND_M``; else ``hands``, then ``side``);
- ``seated``: every person seated (:mod:`synth.postures`, prior poses only) side by side on one
  bench: the lower seat raised to the higher (at most ``max_raise``; the person with it, feet off
  the ground), the two box seats then joined into one where their frames agree.

**Resolution.** The new person starts with its anchor (pelvis, hand or shoulder) on the partner's,
and is moved along the arrangement's direction (sideways, or forward for ``facing``) to the nearest
position, found by bisection to ``STEP_M``, where nothing of it is inside anyone placed before and
nothing of theirs inside it: the **exact test** (:mod:`blsm.occupancy`): every vertex of body, hair
and clothes (and samples of a seat's surface) of one is tested against the other's closed body mesh
(and seat box) by its winding number, and the deepest inside vertex's distance to that surface must
be at most ``tolerance``. LEAP's point-based loss (Eq. 20) is the learned alternative for this
search; the exact test is used because it is exact where the loss is learned, and costs what the
benchmark in docs/benchmarks.md says.

The sample's JSON records ``placement``: ``arrangement`` (the image's draw) and, per placed pair,
``people`` [partner, person], ``arrangement`` (what was placed: a fallback says so), ``depth_mm``
(the deepest vertex inside the other after placement) and ``gap_mm`` (the closest vertex-to-surface
distance between the two, 0 where they touch).
"""

from __future__ import annotations

import math
from typing import Any

import numpy as np

from blsm import occupancy
from synth.camera import facing_yaw_deg
from synth.occluders import Occluder, occluder_mesh

ARRANGEMENTS = ("side", "facing", "hands", "shoulder", "seated")
STEP_M = 0.001  # the bisection's last interval, metres
HAND_HEIGHT_M = 0.12  # the near hands of a "hands" pair at most this far apart in height
SHOULDER_BAND_M = (-0.05, 0.15)  # a hand this far above the shoulder joint can rest on the shoulder
SEAT_SPACING_M = 0.03  # the seat's surface sampled this densely for the exact test
GRID_M = 0.04  # the cells of a solid's classification grid (Solid.classify)
MAX_SHIFT_M = 3.0


class Solid:
    """A placed person's (or seat's) geometry for the exact test: ``vertices``/``faces`` the closed
    mesh whose inside counts, ``points`` (N, 3) what is tested against others' meshes.

    The search asks :meth:`exceeds` many times: the mesh's signed distance
    (:class:`blsm.occupancy.MeshSDF`, exact for a closed manifold mesh) is built once, in the frame
    the solid was made in (``offset``: how far it moved since), and a grid of :data:`GRID_M` cells
    over it is classified once by the signed distance ``s(c)`` of each cell's centre (1-Lipschitz,
    so bounds for every point of the cell, ``r`` its half-diagonal): ``s(c) > r``, wholly outside;
    ``s(c) < -(r + tolerance)``, wholly deeper than the tolerance; else the cell's points get the
    signed distance. A point then costs a lookup unless it lies within about ``2 r`` of the surface."""

    def __init__(self, vertices: np.ndarray, faces: np.ndarray, points: np.ndarray, offset: np.ndarray | None = None,
                 cache: dict | None = None) -> None:
        self.vertices = np.asarray(vertices, np.float64)
        self.faces = np.asarray(faces, np.int64)
        self.points = np.asarray(points, np.float64)
        self.offset = np.zeros(3) if offset is None else np.asarray(offset, np.float64)  # moved since made
        self._cache = {} if cache is None else cache  # shared with its moved copies

    def moved(self, d: np.ndarray) -> Solid:
        return Solid(self.vertices + d, self.faces, self.points + d, self.offset + d, self._cache)

    def signed(self, q: np.ndarray) -> np.ndarray:
        """(N,) signed distances of points ``q`` to the mesh (negative inside)."""
        if "sdf" not in self._cache:
            self._cache["sdf"] = occupancy.MeshSDF(self.vertices - self.offset, self.faces)
        return self._cache["sdf"](q - self.offset)[0]

    def classify(self, q: np.ndarray, tol: float) -> np.ndarray:
        """(N,) int8 of points ``q``: 1 outside, -1 deeper inside than ``tol``, 0 to be measured."""
        if self._cache.get("grid", (None,))[0] != tol:
            self._cache["grid"] = (tol, *self._make_grid(tol))
        _, lo, state = self._cache["grid"]
        idx = np.floor((q - self.offset - lo) / GRID_M).astype(np.int64)
        ok = np.all((idx >= 0) & (idx < np.array(state.shape)), axis=1)
        out = np.ones(len(q), np.int8)
        out[ok] = state[idx[ok, 0], idx[ok, 1], idx[ok, 2]]
        return out

    def _make_grid(self, tol: float) -> tuple[np.ndarray, np.ndarray]:
        r = GRID_M * math.sqrt(3.0) / 2.0
        v = self.vertices - self.offset
        lo = v.min(0) - r
        shape = np.ceil((v.max(0) + r - lo) / GRID_M).astype(np.int64)
        axes_ = [lo[k] + GRID_M * (np.arange(shape[k]) + 0.5) for k in range(3)]
        centres = np.stack(np.meshgrid(*axes_, indexing="ij"), -1).reshape(-1, 3)
        sd = self.signed(centres + self.offset).reshape(*shape)
        state = np.zeros(tuple(shape), np.int8)
        state[sd > r] = 1
        state[sd < -(r + tol)] = -1
        return lo, state

    def exceeds(self, q: np.ndarray, tol: float) -> bool:
        """Whether a point of ``q`` is inside the mesh deeper than ``tol``."""
        st = self.classify(q, tol)
        if (st < 0).any():
            return True
        near = q[st == 0]
        return bool(len(near)) and float(self.signed(near).min()) < -tol


def person_solid(p: Any) -> Solid:
    """Person ``p``'s body mesh and the vertices of body, hair and clothes."""
    return Solid(p.vertices, p.faces, p.shell())


def seat_solid(o: Occluder) -> Solid:
    """A box seat's mesh and points on its surface every :data:`SEAT_SPACING_M`."""
    v, f, _ = occluder_mesh(o)
    tri = v[f]
    uniq, inv = np.unique(np.round(v, 9), axis=0, return_inverse=True)  # welded: closed and manifold
    v, f = uniq, inv.reshape(-1)[f]
    pts = [tri.reshape(-1, 3)]
    for t in tri:  # each triangle filled with a grid of barycentric points
        e1, e2 = t[1] - t[0], t[2] - t[0]
        n = max(1, int(max(np.linalg.norm(e1), np.linalg.norm(e2)) / SEAT_SPACING_M))
        a, b = np.meshgrid(np.arange(n + 1) / n, np.arange(n + 1) / n)
        keep = (a + b) <= 1.0
        pts.append(t[0] + a[keep][:, None] * e1 + b[keep][:, None] * e2)
    return Solid(v, f, np.concatenate(pts))


def collides(a: Solid, b: Solid, d: np.ndarray, tol: float) -> bool:
    """Whether ``b`` moved by ``d`` and ``a`` interpenetrate by more than ``tol``: a point of one
    inside the other's mesh deeper than ``tol`` (:meth:`Solid.exceeds`)."""
    return a.exceeds(b.points + d, tol) or b.exceeds(a.points - d, tol)


def depth_and_gap(a: Solid, b: Solid, tol: float = 0.0) -> tuple[float, float]:
    """The deepest point of one inside the other's mesh (0 when none is) and the smallest distance
    from a point of one to the other's surface (0 when they interpenetrate), metres. Points that the
    grids put wholly outside are measured only when no other point is (they are then the nearest)."""
    near, far = [], []
    for src, dst in ((b.points, a), (a.points, b)):
        st = dst.classify(src, tol)
        near.append(dst.signed(src[st != 1]))
        far.append((src[st == 1], dst))
    s = np.concatenate(near)
    if not len(s) or s.min() > 0.0:  # apart: the nearest points may lie in the outside cells
        s = np.concatenate([s] + [dst.signed(q) for q, dst in far])
    return float(max(-s.min(), 0.0)), float(max(s.min(), 0.0))


def turn_to(orient: np.ndarray, yaw_deg: float) -> np.ndarray:
    """The root rotation vector ``orient`` turned about +Y so that the body faces ``yaw_deg``."""
    from scipy.spatial.transform import Rotation

    turn = Rotation.from_euler("y", yaw_deg - facing_yaw_deg(orient), degrees=True)
    return (turn * Rotation.from_rotvec(np.asarray(orient, np.float64))).as_rotvec().astype(np.float32)


def axes(yaw_deg: float) -> tuple[np.ndarray, np.ndarray]:
    """The (x, 0, z) forward and left directions of a body facing ``yaw_deg``."""
    y = math.radians(yaw_deg)
    return np.array([math.sin(y), 0.0, math.cos(y)]), np.array([math.cos(y), 0.0, -math.sin(y)])


def draw_arrangement(weights: dict[str, float], seated_ok: bool, rng: np.random.Generator) -> str:
    """One arrangement by ``weights`` (``seated`` only where ``seated_ok``)."""
    names = [a for a in ARRANGEMENTS if weights[a] > 0 and (a != "seated" or seated_ok)]
    w = np.array([weights[a] for a in names], np.float64)
    return names[int(rng.choice(len(names), p=w / w.sum()))]


def _anchor(p: Any, names: list[str], joint: str) -> np.ndarray:
    return np.asarray(p.joints[names.index(joint)], np.float64)


class ClosePlacer:
    """Places the people of one image close together (module docstring).

    Args:
        cfg: the ``people.close`` section (:class:`synth.config.CloseConfig`).
        bone_names: the model's bones; ``keypoint_names`` its keypoints.
    """

    def __init__(self, cfg: Any, bone_names: list[str], keypoint_names: list[str]) -> None:
        self.cfg, self.names, self.kp_names = cfg, list(bone_names), list(keypoint_names)

    def hand(self, p: Any, side: str) -> np.ndarray:
        tip = np.asarray(p.keypoints[self.kp_names.index(f"hand_tip_{side}")], np.float64)
        return 0.5 * (_anchor(p, self.names, f"wrist_{side}") + tip)

    def plan(self, arrangement: str, k: int, partner: Any, person: Any, side: float) -> tuple[str, np.ndarray, np.ndarray]:
        """Person ``k``'s placement against ``partner``: (the arrangement placed, the start offset
        (3,) of ``person`` (at the origin), the direction (3,) it moves in); ``side`` +1: to the
        partner's left, -1: right."""
        fwd, left = axes(facing_yaw_deg(partner.global_orient))
        near_p = "l" if side > 0 else "r"  # the partner's hand on the person's side
        near_q = "r" if side > 0 else "l"  # the person's hand and shoulder towards the partner
        pelvis = lambda q: _anchor(q, self.names, "pelvis")  # noqa: E731
        if arrangement == "facing" and k == 1:
            return "facing", (pelvis(partner) - pelvis(person)) * [1, 0, 1], fwd
        if arrangement == "shoulder":
            hand = self.hand(partner, near_p)
            shoulder = _anchor(person, self.names, f"shoulder_{near_q}")
            lift = hand[1] - shoulder[1]
            if SHOULDER_BAND_M[0] <= lift <= SHOULDER_BAND_M[1]:
                return "shoulder", (hand - shoulder) * [1, 0, 1], side * left
            arrangement = "hands"
        if arrangement == "hands":
            a, b = self.hand(partner, near_p), self.hand(person, near_q)
            if abs(a[1] - b[1]) <= HAND_HEIGHT_M:
                return "hands", (a - b) * [1, 0, 1], side * left
        placed = "seated" if arrangement == "seated" else "side"
        return placed, (pelvis(partner) - pelvis(person)) * [1, 0, 1], side * left

    def resolve(self, pairs: list[tuple[Solid, Solid]], start: np.ndarray, u: np.ndarray) -> tuple[np.ndarray, int]:
        """The offset ``start + s u`` nearest to ``start`` along ``u`` (s >= 0 where the start
        collides, else s <= 0: brought in until it would) at which no pair ``(placed, moving)`` of
        ``pairs`` collides (:func:`collides` with ``tolerance``), the moving one moved by the
        offset; to :data:`STEP_M`; and the tests it took."""
        tol, tests = self.cfg.tolerance, 0

        def hit(s: float) -> bool:
            nonlocal tests
            tests += 1
            d = start + s * u
            return any(collides(a, m, d, tol) for a, m in pairs)

        if hit(0.0):
            lo, hi = 0.0, 0.05
            while hit(hi):
                lo, hi = hi, hi * 2.0
                if hi > MAX_SHIFT_M:
                    raise RuntimeError("close placement: no free position within 3 m")
        else:
            lo, hi = -0.05, 0.0
            while not hit(lo):
                hi, lo = lo, lo * 2.0
                if lo < -MAX_SHIFT_M:  # never touches: keep the start
                    return start, tests
        while hi - lo > STEP_M:
            mid = 0.5 * (lo + hi)
            if hit(mid):
                lo = mid
            else:
                hi = mid
        return start + hi * u, tests


def merge_seats(a: Occluder, b: Occluder) -> Occluder | None:
    """One bench for two box seats side by side: in ``a``'s frame, across both widths and over the
    depth they share, as high as the lower (the other's people then sit at most 1 cm above it); None where their frames differ by over 10 degrees, their heights by over 1 cm,
    or the shared depth is under 15 cm."""
    from dataclasses import replace

    dyaw = (b.yaw - a.yaw + math.pi) % (2 * math.pi) - math.pi
    if a.kind != "box" or b.kind != "box" or abs(dyaw) > math.radians(10.0) or abs(a.size[1] - b.size[1]) > 0.01:
        return None
    c, s = math.cos(a.yaw), math.sin(a.yaw)
    ax, fw = np.array([c, -s]), np.array([s, c])  # the box's x (width) and z (depth) axes in (x, z)

    def extent(o: Occluder) -> tuple[float, float, float, float]:
        v = occluder_mesh(o)[0][:, [0, 2]] - np.asarray(a.centre)
        u, w = v @ ax, v @ fw
        return u.min(), u.max(), w.min(), w.max()

    ea, eb = extent(a), extent(b)
    u0, u1 = min(ea[0], eb[0]), max(ea[1], eb[1])
    w0, w1 = max(ea[2], eb[2]), min(ea[3], eb[3])
    if w1 - w0 < 0.15:
        return None
    mid = np.asarray(a.centre) + ax * 0.5 * (u0 + u1) + fw * 0.5 * (w0 + w1)
    return replace(a, centre=(float(mid[0]), float(mid[1])), size=(u1 - u0, min(a.size[1], b.size[1]), w1 - w0))


def _pairs(bodies: list[Solid], seats: list[Solid], body: Solid, seat: Solid | None,
           joins: int | None) -> list[tuple[Solid, Solid]]:
    """The (placed, new) pairs a new person's search tests: its body against every placed body and
    seat, its seat (if any) against every placed body and every seat but the one it ``joins``."""
    out = [(a, body) for a in bodies + seats]
    if seat is not None:
        out += [(a, seat) for a in bodies] + [(a, seat) for j, a in enumerate(seats) if j != joins]
    return out


def place_close(maker: Any, n: int, rng: np.random.Generator) -> tuple[list[Any], list[Occluder], dict[str, Any]]:
    """``n`` people drawn by ``maker`` (:class:`synth.sample.SampleMaker`) and placed close
    together (module docstring); returns them (feet on the ground, their ``outline`` set), their
    seats and the sample's ``placement`` record."""
    from dataclasses import replace

    from synth.camera import outline_index
    from synth.postures import seat_under

    cfg = maker.cfg
    cc, tol = cfg.people.close, cfg.people.close.tolerance
    names = list(maker.model.bone_names)
    placer = ClosePlacer(cc, names, list(maker.model.keypoint_names))
    arrangement = draw_arrangement(cc.weights(), cfg.poses.source == "prior", rng)
    side = 1.0 if rng.uniform() < 0.5 else -1.0
    people: list[Any] = []
    bodies: list[Solid] = []  # the placed people's bodies
    seats: list[Occluder] = []  # the seats placed (a bench may carry several people)
    seat_of: list[int | None] = []  # each person's seat
    seat_solids: dict[Occluder, Solid] = {}  # each seat's solid, made once (seats are frozen values)
    pairs = []
    for k in range(n):
        partner = people[-1] if people else None
        yaw = None
        if partner is not None:
            turn = 180.0 if arrangement == "facing" and k == 1 else 0.0
            spread = cc.yaw_deg / 4.0 if arrangement == "seated" else cc.yaw_deg
            yaw = facing_yaw_deg(partner.global_orient) + turn + rng.uniform(-spread, spread)
        p = maker.draw_person(rng, [q.si for q in people], seated=arrangement == "seated", yaw_deg=yaw)
        v = p.shell()
        p.outline = v[outline_index(v)]
        p.move(np.array([0.0, -float(p.vertices[:, 1].min()), 0.0]))  # the body's feet on the floor y = 0
        seat = None
        if p.motion.get("posture") == "seated":
            seat = seat_under(p.shell(), p.joints, names, rng)
            p.motion["seat"] = seat is not None
        if partner is None:
            people.append(p)
            bodies.append(person_solid(p))
            seats += [seat] if seat is not None else []
            seat_of.append(0 if seat is not None else None)
            continue
        way = side if arrangement != "facing" or k == 1 else (1.0 if rng.uniform() < 0.5 else -1.0)
        placed, start, u = placer.plan(arrangement, k, partner, p, way)
        ps = seat_of[-1]
        share = False
        if placed == "seated" and seat is not None and ps is not None:
            dt = seats[ps].size[1] - seat.size[1]  # raise the lower seat's people to the other's height
            if 0.0 < dt <= cc.max_raise:
                p.move(np.array([0.0, dt, 0.0]))
                seat = replace(seat, size=(seat.size[0], seat.size[1] + dt, seat.size[2]))
            elif -cc.max_raise <= dt < 0.0 and k == 1:
                partner.move(np.array([0.0, -dt, 0.0]))
                seats[ps] = replace(seats[ps], size=(seats[ps].size[0], seats[ps].size[1] - dt, seats[ps].size[2]))
                bodies[-1] = bodies[-1].moved(np.array([0.0, -dt, 0.0]))
            dyaw = (seat.yaw - seats[ps].yaw + math.pi) % (2 * math.pi) - math.pi
            share = abs(dyaw) <= math.radians(10.0) and abs(seat.size[1] - seats[ps].size[1]) <= 0.01
        body = person_solid(p)
        own = seat_solid(seat) if seat is not None else None
        for o in seats:
            if o not in seat_solids:
                seat_solids[o] = seat_solid(o)
        placed_seats = [seat_solids[o] for o in seats]
        offset, tests = placer.resolve(_pairs(bodies, placed_seats, body, own, ps if share else None), start, u)
        joined = False
        if share:  # one bench for both where it touches no one
            moved_seat = replace(seat, centre=(seat.centre[0] + float(offset[0]), seat.centre[1] + float(offset[2])))
            bench = merge_seats(seats[ps], moved_seat)
            if bench is not None:
                bs = seat_solid(bench)
                joined = not any(collides(a, bs, np.zeros(3), tol) for a in bodies + [body.moved(offset)])
            if joined:
                seats[ps] = bench
            else:
                offset, more = placer.resolve(_pairs(bodies, placed_seats, body, own, None), start, u)
                tests += more
        p.move(offset)
        people.append(p)
        bodies.append(body.moved(offset))
        if joined:
            seat_of.append(ps)
        elif seat is not None:
            seats.append(replace(seat, centre=(seat.centre[0] + float(offset[0]), seat.centre[1] + float(offset[2]))))
            seat_of.append(len(seats) - 1)
        else:
            seat_of.append(None)
        a, b = bodies[-2], bodies[-1]
        depth, gap = depth_and_gap(a, b, tol)
        pairs.append({"people": [k - 1, k], "arrangement": placed, "tests": tests,
                      "depth_mm": round(1000.0 * depth, 3), "gap_mm": round(1000.0 * gap, 3)})
    shared = [s for s in set(seat_of) if s is not None and seat_of.count(s) > 1]
    return people, seats, {"arrangement": arrangement, "bench": bool(shared), "pairs": pairs}
