"""A TAMP-style planner for the robosuite world's tasks: top-down picks and places, IK on robosuite's Panda.

Like :mod:`planner_client.tamp` for our world: symbolic pick-and-place steps with the seven categories
in their natural order per moved object, TCP waypoints at a clearance height, top-down grasps across
a pair of the object's faces, place targets from the pose estimates, a small release gap, joint
targets by IK on robosuite's own Panda model (:mod:`robosuite_worker.robot`), time-resampled to the
task's T. Its conditions are those of a sensible first version and no more; which object goes first
and which pair of faces each grasp takes are its *choices* (:class:`Choice`), and the loop replans
over them as it replans over block orders in our world.

Tasks so far: ``stack_three`` -- the order of the tower (6), a pair of faces per moved cube (4) and a
grasp height per moved cube (4: at the centre, or ``high_grasp_below_top`` under the top face, which
keeps the fingertips clear of the tower but holds the cube by less of its side): 96 choices, the
default (alphabetical order, least wrist turn, centre grasps) first and the other orders next.
``nut_assembly`` -- the handle grasped across its width or along it, at one of five points along it
(:data:`NUT_GRIPS`), and the nut lowered around the peg with its handle towards the robot, or dropped
from above the peg with the handle towards the robot or to the side: 30 choices (lowering it with the
handle to the side is out of the arm's reach), the default (across, at the handle's middle, lowered)
first. ``pick_place`` -- the four objects into their quadrants of the second bin: the order (24), per
object the pair of faces (2, but 1 for the cereal box, whose other pair is wider than the open hand)
and the grasp height (2): 3072 choices, the default (robosuite's object order Milk, Bread, Cereal, Can;
least wrist turn; centre grasps) first and the other orders next.
"""

from __future__ import annotations

from dataclasses import dataclass, field
from itertools import permutations, product

import numpy as np

from firp.core.contract import make_plan
from planner_client.ik import ArmIK, ArmModel, IKConfig, IKFailure, rotation_yaw
from planner_client.tamp import QUARTER, PickPlaceTiming, Segment, nearest_equivalent, pick_and_place, trajectory

__all__ = ["Choice", "NUT_TASKS", "RobosuitePlan", "RobosuitePlannerConfig", "RobosuiteTampPlanner", "TASK_HORIZONS"]

#: T of each task (robosuite_worker.tasks.TASKS, repeated here: the planner does not import robosuite's world)
TASK_HORIZONS = {"stack_three": 80, "nut_assembly": 100, "nut_assembly_round": 100, "pick_place": 200}
#: the nut tasks: one nut onto its peg, the square one or the round one (the same moves; any yaw fits a round peg)
NUT_TASKS = ("nut_assembly", "nut_assembly_round")


@dataclass(frozen=True)
class RobosuitePlannerConfig:
    clearance: float = 0.15  # TCP height above the table for transport
    release_gap: float = 0.005  # an object is released this far above its resting height
    high_grasp_below_top: float = 0.008  # a "high" grasp closes this far below the object's top face
    timing: PickPlaceTiming = field(default_factory=PickPlaceTiming)
    ik: IKConfig = field(default_factory=IKConfig)
    # pick_place's second bin lies at the edge of a top-down hand's reach, where the pull towards the home
    # posture keeps the default solver a millimetre short: a weaker pull and more iterations there
    reach_ik: IKConfig = field(default_factory=lambda: IKConfig(max_iterations=1000, posture_gain=0.01))
    reach_tasks: tuple[str, ...] = ("pick_place",)


#: grasp heights a choice can take, per moved object
GRASP_HEIGHTS = ("centre", "high")
#: where along the nut's handle (5 cm long, its inner 1.5 cm beside the nut's wall) the hand holds it: metres
#: outwards from the handle's centre, the site robosuite marks on it -- middle, 5 and 10 mm outwards, 4 and 8 mm
#: inwards. Measured on 4 scenes (30 choices each): across the handle, the inner grips fail 5 times in 8 (the
#: fingers meet the nut's wall); along it, the outer grips fail 22 times in 24 (the outer finger passes the
#: handle's end); the others succeed 94% of the time
NUT_GRIPS = (0.0, 0.005, 0.01, -0.004, -0.008)
NUT_GRIP_NAMES = ("m", "o", "O", "i", "I")
#: the open hand's span (each finger 0.04 m from the centre) and half the height of a finger pad: a "high"
#: grasp keeps the pads' upper edges this far below the object's top face less ``high_grasp_below_top``
FINGER_OPEN_M = 0.04
PAD_HALF_HEIGHT = 0.01
#: pick_place: half the thickness of the second bin's dividers, and the room kept between a placed object's
#: circumscribed circle and its quadrant's walls
BIN_DIVIDER_HALF = 0.01
PLACE_MARGIN = 0.01
#: the nut's release height above the peg's top, for ``drops`` 1 (0 lowers it to the table around the peg)
NUT_DROP_HEIGHT = 0.01


@dataclass(frozen=True)
class Choice:
    """The planner's choices for one plan: which objects in which order, and per grasp which pair of
    faces and how high on them."""

    order: tuple[str, ...]
    axes: tuple[int, ...]  # per moved object: 0 = the faces needing the least wrist turn, 1 = the other pair
    heights: tuple[int, ...] = ()  # per moved object, index into GRASP_HEIGHTS (missing: centre)
    drops: tuple[int, ...] = ()  # nut: 0 = lowered onto the table around the peg, 1 = dropped from above the peg
    turns: tuple[int, ...] = ()  # nut: 0 = the nearest quarter turn that fits the peg, 1 = the next nearest
    grips: tuple[int, ...] = ()  # nut: where along its handle the hand holds it, index into NUT_GRIPS

    def height(self, k: int) -> str:
        return GRASP_HEIGHTS[self.heights[k]] if k < len(self.heights) else "centre"

    def label(self) -> str:
        parts = ["-".join(self.order), "".join(map(str, self.axes))]
        if self.heights:
            parts.append("".join("h" if h else "c" for h in self.heights))
        if self.drops:
            parts.append("".join("d" if d else "l" for d in self.drops))
        if self.turns:
            parts.append("".join(f"q{t}" for t in self.turns))
        if self.grips:
            parts.append("".join(NUT_GRIP_NAMES[g] for g in self.grips))
        return ":".join(parts)


@dataclass
class RobosuitePlan:
    actions: np.ndarray  # (T, 16)
    choice: Choice
    grasp_yaws: list[float]
    place_targets: list[list[float]]
    segments: list[Segment] = field(repr=False, default_factory=list)


class RobosuiteTampPlanner:
    """Plans the robosuite world's tasks from an episode's observation."""

    def __init__(self, config: RobosuitePlannerConfig = RobosuitePlannerConfig()):
        self.config = config
        self._ik: dict[tuple[float, ...], ArmIK] = {}

    def ik(self, base: list[float], task: str = "") -> ArmIK:
        """IK on robosuite's Panda standing at ``base`` (one solver per base and settings, built on first use)."""
        config = self.config.reach_ik if task in self.config.reach_tasks else self.config.ik
        key = (*(round(v, 9) for v in base), config)
        if key not in self._ik:
            from robosuite_worker.robot import panda_kinematics

            k = panda_kinematics()
            arm = ArmModel(k.model, k.tcp_site, k.qpos, k.dof, k.home, k.finger_axis, np.asarray(base, dtype=float))
            self._ik[key] = ArmIK(arm, config)
        return self._ik[key]

    # -- choices -----------------------------------------------------------------------------------
    def choices(self, task: str, observation: dict) -> list[Choice]:
        """Every choice for this scene, the default first (the loop walks this list)."""
        if task == "stack_three":
            names = tuple(sorted(observation["blocks"]))
            orders = list(permutations(names))
            return [Choice(order, axes, heights) for heights in product((0, 1), repeat=2)
                    for axes in product((0, 1), repeat=2) for order in orders]
        if task in NUT_TASKS:
            names = tuple(observation["blocks"])
            # lowered around the peg only with the handle towards the robot: the other yaws put the hand
            # out of the arm's reach at the table (the peg stands 79 cm from the base)
            ways = ((0, 0), (1, 0), (1, 1))  # (drops, turns)
            return [Choice(names, (axis,), drops=(drop,), turns=(turn,), grips=(grip,))
                    for grip in range(len(NUT_GRIPS)) for drop, turn in ways for axis in (0, 1)]
        if task == "pick_place":
            names = tuple(observation["blocks"])
            pairs = [self._grasp_pairs(observation["scene"]["objects"][name]) for name in names]
            orders = list(permutations(names))
            return [Choice(order, tuple(axes[names.index(n)] for n in order),
                           tuple(heights[names.index(n)] for n in order))
                    for heights in product((0, 1), repeat=len(names))
                    for axes in product(*(range(len(p)) for p in pairs)) for order in orders]
        raise ValueError(f"task: the robosuite planner does not plan {task!r} yet")

    # -- what the trial loop replans over (planner_client.loop.Planner) ---------------------------------
    def candidates(self, task: str, observation: dict) -> list[Choice]:
        return self.choices(task, observation)

    def horizon(self, task: str) -> int:
        return TASK_HORIZONS[task]

    @staticmethod
    def describe(choice: Choice) -> str:
        return choice.label()

    # -- plans ---------------------------------------------------------------------------------------
    def plan(self, task: str, observation: dict, choice: Choice | None = None) -> RobosuitePlan:
        choice = choice or self.choices(task, observation)[0]
        scene = observation["scene"]
        ik = self.ik(scene["robot_base"], task)
        q = np.asarray(scene["robot_start"], dtype=float)
        start_pos, start_rot = ik.forward(q)
        start_yaw = rotation_yaw(start_rot, ik.arm.finger_axis)
        if task == "stack_three":
            alternatives = [self._stack_moves(observation, choice, start_yaw)]
        elif task in NUT_TASKS:
            # of the two hand yaws holding the handle alike, the first one the wrist can turn through
            alternatives = [self._nut_moves(observation, choice, start_yaw, flip) for flip in (0.0, np.pi, -np.pi)]
        elif task == "pick_place":
            # a grasp's hand yaw and the same yaw turned half a turn hold the object alike; near the far bin
            # the wrist reaches one of them only (its last joint at a limit): the nearest first, then each
            # object's other yaw in turn
            moves = self._pick_place_moves(observation, choice, start_yaw)
            alternatives = [moves] + [[(g, y + (np.pi if k == j else 0.0), r, ry + (np.pi if k == j else 0.0))
                                       for k, (g, y, r, ry) in enumerate(moves)] for j in range(len(moves))]
        else:
            raise ValueError(f"task: the robosuite planner does not plan {task!r} yet")
        for k, moves in enumerate(alternatives):
            segments, yaws, places = self._segments(moves, start_pos)
            try:
                categories, targets = trajectory(segments, start_pos, start_yaw, TASK_HORIZONS[task], ik, q)
            except IKFailure:
                if k == len(alternatives) - 1:
                    raise
                continue
            return RobosuitePlan(make_plan(categories, targets), choice, yaws, places, segments)

    def _stack_moves(self, observation: dict, choice: Choice, neutral_yaw: float
                     ) -> list[tuple[np.ndarray, float, np.ndarray, float]]:
        """(grasp point, grasp yaw, release point, release yaw) of the hand per moved cube: onto the tower so far.

        A grasp's yaw is taken modulo the half turn closest to the hand's starting yaw (``neutral_yaw``),
        which keeps the wrist inside its range."""
        blocks, half = observation["blocks"], observation["scene"]["cube_half"]
        base = choice.order[0]
        top = np.asarray(blocks[base]["position"], dtype=float) + [0.0, 0.0, half[base]]  # the tower's top face
        base_yaw = float(blocks[base]["yaw"])
        moves = []
        for k, (name, axis) in enumerate(zip(choice.order[1:], choice.axes)):
            pos, yaw = np.asarray(blocks[name]["position"], dtype=float), float(blocks[name]["yaw"])
            grasp = pos.copy()
            if choice.height(k) == "high":
                grasp[2] += half[name] - self.config.high_grasp_below_top
            options = sorted((nearest_equivalent(yaw + j * QUARTER, neutral_yaw, np.pi) for j in (0, 1)),
                             key=lambda option: abs(option - neutral_yaw))
            grasp_yaw = options[axis]
            # the hand releases where it holds the cube: its centre's target plus the grasp's height on it
            place = np.array([top[0], top[1], top[2] + half[name] + self.config.release_gap + grasp[2] - pos[2]])
            moves.append((grasp, grasp_yaw, place, nearest_equivalent(base_yaw, grasp_yaw)))
            top = np.array([top[0], top[1], top[2] + 2 * half[name]])
        return moves

    def _nut_moves(self, observation: dict, choice: Choice, neutral_yaw: float, flip: float = 0.0
                   ) -> list[tuple[np.ndarray, float, np.ndarray, float]]:
        """The hand's one move for the nut: grasp its handle, carry it over the peg turned so that its square
        hole fits the square peg (a quarter turn of the nut is the same nut), lower or drop it around the peg.

        ``axes`` 0 closes the fingers across the handle's width, 1 along its length; ``turns`` 0 turns the nut
        so that its handle points towards the robot, 1 to the next best of its four equivalent yaws;
        ``drops`` 0 lowers it around the peg, 1 lets it go above the peg's top."""
        (name,), scene = choice.order, observation["scene"]
        nut = observation["blocks"][name]
        pos, yaw = np.asarray(nut["position"], dtype=float), float(nut["yaw"])
        handle = np.asarray(scene["handle_offset"], dtype=float)  # in the nut's frame

        def rotate(angle: float, v: np.ndarray) -> np.ndarray:
            c, s = np.cos(angle), np.sin(angle)
            return np.array([c * v[0] - s * v[1], s * v[0] + c * v[1]])

        grip = NUT_GRIPS[choice.grips[0]] if choice.grips else 0.0
        handle = handle * (1.0 + grip / np.linalg.norm(handle))
        grasp = np.array([*(pos[:2] + rotate(yaw, handle)), pos[2]])
        # the nut's yaw over the peg: a quarter turn of it fits the peg as well, so the four differ in where the
        # handle (the hand) ends up -- best towards the robot's base, which keeps the hand within reach
        peg_yaw, base = float(scene.get("peg_yaw", 0.0)), np.asarray(scene["robot_base"], dtype=float)
        peg = np.asarray(scene["peg"], dtype=float)
        towards_base = np.arctan2(*(base[:2] - peg[:2])[::-1])
        handle_angle = np.arctan2(handle[1], handle[0])
        options = [nearest_equivalent(peg_yaw, yaw, QUARTER) + k * QUARTER for k in (-1, 0, 1, 2)]
        target_yaw = sorted(options, key=lambda t: abs(np.angle(np.exp(1j * (t + handle_angle - towards_base)))))[
            choice.turns[0]]
        turn = target_yaw - yaw
        # the fingers close across the handle's width (axis 0) or along it (1); of the two equivalent hand yaws
        # the one that keeps the whole turn closest to the hand's starting yaw
        finger_yaw = yaw + (QUARTER if choice.axes[0] == 0 else 0.0)
        grasp_yaw = nearest_equivalent(finger_yaw, neutral_yaw - turn / 2, np.pi) + flip
        if choice.drops[0]:  # released with the nut's underside this far above the peg's top
            nut_z = scene["peg_top"] + scene["nut_half_height"] + NUT_DROP_HEIGHT
        else:  # lowered around the peg to just above the table
            nut_z = scene["table_height"] + scene["nut_half_height"] + self.config.release_gap
        release = np.array([*(peg[:2] + rotate(target_yaw, handle)), nut_z + grasp[2] - pos[2]])
        return [(grasp, grasp_yaw, release, grasp_yaw + turn)]

    @staticmethod
    def _grasp_pairs(model: dict) -> list[int]:
        """The quarter turns (0: the fingers close along the object's x, 1: along its y) whose faces fit
        between the open fingers with 1 cm to spare. A square or round object fits both ways, which hold it
        alike but turn the hand -- wide along its fingers -- differently among its neighbours."""
        half = model["half"]
        return [j for j in (0, 1) if 2 * half[j] <= 2 * FINGER_OPEN_M - 0.01]

    def _pick_place_moves(self, observation: dict, choice: Choice, neutral_yaw: float
                          ) -> list[tuple[np.ndarray, float, np.ndarray, float]]:
        """Each object in turn into its quadrant of the second bin: grasped top-down across a pair of faces
        that fits the open hand, at its centre or high on it, and lowered onto the bin's floor at the reachable
        point of its quadrant (:meth:`_place_point`) without turning."""
        scene = observation["scene"]
        moves = []
        for k, (name, axis) in enumerate(zip(choice.order, choice.axes)):
            model, estimate = scene["objects"][name], observation["blocks"][name]
            pos, yaw = np.asarray(estimate["position"], dtype=float), float(estimate["yaw"])
            half = model["half"]
            centre = pos + [0.0, 0.0, model["centre_z"]]
            grasp = centre.copy()
            if choice.height(k) == "high":
                grasp[2] += max(0.0, half[2] - self.config.high_grasp_below_top - PAD_HALF_HEIGHT)
            quarter = self._grasp_pairs(model)[axis]
            grasp_yaw = nearest_equivalent(yaw + quarter * QUARTER, neutral_yaw, np.pi)
            target = self._place_point(scene, name, yaw)
            release = np.array([target[0], target[1],
                                scene["bin_floor"] + half[2] + self.config.release_gap + grasp[2] - centre[2]])
            moves.append((grasp, grasp_yaw, release, grasp_yaw))
        return moves

    @staticmethod
    def quadrant(scene: dict, name: str) -> tuple[np.ndarray, np.ndarray]:
        """The (x, y) corners, low and high, of ``name``'s quadrant of the second bin: the bounds robosuite's
        ``not_in_bin`` checks (its walls and dividers included)."""
        target = np.asarray(scene["targets"][name], dtype=float)[:2]
        centre, size = np.asarray(scene["bin2"][:2], dtype=float), np.asarray(scene["bin_size"], dtype=float)
        low = np.minimum(centre, centre + np.sign(target - centre) * size / 2)
        return low, low + size / 2

    @staticmethod
    def _place_point(scene: dict, name: str, yaw: float) -> np.ndarray:
        """Where in its quadrant of the second bin an object goes: the quadrant's point nearest the robot's
        base that keeps the object's footprint (at ``yaw``, its own) ``PLACE_MARGIN`` from the quadrant's
        walls. robosuite's targets, the quadrants' centres, lie up to 7 cm beyond a top-down hand's reach
        in the far quadrant."""
        low, high = RobosuiteTampPlanner.quadrant(scene, name)
        # the dividers run along the bin's centre lines: keep clear of the half of them inside the quadrant
        centre = np.asarray(scene["bin2"][:2], dtype=float)
        low = np.where(np.isclose(low, centre), low + BIN_DIVIDER_HALF, low)
        high = np.where(np.isclose(high, centre), high - BIN_DIVIDER_HALF, high)
        hx, hy = scene["objects"][name]["half"][:2]
        if abs(hx - hy) < 0.001:  # round: its radius
            extent = np.array([hx, hy])
        else:  # a box at the yaw it keeps from its grasp: its footprint along the world's axes
            c, s = abs(np.cos(yaw)), abs(np.sin(yaw))
            extent = np.array([c * hx + s * hy, s * hx + c * hy])
        low, high = low + extent + PLACE_MARGIN, high - extent - PLACE_MARGIN
        base = np.asarray(scene["robot_base"][:2], dtype=float)
        return np.clip(base, low, np.maximum(low, high))

    def _segments(self, moves, start_pos: np.ndarray) -> tuple[list[Segment], list[float], list]:
        segments: list[Segment] = []
        pos = np.asarray(start_pos, dtype=float)
        yaws, places = [], []
        for grasp, grasp_yaw, release, release_yaw in moves:
            height = max(grasp[2], release[2]) + self.config.clearance
            above_grasp = np.array([grasp[0], grasp[1], height])
            above_release = np.array([release[0], release[1], height])
            segments += pick_and_place(self.config.timing, pos, (above_grasp, grasp, grasp_yaw),
                                       (above_release, release, release_yaw))
            pos = above_release
            yaws.append(grasp_yaw)
            places.append([*release.tolist(), release_yaw])
        return segments, yaws, places
