"""What a plan says about the scene, read in each grasp's frame: pure torch, from the plan alone.

Why this exists: the stacking outcome is close to a simple function of the scene *seen from each
grasp* (which neighbour sits how close to the fingers, how the cubes are turned relative to the
grasp, how far the tower's target is from its base) -- gradient boosting on such numbers built from
the planner's estimates reaches 0.84 balanced accuracy where every learned model that reads the
plan as 120 x 16 joint-space numbers stays near 0.73 (``experiments/outcome_predictability.py``).
The plan carries those numbers: at the first step of a "grasp" run the joint targets put the
tool-centre point (TCP) on the block the planner believes is there, with the fingers at the grasp
yaw; at the first step of a "release" run, on the place target. Forward kinematics recovers them,
so the grasp-frame description needs no privileged input and no mujoco.

Forward kinematics: the Franka Panda's documented modified (Craig) Denavit-Hartenberg parameters,
flange 0.107 m beyond joint 7, hand turned -45 deg about the flange axis, TCP 0.1034 m further
along it (the sim's ``tcp`` site); the robot base at the world origin, as in the sim.
``tests/firp/test_plan_geometry.py`` checks it against MuJoCo's kinematics of the sim's Panda.

The description (:func:`plan_geometry`), for up to ``max_picks`` pick-and-place pairs in plan
order -- pick ``k`` = the k-th grasp run and the release run after it:

* per pick ``k``: grasp point and release point (x, y, z) and the release's rise over the first
  release (how high on the tower it goes);
* in pick ``k``'s grasp frame (origin at the grasp point, x along the fingers' closing axis): every
  other pick's grasp point (offset, absolute offset, distance, relative yaw as cos/sin of 4x the
  angle -- a cube looks the same after a quarter turn -- and whether that block is still there,
  i.e. picked later) and every release point (same numbers, and whether it is already occupied,
  i.e. released earlier);
* in pick ``k``'s release frame: the first release point's offset (a tower's misalignment).

``description="clearance"`` (or ``"both"``, :class:`~firp.model.config.GeometryConfig`) describes
instead (or also) how near the hand comes to the other blocks -- what decides robosuite's
three-cube stacking: an open finger or the hand's body that comes down on a neighbouring cube or on
the tower pushes it away. There, the success rate climbs from 30% for plans whose finger lands a
centimetre into a neighbour to 99% for plans that clear every neighbour by 2 cm
(``experiments/grasp_clearance.py``). The grasp-frame numbers hold the neighbours' offsets too, but a
learner must then find the edge of a turned square beside a finger's footprint from some 640 plans;
the clearance hands it that edge. Per pick, six signed floor-plane distances (negative: overlap) of
three parts of the Franka hand -- the fingertip pads, the fingers, the hand's lowest slab
(:data:`FINGER_PAD`, :data:`FINGER_BODY`, :data:`HAND_SLAB_HALF`) -- to the nearest square block of
half-size ``object_half``, each block turned as its grasp:

* at the grasp, fingers open as the plan opened them, among the tower (a block under the first
  release point) and the blocks picked later (still on the table);
* at the release, fingers closed on a block of half-size ``object_half``, among the blocks picked later.

Clipped to :data:`CLEARANCE_FAR` (a block farther away does not matter, and no block reads as far,
not as touching).

``description="clearance_and_heights"`` adds, per pick, the heights at which the grasp closes and the
release opens and the release's rise (:data:`PICK_HEIGHTS`): on robosuite's stacking, gradient
boosting on the 150 grasp-frame numbers and the clearance draws nearly all it uses beyond the clearance
from these few columns, and a small MLP given the clearance and the heights alone comes within 0.01 of
it, where given all 168 columns it loses 0.07 (``experiments/grasp_clearance.py``).

``description="sized_clearance_and_heights"`` holds the same 27 numbers, with the clearance measured to
blocks of the sizes the plan shows (:func:`block_halves`) instead of one ``object_half`` for all: robosuite's
three-cube stacking has a 5 cm cube beside two 4 cm ones, and a neighbour 5 mm wider on each side than
assumed is the margin that decides there. The plan shows the tower's blocks (each release's height over its
grasp is the tower's height under it), not the last block stacked; with the true sizes of all three, a
64-unit MLP comes to 0.90 where the one-size clearance gives it 0.88 (``experiments/grasp_clearance.py``).

``description="table_sized_clearance_and_heights"`` shows the last block too: the same 27 numbers, each
picked block's size read from how high over the table its grasp closes (:func:`grasp_halves`: the centre of
the block, or :data:`HIGH_GRASP_BELOW_TOP` under its top face, for robosuite's planner), the base's from the
first release. It needs where the table lies under the robot's base (:data:`TABLE_Z`, robosuite's stacking)
-- a fact of the task, as the arm's kinematics are -- and reads the decoded sizes to 0.6 mm on average.

Missing picks (a shorter plan) are zeros with a presence flag, so one width serves any plan.
"""

from __future__ import annotations

import math

import torch
from torch import Tensor, nn

from firp.core.contract import CATEGORY_INDEX, N_CATEGORIES
from firp.model.config import PLAN_DESCRIPTIONS, GeometryConfig
from firp.model.ops import plan_categories

__all__ = [
    "CLEARANCE_FAR",
    "DEFAULT_MAX_PICKS",
    "HAND_PARTS",
    "PANDA_DH",
    "PICK_HEIGHTS",
    "PlanGeometry",
    "TABLE_Z",
    "block_halves",
    "build_plan_geometry",
    "clearance_dim",
    "geometry_dim",
    "grasp_halves",
    "hand_clearance",
    "panda_tcp_pose",
    "pick_events",
    "plan_context",
    "plan_geometry",
    "standardise",
    "tcp_yaw",
]

#: Modified DH parameters (a_{i-1}, d_i, alpha_{i-1}) of the Panda's seven joints (Franka's docs).
PANDA_DH: tuple[tuple[float, float, float], ...] = (
    (0.0, 0.333, 0.0),
    (0.0, 0.0, -math.pi / 2),
    (0.0, 0.316, math.pi / 2),
    (0.0825, 0.0, math.pi / 2),
    (-0.0825, 0.384, -math.pi / 2),
    (0.0, 0.0, math.pi / 2),
    (0.088, 0.0, math.pi / 2),
)
FLANGE_D = 0.107  # joint 7 -> flange, along z
HAND_YAW = -math.pi / 4  # the hand is mounted turned by -45 deg about the flange axis
TCP_OFFSET = 0.1034  # flange -> between the fingertips, along z (the sim's tcp site)
DEFAULT_MAX_PICKS = 3
#: The Franka hand's parts in a grasp frame (x along the fingers' closing axis, from the inner face of a
#: finger outwards; y across it): (depth along x, half-width along y), measured on robosuite's Panda
#: collision meshes with the fingers open: the fingertip pads' lowest 2 cm, the fingers' widest part, and
#: the hand's lowest 2 cm slab, 20.8 cm long (centred on the TCP) and 3.8 cm wide.
FINGER_PAD = (0.0144, 0.0088)
FINGER_BODY = (0.0265, 0.0105)
HAND_SLAB_HALF = (0.104, 0.019)
HAND_PARTS = ("pad", "finger", "hand")
#: ``description="clearance_and_heights"``'s numbers per pick beside the clearance: the grasp's and the
#: release's TCP height and the release's rise over the first release (how high on the tower it goes).
PICK_HEIGHTS = ("grasp_z", "release_z", "rise")
#: The descriptions that hold each pick's heights (:data:`PICK_HEIGHTS`) beside the clearance.
WITH_HEIGHTS = ("clearance_and_heights", "sized_clearance_and_heights", "table_sized_clearance_and_heights")
#: the descriptions whose clearance is measured to blocks of the sizes the plan shows
SIZED = ("sized_clearance_and_heights", "table_sized_clearance_and_heights")
#: robosuite's stacking: the table's top in the Panda base's frame (z, metres), measured on 2000 episodes'
#: plans as each grasp's height less the grasped cube's centre or high-grasp height: -0.1191 +- 0.0010
#: (the spread is the planner's 1 mm height estimate error)
TABLE_Z = -0.1191
#: robosuite's planner closes a "high" grasp this far under the block's top face, a centre grasp at its centre
HIGH_GRASP_BELOW_TOP = 0.008
#: robosuite's stacking: the smallest and largest cube half-sizes (two 2 cm cubes and a 2.5 cm one)
CUBE_HALF_RANGE = (0.02, 0.025)
#: Clearances are clipped to this many metres: an absent block, or one farther away, reads as far.
CLEARANCE_FAR = 0.1
#: Half-size of the square the clearance assumes at a neighbour (the tasks' cubes: 0.02-0.025 m).
DEFAULT_OBJECT_HALF = 0.02
#: Bound on a standardised value. Training plans stay within +/-5 (the shipped stacking bundle: 4.3
#: over all 640 episodes); a plan unlike any seen (e.g. a third pick where training had two) must not
#: feed the head values in the thousands through a column that was constant in training.
STANDARD_CLIP = 10.0
_QUARTER_TURN_HARMONIC = 4.0  # a cube is the same after a quarter turn: compare yaws through 4 * angle


def _dh(a: float, d: float, alpha: float, theta: Tensor) -> Tensor:
    """Modified DH transform ``RotX(alpha) TransX(a) RotZ(theta) TransZ(d)``: ``theta`` (...) -> (..., 4, 4)."""
    c, s = torch.cos(theta), torch.sin(theta)
    ca, sa = math.cos(alpha), math.sin(alpha)
    zero, one = torch.zeros_like(theta), torch.ones_like(theta)
    rows = [
        [c, -s, zero, zero + a],
        [s * ca, c * ca, zero - sa, zero - d * sa],
        [s * sa, c * sa, zero + ca, zero + d * ca],
        [zero, zero, zero, one],
    ]
    return torch.stack([torch.stack(r, dim=-1) for r in rows], dim=-2)


def _fixed(theta: float, d: float, like: Tensor) -> Tensor:
    """``RotZ(theta) TransZ(d)`` as a (4, 4) tensor of ``like``'s dtype/device."""
    return _dh(0.0, d, 0.0, like.new_tensor(theta))


def panda_tcp_pose(joints: Tensor) -> tuple[Tensor, Tensor]:
    """Arm joint angles ``(..., 7)`` -> TCP position ``(..., 3)`` and rotation ``(..., 3, 3)`` (world frame)."""
    if joints.shape[-1] != 7:
        raise ValueError(f"panda_tcp_pose needs the 7 arm joints in the last dimension, got shape {tuple(joints.shape)}")
    T = None
    for i, (a, d, alpha) in enumerate(PANDA_DH):
        step = _dh(a, d, alpha, joints[..., i])
        T = step if T is None else T @ step
    T = T @ _fixed(0.0, FLANGE_D, joints) @ _fixed(HAND_YAW, TCP_OFFSET, joints)
    return T[..., :3, 3], T[..., :3, :3]


def tcp_yaw(rotation: Tensor) -> Tensor:
    """Yaw of the fingers' closing axis (the TCP frame's y axis) of a top-down grasp: ``(..., 3, 3)`` -> ``(...)``.

    The same convention as the planner's ``rotation_yaw``: ``atan2(R[1, 1], R[0, 1])``.
    """
    return torch.atan2(rotation[..., 1, 1], rotation[..., 0, 1])


def _run_starts(is_category: Tensor, mask: Tensor | None) -> Tensor:
    """``(B, T)`` bool -> ``(B, T)`` bool: the first step of every run of True (masked steps are False)."""
    if mask is not None:
        is_category = is_category & mask.bool()
    before = torch.nn.functional.pad(is_category[:, :-1], (1, 0), value=False)
    return is_category & ~before


def _gather_first(starts: Tensor, count: int) -> tuple[Tensor, Tensor]:
    """Indices of the first ``count`` True entries per row of ``starts`` (B, T): ``(B, count)`` long
    (0 where absent) and a ``(B, count)`` presence flag."""
    B, T = starts.shape
    rank = torch.cumsum(starts.long(), dim=1) - 1  # (B, T) 0-based rank of each start
    index = torch.zeros(B, count, dtype=torch.long, device=starts.device)
    present = torch.zeros(B, count, dtype=torch.bool, device=starts.device)
    steps = torch.arange(T, device=starts.device).expand(B, T)
    for k in range(count):
        hit = starts & (rank == k)  # (B, T), at most one True per row
        present[:, k] = hit.any(dim=1)
        index[:, k] = torch.where(hit, steps, torch.zeros_like(steps)).sum(dim=1)
    return index, present


def pick_events(actions: Tensor, mask: Tensor | None = None, max_picks: int = DEFAULT_MAX_PICKS) -> dict[str, Tensor]:
    """TCP poses at each pick's grasp and release, read from a raw (unnormalised) plan.

    ``actions`` (B, T, 16): one-hot categories then joint targets in radians. Pick ``k`` is the
    ``k``-th run of "grasp" and the first "release" run that starts after it. Returns ``grasp_pos``,
    ``release_pos`` (B, P, 3), ``grasp_yaw``, ``release_yaw`` (B, P) and ``present`` (B, P) bool
    (a grasp with a release after it); absent picks are zeros.
    """
    if actions.ndim != 3 or actions.shape[-1] < N_CATEGORIES + 7:
        raise ValueError(f"actions must be (B, T, >= {N_CATEGORIES + 7}), got shape {tuple(actions.shape)}")
    categories = plan_categories(actions)  # (B, T)
    grasp_starts = _run_starts(categories == CATEGORY_INDEX["grasp"], mask)
    release_starts = _run_starts(categories == CATEGORY_INDEX["release"], mask)
    grasp_idx, has_grasp = _gather_first(grasp_starts, max_picks)  # (B, P)
    # the release of pick k: the first release start after its grasp
    B, T = release_starts.shape
    steps = torch.arange(T, device=actions.device)
    after = steps.view(1, 1, T) > grasp_idx.unsqueeze(-1)  # (B, P, T)
    candidates = release_starts.unsqueeze(1) & after
    has_release = candidates.any(dim=-1)
    release_idx = torch.where(candidates, steps.view(1, 1, T), torch.full_like(after, T, dtype=torch.long)).min(dim=-1).values
    release_idx = torch.where(has_release, release_idx, torch.zeros_like(release_idx))
    present = has_grasp & has_release  # (B, P)
    rows = torch.arange(B, device=actions.device).unsqueeze(-1)  # (B, 1)
    joints = actions[..., N_CATEGORIES:N_CATEGORIES + 7]  # (B, T, 7)
    at_events = joints[rows, torch.cat([grasp_idx, release_idx], dim=1)]  # (B, 2P, 7): FK only where needed
    pos, rot = panda_tcp_pose(at_events)  # (B, 2P, 3), (B, 2P, 3, 3)
    yaw = tcp_yaw(rot)  # (B, 2P)
    keep = present.to(actions.dtype)
    P = max_picks
    # how far each finger stands from the TCP as the hand comes down on the block: the finger target of the
    # step before the grasp run (the run itself closes them)
    before_grasp = (grasp_idx - 1).clamp(min=0)
    grasp_open = actions[rows, before_grasp, N_CATEGORIES + 7].clamp(min=0.0)  # (B, P)
    return {
        "grasp_pos": pos[:, :P] * keep.unsqueeze(-1),
        "release_pos": pos[:, P:] * keep.unsqueeze(-1),
        "grasp_yaw": yaw[:, :P] * keep,
        "release_yaw": yaw[:, P:] * keep,
        "grasp_open": grasp_open * keep,
        "present": present,
    }


def _in_frame(origin: Tensor, yaw: Tensor, points: Tensor) -> Tensor:
    """xy of ``points`` (B, N, >=2) in the frame at ``origin`` (B, >=2) turned by ``yaw`` (B,) -> (B, N, 2)."""
    c, s = torch.cos(yaw).unsqueeze(-1), torch.sin(yaw).unsqueeze(-1)  # (B, 1)
    d = points[..., :2] - origin[:, None, :2]  # (B, N, 2)
    return torch.stack([c * d[..., 0] + s * d[..., 1], -s * d[..., 0] + c * d[..., 1]], dim=-1)


def _relation(rel: Tensor, dyaw: Tensor, flag: Tensor) -> Tensor:
    """Per other point: offset (2), |offset| (2), distance, cos/sin(4 dyaw), flag -> (B, N, 8)."""
    dist = torch.sqrt((rel ** 2).sum(-1) + 1e-12)
    h = _QUARTER_TURN_HARMONIC * dyaw
    return torch.cat([rel, rel.abs(), dist.unsqueeze(-1), torch.cos(h).unsqueeze(-1), torch.sin(h).unsqueeze(-1),
                      flag.unsqueeze(-1)], dim=-1)


def _corners(centre: Tensor, half: Tensor, yaw: Tensor) -> Tensor:
    """Rectangles: centres (..., 2), half extents (..., 2) along their own axes, turned by yaw (...) -> (..., 4, 2)."""
    signs = centre.new_tensor([[-1.0, -1.0], [1.0, -1.0], [1.0, 1.0], [-1.0, 1.0]])  # counter-clockwise
    local = signs * half.unsqueeze(-2)  # (..., 4, 2)
    c, s = torch.cos(yaw).unsqueeze(-1), torch.sin(yaw).unsqueeze(-1)  # (..., 1)
    turned = torch.stack([c * local[..., 0] - s * local[..., 1], s * local[..., 0] + c * local[..., 1]], dim=-1)
    return centre.unsqueeze(-2) + turned


def _points_to_edges(points: Tensor, polygon: Tensor) -> Tensor:
    """Smallest distance from any of ``points`` (..., 4, 2) to any edge of ``polygon`` (..., 4, 2) -> (...)."""
    a, b = polygon, polygon.roll(-1, dims=-2)  # (..., 4, 2) edge ends
    ab = (b - a).unsqueeze(-3)  # (..., 1, 4, 2)
    ap = points.unsqueeze(-2) - a.unsqueeze(-3)  # (..., 4 points, 4 edges, 2)
    t = ((ap * ab).sum(-1) / (ab * ab).sum(-1).clamp(min=1e-18)).clamp(0.0, 1.0)
    return (ap - t.unsqueeze(-1) * ab).norm(dim=-1).flatten(-2).min(dim=-1).values


def _signed_distance(p: Tensor, q: Tensor) -> Tensor:
    """Convex quadrilaterals ``p``, ``q`` (..., 4, 2) -> their distance (...), negative by the depth they overlap.

    Separating axes: along each edge normal of either, the gap between the two projections; all gaps
    <= 0 means overlap, and the largest is minus the smallest push that parts them. Apart, the true
    distance is the nearest vertex-to-edge distance."""
    edges = torch.cat([p.roll(-1, dims=-2) - p, q.roll(-1, dims=-2) - q], dim=-2)  # (..., 8, 2)
    normals = torch.stack([-edges[..., 1], edges[..., 0]], dim=-1)
    normals = normals / normals.norm(dim=-1, keepdim=True).clamp(min=1e-18)
    on_p = torch.einsum("...vd,...nd->...nv", p, normals)  # (..., 8 axes, 4 vertices)
    on_q = torch.einsum("...vd,...nd->...nv", q, normals)
    gaps = torch.maximum(on_q.min(-1).values - on_p.max(-1).values, on_p.min(-1).values - on_q.max(-1).values)
    largest_gap = gaps.max(dim=-1).values  # (...)
    apart = torch.minimum(_points_to_edges(p, q), _points_to_edges(q, p))
    return torch.where(largest_gap > 0, apart, largest_gap)


def hand_clearance(neighbours: Tensor, neighbour_yaw: Tensor, finger_offset: Tensor, object_half: float | Tensor
                   ) -> Tensor:
    """Clearance of the Franka hand's parts to square blocks, in the hand's frame (TCP at the origin, fingers
    closing along x).

    ``neighbours`` (B, N, 2) block centres and ``neighbour_yaw`` (B, N) their turn relative to the hand;
    ``finger_offset`` (B,) how far each finger's inner face stands from the TCP; ``object_half`` the blocks'
    half-size, one for all or (B, N) one per block. Returns (B, N, 3): the signed
    floor-plane distance of the fingertip pads, the fingers (the nearer of the two each) and the hand's lowest
    slab to each block, clipped to :data:`CLEARANCE_FAR`."""
    B, N = neighbour_yaw.shape
    half = torch.as_tensor(object_half, dtype=neighbours.dtype, device=neighbours.device).expand(B, N)
    squares = _corners(neighbours, half.unsqueeze(-1).expand(B, N, 2), neighbour_yaw)  # (B, N, 4, 2)
    zero = neighbours.new_zeros(B)
    parts = []
    for depth, half_width in (FINGER_PAD, FINGER_BODY):
        nearer = None
        for side in (1.0, -1.0):
            centre = torch.stack([side * (finger_offset + depth / 2), zero], dim=-1)  # (B, 2)
            half = neighbours.new_tensor([depth / 2, half_width]).expand(B, 2)
            finger = _corners(centre, half, zero).unsqueeze(1)  # (B, 1, 4, 2)
            d = _signed_distance(finger.expand(B, N, 4, 2), squares)  # (B, N)
            nearer = d if nearer is None else torch.minimum(nearer, d)
        parts.append(nearer)
    slab = _corners(torch.stack([zero, zero], dim=-1), neighbours.new_tensor(HAND_SLAB_HALF).expand(B, 2), zero)
    parts.append(_signed_distance(slab.unsqueeze(1).expand(B, N, 4, 2), squares))
    return torch.stack(parts, dim=-1).clamp(max=CLEARANCE_FAR)  # (B, N, 3)


def clearance_dim(max_picks: int = DEFAULT_MAX_PICKS) -> int:
    """Columns of the clearance: per pick, each hand part's nearest block at the grasp and at the release."""
    return max_picks * 2 * len(HAND_PARTS)


def geometry_dim(max_picks: int = DEFAULT_MAX_PICKS, description: str = "grasp_frame") -> int:
    """Width of :func:`plan_geometry`'s output."""
    _check_description(description)
    P = max_picks
    per_pick = 1 + 3 + 3 + 1 + 8 * (P - 1) + 8 * P + 2  # presence, grasp xyz, release xyz, rise, grasps, releases, tower
    grasp_frame = P * per_pick if description in ("grasp_frame", "both") else 0
    clearance = clearance_dim(P) if description != "grasp_frame" else 0
    heights = P * len(PICK_HEIGHTS) if description in WITH_HEIGHTS else 0
    return grasp_frame + clearance + heights


def _check_description(description: str) -> None:
    if description not in PLAN_DESCRIPTIONS:
        raise ValueError(f"description: {description!r} is none of {', '.join(PLAN_DESCRIPTIONS)}")


def block_halves(ev: dict[str, Tensor], object_half: float) -> Tensor:
    """Each block's half-size as the plan shows it (B, 1 + P): the tower's base, then each pick's block.

    The hand holds a block at the same height above the block's bottom when it grasps it (on the table)
    and when it releases it (on the tower), so ``release z - grasp z`` of pick ``k`` is the tower's height
    under it (plus the planner's release gap): the base's full height at the first release, and each
    picked block's height in the step from one release to the next. The last block's size is not shown
    (nothing is put on it): ``object_half``, as for absent picks. The base reads high by half the release
    gap (2.5 mm for robosuite's planner); the others' gaps cancel. Clamped to [5 mm, :data:`CLEARANCE_FAR`]
    against plans that release below where they grasp."""
    present = ev["present"]  # (B, P)
    tower = ev["release_pos"][..., 2] - ev["grasp_pos"][..., 2]  # (B, P)
    default = torch.full_like(tower[:, 0], object_half)
    base = torch.where(present[:, 0], tower[:, 0] / 2, default)
    steps = (tower[:, 1:] - tower[:, :-1]) / 2  # (B, P-1): pick k's block, seen under pick k+1's release
    picked = torch.where(present[:, :-1] & present[:, 1:], steps, default.unsqueeze(-1))
    halves = torch.cat([base.unsqueeze(-1), picked, default.unsqueeze(-1)], dim=-1)  # (B, 1 + P)
    return halves.clamp(0.005, CLEARANCE_FAR)


def grasp_halves(ev: dict[str, Tensor], object_half: float, table_z: float = TABLE_Z) -> Tensor:
    """Each block's half-size (B, 1 + P) in :func:`block_halves`' layout, each picked block's read from its
    grasp's height over the table: a centre grasp closes ``half`` over it, a high grasp ``2 half -``
    :data:`HIGH_GRASP_BELOW_TOP`. For the task's cubes (:data:`CUBE_HALF_RANGE`) the two never meet -- a
    centre grasp at 2.0-2.5 cm, a high one at 3.2-4.2 cm -- so a height under the midpoint between the
    highest centre grasp and the lowest high grasp is a centre grasp. The base (never grasped) keeps
    :func:`block_halves`' size, from the first release."""
    shown = block_halves(ev, object_half)  # (B, 1 + P)
    over_table = ev["grasp_pos"][..., 2] - table_z  # (B, P)
    centre_max, high_min = CUBE_HALF_RANGE[1], 2 * CUBE_HALF_RANGE[0] - HIGH_GRASP_BELOW_TOP
    decoded = torch.where(over_table < (centre_max + high_min) / 2, over_table,
                          (over_table + HIGH_GRASP_BELOW_TOP) / 2)
    picked = torch.where(ev["present"], decoded.clamp(0.005, CLEARANCE_FAR), shown[:, 1:])
    return torch.cat([shown[:, :1], picked], dim=-1)


def _pick_clearances(ev: dict[str, Tensor], k: int, halves: Tensor) -> Tensor:
    """Pick ``k``'s clearances (B, 6): each hand part's nearest block at its grasp (the tower, under the first
    release point, and the blocks still on the table) and at its release (the blocks still on the table);
    :data:`CLEARANCE_FAR` where there is none. ``halves`` (B, 1 + P): the base's and each pick's block's
    half-size (the tower's footprint: the largest block in it so far)."""
    present = ev["present"]
    P = present.shape[1]
    order = torch.arange(P, device=present.device)
    others = order[order != k]
    later = (others > k).unsqueeze(0) & present[:, others]  # (B, P-1): still on the table at pick k
    gpos, gyaw = ev["grasp_pos"][:, k], ev["grasp_yaw"][:, k]
    spots = torch.cat([ev["release_pos"][:, :1], ev["grasp_pos"][:, others]], dim=1)  # (B, P, 3)
    yaws = torch.cat([ev["release_yaw"][:, :1], ev["grasp_yaw"][:, others]], dim=1)  # (B, P)
    there = torch.cat([present[:, :1], later], dim=1)
    picked = halves[:, 1:]  # (B, P)
    tower = halves[:, : k + 1].max(dim=1).values  # the base and the blocks released on it before pick k
    at_grasp = hand_clearance(_in_frame(gpos, gyaw, spots), yaws - gyaw.unsqueeze(-1), ev["grasp_open"][:, k],
                              torch.cat([tower.unsqueeze(-1), picked[:, others]], dim=1))  # (B, P, 3)
    at_grasp = torch.where(there.unsqueeze(-1), at_grasp, torch.full_like(at_grasp, CLEARANCE_FAR))
    rpos, ryaw = ev["release_pos"][:, k], ev["release_yaw"][:, k]
    at_release = hand_clearance(_in_frame(rpos, ryaw, ev["grasp_pos"][:, others]),
                                ev["grasp_yaw"][:, others] - ryaw.unsqueeze(-1),
                                picked[:, k], picked[:, others])  # (B, P-1, 3): fingers closed on the block
    at_release = torch.where(later.unsqueeze(-1), at_release, torch.full_like(at_release, CLEARANCE_FAR))
    return torch.cat([at_grasp.min(dim=1).values, at_release.min(dim=1).values], dim=-1)


def _grasp_frame_rows(ev: dict[str, Tensor], dtype: torch.dtype) -> list[Tensor]:
    """Per pick, the grasp-frame numbers (B, per-pick width) of :func:`pick_events`' events (the module docstring)."""
    present = ev["present"].to(dtype)  # (B, P)
    B, P = present.shape
    order = torch.arange(P, device=present.device)
    rows: list[Tensor] = []
    first_release = ev["release_pos"][:, 0]  # (B, 3)
    for k in range(P):
        keep = present[:, k : k + 1]  # (B, 1)
        gpos, gyaw = ev["grasp_pos"][:, k], ev["grasp_yaw"][:, k]  # (B, 3), (B,)
        rpos, ryaw = ev["release_pos"][:, k], ev["release_yaw"][:, k]
        rise = (rpos[:, 2] - first_release[:, 2]).unsqueeze(-1)  # (B, 1)
        others = order[order != k]
        grasp_rel = _in_frame(gpos, gyaw, ev["grasp_pos"][:, others])  # (B, P-1, 2)
        grasp_dyaw = ev["grasp_yaw"][:, others] - gyaw.unsqueeze(-1)
        still_there = (others > k).to(dtype).expand(B, -1) * present[:, others]
        release_rel = _in_frame(gpos, gyaw, ev["release_pos"])  # (B, P, 2)
        release_dyaw = ev["release_yaw"] - gyaw.unsqueeze(-1)
        occupied = (order < k).to(dtype).expand(B, -1) * present
        tower = _in_frame(rpos, ryaw, first_release.unsqueeze(1))[:, 0]  # (B, 2)
        parts = [
            keep, gpos, rpos, rise,
            (_relation(grasp_rel, grasp_dyaw, still_there) * present[:, others].unsqueeze(-1)).flatten(1),
            (_relation(release_rel, release_dyaw, occupied) * present.unsqueeze(-1)).flatten(1),
            tower,
        ]
        rows.append(torch.cat(parts, dim=-1) * keep)
    return rows


def plan_geometry(actions: Tensor, mask: Tensor | None = None, max_picks: int = DEFAULT_MAX_PICKS,
                  description: str = "grasp_frame", object_half: float = DEFAULT_OBJECT_HALF,
                  halves: Tensor | None = None) -> Tensor:
    """Raw plan ``(B, T, 16)`` -> its description ``(B, geometry_dim(max_picks, description))``: the grasp-frame
    numbers, the hand's clearance, or both (see the module docstring).

    ``halves`` (B, 1 + P), only with ``sized_clearance_and_heights``: the blocks' true half-sizes in
    :func:`block_halves`' layout instead of the ones the plan shows -- an experiment's yardstick (what
    knowing every block's size would give), not something a scorer is handed."""
    _check_description(description)
    if halves is not None and (description not in SIZED
                               or tuple(halves.shape) != (actions.shape[0], 1 + max_picks)):
        raise ValueError(f"halves: only with {' or '.join(SIZED)}, shaped (B, 1 + max_picks) = "
                         f"({actions.shape[0]}, {1 + max_picks}); got {description!r}, {tuple(halves.shape)}")
    ev = pick_events(actions, mask, max_picks)
    rows = _grasp_frame_rows(ev, actions.dtype) if description in ("grasp_frame", "both") else []
    if description != "grasp_frame":
        present = ev["present"].to(actions.dtype)
        if halves is not None:
            halves = halves.to(actions.dtype)
        elif description == "sized_clearance_and_heights":
            halves = block_halves(ev, object_half)
        elif description == "table_sized_clearance_and_heights":
            halves = grasp_halves(ev, object_half)
        else:
            halves = torch.full((actions.shape[0], 1 + max_picks), object_half, dtype=actions.dtype,
                                device=actions.device)
        rows += [_pick_clearances(ev, k, halves) * present[:, k : k + 1] for k in range(max_picks)]
    if description in WITH_HEIGHTS:
        rows += [_pick_heights(ev, k) * ev["present"][:, k : k + 1].to(actions.dtype) for k in range(max_picks)]
    return torch.cat(rows, dim=-1)  # (B, G)


def _pick_heights(ev: dict[str, Tensor], k: int) -> Tensor:
    """Pick ``k``'s heights (B, 3), :data:`PICK_HEIGHTS`: where its grasp closes and its release opens (the
    TCP's z in the robot base's frame) and the release's rise over the first release."""
    grasp_z, release_z = ev["grasp_pos"][:, k, 2], ev["release_pos"][:, k, 2]
    return torch.stack([grasp_z, release_z, release_z - ev["release_pos"][:, 0, 2]], dim=-1)


def standardise(description: Tensor, mean: Tensor, std: Tensor) -> Tensor:
    """``(description - mean) / std`` clipped to +/- :data:`STANDARD_CLIP` (shared by the fused ensemble)."""
    return ((description - mean) / std).clamp(-STANDARD_CLIP, STANDARD_CLIP)


class PlanGeometry(nn.Module):
    """:func:`plan_geometry` standardised with training-set statistics (buffers, saved with the weights).

    The description mixes metres (offsets of a few centimetres), flags and cosines; like
    :class:`~firp.model.normalize.ActionNormalizer` it is identity until :meth:`fit` is called.
    Reads the *raw* plan (joint targets in radians): forward kinematics needs real angles.
    """

    def __init__(self, max_picks: int = DEFAULT_MAX_PICKS, min_std: float = 1e-3, description: str = "grasp_frame",
                 object_half: float = DEFAULT_OBJECT_HALF):
        super().__init__()
        self.max_picks = max_picks
        self.min_std = min_std
        self.description = description
        self.object_half = object_half
        self.dim = geometry_dim(max_picks, description)
        self.register_buffer("mean", torch.zeros(self.dim))
        self.register_buffer("std", torch.ones(self.dim))

    def describe(self, actions: Tensor, mask: Tensor | None = None) -> Tensor:
        """Raw plans ``(B, T, A)`` -> this module's description of them, not standardised ``(B, G)``."""
        return plan_geometry(actions, mask, self.max_picks, self.description, self.object_half)

    @torch.no_grad()
    def fit(self, actions: Tensor, mask: Tensor | None = None, batch_size: int = 1024) -> None:
        """Per-column statistics of the description over the plans ``actions`` (N, T, A)."""
        parts = [self.describe(actions[i:i + batch_size].double(), None if mask is None else mask[i:i + batch_size])
                 for i in range(0, actions.shape[0], batch_size)]
        g = torch.cat(parts)  # (N, G)
        self.mean.copy_(g.mean(dim=0).to(self.mean.dtype))
        std = g.std(dim=0) if g.shape[0] > 1 else torch.ones_like(g[0])
        std = torch.where(std < self.min_std, torch.ones_like(std), std)  # constant in training: leave unscaled
        self.std.copy_(std.to(self.std.dtype))

    def forward(self, actions: Tensor, mask: Tensor | None = None) -> Tensor:
        """Raw plans ``(B, T, A)`` -> standardised description ``(B, G)``."""
        return standardise(self.describe(actions, mask), self.mean, self.std)


def build_plan_geometry(cfg: GeometryConfig) -> PlanGeometry | None:
    """The description module a model owns when ``cfg.enabled``, else None (the paper's models)."""
    return (PlanGeometry(cfg.max_picks, description=cfg.description, object_half=cfg.object_half) if cfg.enabled
            else None)


def plan_context(geometry: PlanGeometry | None, actions: Tensor, mask: Tensor | None = None) -> Tensor | None:
    """A success head's context: the standardised description of the raw plans (B, G), or None without one."""
    return geometry(actions, mask) if geometry is not None else None
