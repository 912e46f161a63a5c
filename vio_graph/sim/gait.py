"""Sagittal gait of the instrumented leg, physically consistent by construction.

Construction (see docs/simulator.md):
1. plan footholds of both feet on the terrain (the contralateral foot is virtual: it only
   shapes the hip path);
2. foot pitch: one C2 piecewise-quintic (scipy BPoly) through per-stride key poses: landing
   (heel strike toe-up on level ground, forefoot landing toe-down on stairs, Riener 2002),
   flat, heel-off, toe-off, mid-swing;
3. ankle: during contact it follows from the fixed pivot (heel, then whole foot, then toe:
   no sliding, no penetration); in swing the toe follows a quintic spline through clearance
   via-points (toe clearance over nosings / the obstacle / level ground);
4. hip: C2 cubic splines through key positions chosen from published knee-flexion targets at
   contact and mid-stance of both feet, repaired where the hip-ankle distance would exceed
   0.97 of thigh + shank;
5. knee from two-link inverse kinematics (knee flexes forward); joint angles from segment
   angles with vio_graph.kinematics conventions.
Opt-in ``gait.swing_model = joint_space`` replaces step 3's swing (the hip of step 4 stays):
thigh and knee angles are C2 quintic pieces from the toe-off state through a peak knee
flexion and a terminal via point to the landing state, the ankle follows by forward
kinematics, and a C2 bump raises (or lowers) it to the configured clearances.
Dense samples (1 kHz) are then wrapped in quintic interpolating splines so derivatives (IMU)
are analytic.
"""

from __future__ import annotations

import copy
from dataclasses import dataclass, field, replace

import numpy as np
from numpy.typing import NDArray
from scipy.interpolate import BPoly, CubicSpline, make_interp_spline
from scipy.ndimage import gaussian_filter1d, maximum_filter1d

from vio_graph.errors import ConfigError, SimulationError, TerrainTooShortError
from vio_graph.kinematics import LegModel
from vio_graph.sim.config import GaitConfig, RigConfig
from vio_graph.sim.terrain import Terrain

DENSE_RATE_HZ = 1000.0
MAX_REACH_FRACTION = 0.99  # hip-ankle distance / (thigh + shank) must stay below this
REPAIR_REACH_FRACTION = 0.985  # the hip is lowered to this where it would overstretch
_STAIR_DZ_M = 0.05
SWING_PITCH_ITERATIONS = 3
_EXIT_HEEL_MARGIN_M = 0.03  # first foothold after the stairs: heel this far past the edge
_EXIT_STEP_M = 0.30  # then one short step before level steps (no 1 m stride off the stairs)
_MAX_TOE_OVERHANG_M = 0.05  # descent on treads shorter than the foot: toe past the nosing
_WALK_MARGIN_S = 0.3  # the walk must go on this long past the trial's end (the last swing)
_PLATFORM_MARGIN_M = 0.015  # an obstacle stepped onto: heel and toe at least this far in


def leg_model_for(rig: RigConfig) -> LegModel:
    """Link lengths and foot points: Winter (2009) fractions of H, or the prosthesis (Fig. 3)."""
    H = rig.body_height_m
    thigh = 0.245 * H
    if rig.rig == "able_bodied":
        shank = rig.shank_length_m or 0.246 * H
        ankle_h, foot = 0.039 * H, 0.152 * H
        heel = rig.heel_in_foot_xz_m or (-0.055, -ankle_h)
        toe = rig.toe_in_foot_xz_m or (foot - 0.055, -ankle_h)
    else:
        shank = rig.shank_length_m or 0.42
        heel = rig.heel_in_foot_xz_m or (-0.05, -0.075)
        toe = rig.toe_in_foot_xz_m or (0.20, -0.075)
    return LegModel(thigh, shank, tuple(heel), tuple(toe))


def rot_xz(theta: NDArray | float, v: NDArray) -> NDArray[np.float64]:
    """Rotate body (x, z) vectors (..., 2) by rot_y(theta) (broadcast): world (x, z)."""
    th = np.asarray(theta, dtype=float)
    v = np.asarray(v, dtype=float)
    c, s = np.cos(th), np.sin(th)
    return np.stack([c * v[..., 0] + s * v[..., 1], -s * v[..., 0] + c * v[..., 1]], axis=-1)


def drot_xz(theta: NDArray | float, v: NDArray) -> NDArray[np.float64]:
    """d/dtheta of rot_xz(theta, v)."""
    th = np.asarray(theta, dtype=float)
    v = np.asarray(v, dtype=float)
    c, s = np.cos(th), np.sin(th)
    return np.stack([-s * v[..., 0] + c * v[..., 1], -c * v[..., 0] - s * v[..., 1]], axis=-1)


@dataclass(frozen=True)
class Stride:
    """One stride of the instrumented leg: contact on ``toe_xz_m`` (flat-pose toe) at
    ``t_contact_s``; pivots: landing (heel or toe) until ``t_flat_s``, flat until
    ``t_heel_off_s``, toe until ``t_toe_off_s``; swing until ``t_next_s``."""

    toe_xz_m: tuple[float, float]
    next_toe_xz_m: tuple[float, float]
    landing: str  # "heel" | "toe"
    swing_kind: str  # "level" | "ascent" | "descent" | "obstacle" (the swing leaving here)
    arrive_kind: str  # kind of the swing that arrived here
    t_contact_s: float
    t_flat_s: float
    t_heel_off_s: float
    t_toe_off_s: float
    t_next_s: float
    contra_toe_xz_m: tuple[float, float]
    contra_landing: str
    contra_kind: str
    t_contra_contact_s: float
    t_contra_mid_s: float
    t_mid_s: float
    t_rest_s: float = float("nan")  # where a standing pause may go (foot flat, double support)
    contra_joins: bool = False  # step_to_step, instrumented leading: contralateral joins here


@dataclass(frozen=True)
class LegMotion:
    """True sagittal motion of the instrumented leg.

    Dense arrays on ``t_s`` (N,) at 1 kHz: positions (N, 2) world (x, z) in metres, angles
    (N,) in rad (hip flexion = ``thigh_pitch_rad``, ``knee_rad`` flexion, ``ankle_rad``
    plantarflexion, segment pitches per docs/conventions.md). Splines give derivatives.
    """

    leg: LegModel
    t_s: NDArray[np.float64]
    hip_xz_m: NDArray[np.float64]
    knee_xz_m: NDArray[np.float64]
    ankle_xz_m: NDArray[np.float64]
    heel_xz_m: NDArray[np.float64]
    toe_xz_m: NDArray[np.float64]
    thigh_pitch_rad: NDArray[np.float64]
    knee_rad: NDArray[np.float64]
    ankle_rad: NDArray[np.float64]
    shank_pitch_rad: NDArray[np.float64]
    foot_pitch_rad: NDArray[np.float64]
    strides: tuple[Stride, ...]
    _splines: dict = field(repr=False)
    holds_s: tuple[tuple[float, float], ...] = ()  # standing pauses (start, end), real time

    def shank_pitch(self, t_s: NDArray, deriv: int = 0) -> NDArray[np.float64]:
        """Shank pitch (rad) or its ``deriv``-th time derivative at times (M,)."""
        return self._splines["shank"](t_s, deriv)

    def foot_pitch(self, t_s: NDArray, deriv: int = 0) -> NDArray[np.float64]:
        return self._splines["foot"](t_s, deriv)

    def ankle(self, t_s: NDArray, deriv: int = 0) -> NDArray[np.float64]:
        """Ankle (M, 2) position / velocity / acceleration in the world x-z plane."""
        return self._splines["ankle"](t_s, deriv)

    def joint_angles(self, t_s: NDArray) -> tuple[NDArray, NDArray, NDArray]:
        """Hip flexion, knee flexion, ankle plantarflexion (rad) at times (M,)."""
        return (
            self._splines["hip_flex"](t_s),
            self._splines["knee"](t_s),
            self._splines["ankle_angle"](t_s),
        )

    def shank_point(self, t_s: NDArray, r_shank_xz_m: NDArray, deriv: int = 0) -> NDArray:
        """A point fixed in the shank frame (origin at the knee): position (deriv 0),
        velocity (1) or acceleration (2), (M, 2), analytic from the splines."""
        r = np.asarray(r_shank_xz_m, dtype=float) + np.array([0.0, self.leg.shank_length_m])
        phi = self.shank_pitch(t_s)
        if deriv == 0:
            return self.ankle(t_s) + rot_xz(phi, r)
        dphi = self.shank_pitch(t_s, 1)
        if deriv == 1:
            return self.ankle(t_s, 1) + dphi[:, None] * drot_xz(phi, r)
        ddphi = self.shank_pitch(t_s, 2)
        return (
            self.ankle(t_s, 2)
            + ddphi[:, None] * drot_xz(phi, r)
            - (dphi**2)[:, None] * rot_xz(phi, r)
        )

    def stance_mask(self, t_s: NDArray, point: str) -> NDArray[np.bool_]:
        """True where ``point`` ("heel" or "toe") is a fixed contact point of the foot."""
        t = np.asarray(t_s, dtype=float)
        m = np.zeros(t.shape, dtype=bool)
        for s in self.strides:
            if point == "heel":
                t0 = s.t_contact_s if s.landing == "heel" else s.t_flat_s
                m |= (t >= t0) & (t <= s.t_heel_off_s)
            else:
                t0 = s.t_contact_s if s.landing == "toe" else s.t_flat_s
                m |= (t >= t0) & (t <= s.t_toe_off_s)
        return m


# --------------------------------------------------------------------------- footholds


def _plan_steps(
    terrain: Terrain, gait: GaitConfig, leg: LegModel, rng: np.random.Generator, n_max: int
) -> list[tuple[float, float]]:
    """Alternating footholds (flat-pose toe x, z) of both feet: instrumented at even indices."""
    foot_len = leg.toe_in_foot_xz_m[0] - leg.heel_in_foot_xz_m[0]
    stride = gait.level_stride_length_m * (1 + gait.stride_length_jitter * rng.standard_normal())
    step = 0.5 * stride
    xf = terrain.feature_x_m
    prm = terrain.params
    x_end = terrain.profile_xz_m[-1, 0] - 0.4
    toes: list[float] = [xf - gait.start_distance_m]
    if terrain.kind in ("stair_up", "stair_down"):
        t, n = float(prm["tread_m"]), int(prm["n_steps"])
        n_fl = int(prm.get("n_flights", 1))
        up = terrain.kind == "stair_up"
        # footholds from the actual nosings (irregular stairs: drawn treads; regular: the
        # same numbers as x0 + i t)
        nosing_x = terrain.edges_xz_m[:, 0].reshape(n_fl, n)
        x_first = nosing_x[0, 0] - (gait.stair_toe_margin_m if up else 0.02)
        if x_first - toes[0] > step:  # a long level approach: walk to the stair
            k = int(np.ceil((x_first - toes[0]) / step))
            k += 1 - k % 2  # odd: the same leg steps onto the stair as from a short start
            toes += list(toes[0] + (x_first - toes[0]) * np.arange(1, k) / k)
        for f in range(n_fl):
            xs = nosing_x[f]
            if f > 0:  # landing between flights: level steps up to the next flight
                _landing_steps(
                    toes,
                    xs[0] - (gait.stair_toe_margin_m if up else 0.02),
                    float(nosing_x[f - 1, -1]),
                    foot_len,
                    step,
                )
            if up:
                toes.append(xs[0] - gait.stair_toe_margin_m)
                toes += [xs[i + 1] - gait.stair_toe_margin_m for i in range(n - 1)]
                toes.append(xs[n - 1] + foot_len + _EXIT_HEEL_MARGIN_M)  # heel past edge
            else:
                toes.append(xs[0] - 0.02)
                # treads shorter than the foot: heel closer to the riser, toe over the nosing
                treads = np.diff(xs) if terrain.irregular else np.full(n - 1, t)
                for i in range(1, n):
                    m = min(
                        gait.stair_heel_margin_m,
                        max(0.005, float(treads[i - 1]) + _MAX_TOE_OVERHANG_M - foot_len),
                    )
                    toes.append(xs[i - 1] + m + foot_len)
                toes.append(xs[n - 1] + _EXIT_HEEL_MARGIN_M + foot_len)
        toes.append(toes[-1] + _EXIT_STEP_M)  # short transition step onto the landing
    elif steps_onto_obstacle(terrain, gait):
        _platform_steps(toes, xf, float(prm["depth_m"]), foot_len, step, gait)
    elif terrain.kind == "obstacle":
        d = float(prm["depth_m"])
        trail = xf - 0.18  # contralateral (trailing) toe before the obstacle
        k = max(1, int(np.ceil((trail - toes[0]) / step)))
        k += 1 - k % 2  # odd: the instrumented leg leads over the obstacle
        toes += list(toes[0] + (trail - toes[0]) * np.arange(1, k + 1) / k)
        toes.append(xf + d + 0.20 + foot_len)
        toes.append(toes[-1] + 0.8 * step)
    while len(toes) < n_max and toes[-1] + step < x_end:
        toes.append(toes[-1] + step)
    x = np.asarray(toes[:n_max]) + gait.step_jitter_m * rng.standard_normal(min(len(toes), n_max))
    if terrain.kind in ("stair_up", "stair_down") or steps_onto_obstacle(terrain, gait):
        # keep stair (and platform) footholds on their treads
        x = np.asarray(toes[:n_max]) + np.clip(x - np.asarray(toes[:n_max]), -0.01, 0.01)
    heel_x = x - foot_len
    z = np.maximum(terrain.height_at(x), terrain.height_at(heel_x))
    return list(zip(x.tolist(), z.tolist(), strict=True))


def steps_onto_obstacle(terrain: Terrain, gait: GaitConfig) -> bool:
    """True when the obstacle is deeper than ``gait.obstacle_step_on_depth_m``: the leg steps
    onto it (ascent, then descent swing) instead of over it (one obstacle swing)."""
    return terrain.kind == "obstacle" and float(terrain.params["depth_m"]) > (
        gait.obstacle_step_on_depth_m
    )


def _platform_steps(
    toes: list[float], xf: float, depth: float, foot_len: float, step: float, gait: GaitConfig
) -> None:
    """Footholds (appended to ``toes``, which holds the start) over an obstacle stepped onto,
    like one stair step up and one down: level steps to the contralateral toe
    ``gait.stair_toe_margin_m`` before the near face, the instrumented foot onto the top
    (centred on it), the contralateral foot past it to the floor beyond (heel
    ``gait.stair_heel_margin_m`` past the far face), the instrumented foot down to the floor
    one short transition step (_EXIT_STEP_M) further."""
    room = depth - foot_len
    if room < 2 * _PLATFORM_MARGIN_M:
        raise ConfigError(
            f"terrain.obstacle_depth_m = {depth:.2f} m is deeper than "
            f"gait.obstacle_step_on_depth_m = {gait.obstacle_step_on_depth_m:.2f} m (too deep "
            f"to step over) but leaves no room on its top for a {foot_len:.2f} m foot: raise "
            "gait.obstacle_step_on_depth_m (step over it) or make the obstacle deeper"
        )
    trail = xf - gait.stair_toe_margin_m
    k = max(1, int(np.ceil((trail - toes[0]) / step)))
    k += 1 - k % 2  # odd: the instrumented leg steps onto the obstacle
    toes += list(toes[0] + (trail - toes[0]) * np.arange(1, k + 1) / k)
    toes.append(xf + 0.5 * (depth + foot_len))  # the foot centred on the top
    toes.append(xf + depth + gait.stair_heel_margin_m + foot_len)
    toes.append(toes[-1] + _EXIT_STEP_M)


def _landing_steps(
    toes: list[float], x_approach: float, x_edge: float, foot_len: float, step: float
) -> None:
    """Footholds on a landing between flights (appended to ``toes``, which ends with the
    exit foothold past the last edge ``x_edge``): level steps no longer than ``step`` towards
    the approach foothold ``x_approach`` before the next flight (appended by the caller)."""
    if x_approach - foot_len < x_edge + 0.005:
        raise ConfigError(
            f"terrain.flight_landing_m is too short for a {foot_len:.2f} m foot: the foot "
            "before the next flight would hang over the previous nosing"
        )
    x_exit = toes[-1]
    if x_approach - x_exit < 0.08:  # no room for the exit foothold: go straight to approach
        toes.pop()
        x_exit = toes[-1]
    k = max(1, int(np.ceil((x_approach - x_exit) / step)))
    toes += list(x_exit + (x_approach - x_exit) * np.arange(1, k) / k)


def _swing_kind(terrain: Terrain, a: tuple[float, float], b: tuple[float, float]) -> str:
    dz = b[1] - a[1]
    if dz > _STAIR_DZ_M:
        return "ascent"
    if dz < -_STAIR_DZ_M:
        return "descent"
    e = terrain.edges_xz_m
    if terrain.kind == "obstacle" and np.any((e[:, 0] > a[0]) & (e[:, 0] < b[0])):
        return "obstacle"
    return "level"


def _kind_class(kind: str) -> str:
    return "level" if kind == "obstacle" else kind


def plan_strides(
    terrain: Terrain,
    gait: GaitConfig,
    leg: LegModel,
    duration_s: float,
    rng: np.random.Generator,
    allow_short: bool = False,
) -> list[Stride]:
    """Timed strides of the instrumented leg covering [0, duration_s] (+ margin).

    ``allow_short``: return what the terrain allows instead of raising (the caller checks
    coverage, e.g. after inserting pauses)."""
    sts = gait.pattern == "step_to_step" and terrain.kind in ("stair_up", "stair_down")
    lead = sts and gait.leading_leg == "instrumented"
    steps = _plan_steps(terrain, gait, leg, rng, 4000)
    if lead:  # both feet on each tread: instrumented steps up first, contralateral joins
        inst = steps[:1] + steps[2:]
        contra = list(inst)
    elif sts:  # both feet on each tread: instrumented i -> i+1, contralateral leads
        inst = steps[:1] + steps[2:]
        contra = inst[1:]
    else:
        inst, contra = steps[0::2], steps[1::2]
    jit = 1 + gait.stride_time_jitter * rng.standard_normal()
    strides: list[Stride] = []
    t = 0.0
    arrive = "level"
    for j in range(min(len(inst) - 1, len(contra))):
        a, b, c = inst[j], inst[j + 1], contra[j]
        kind = _swing_kind(terrain, a, b)
        c_prev = contra[j - 1] if j > 0 else (c[0] - (b[0] - a[0]), a[1])
        c_kind = _swing_kind(terrain, c_prev, c) if j > 0 else kind
        stair = kind in ("ascent", "descent") or c_kind in ("ascent", "descent")
        landing = "toe" if arrive in ("ascent", "descent") else "heel"
        c_landing = "toe" if c_kind in ("ascent", "descent") else "heel"
        if lead:  # land on the next tread, the other foot joins, pause, swing on
            move = gait.stair_stride_time_s * jit / gait.cadence_scale
            p = gait.step_to_step_pause_s * jit
            T = move + p
            f = dict(
                flat=0.12 * move,
                ho=p + 0.45 * move,
                to=p + 0.62 * move,
                cc=0.42 * move,
                cm=0.42 * move + 0.5 * p,
                mid=0.2 * move,
            )
            f["rest"] = f["cm"]
        elif sts:
            move = gait.stair_stride_time_s * jit / gait.cadence_scale
            p = gait.step_to_step_pause_s * jit
            T = move + p
            f = dict(
                flat=0.12 * move,
                ho=p + 0.45 * move,
                to=p + 0.62 * move,
                cc=p + 0.32 * move,
                cm=p + 0.6 * move,
                mid=0.5 * p,
            )
            # both feet on the tread, foot flat: from flat to the other foot's toe-off
            f["rest"] = 0.5 * (f["flat"] + max(f["flat"], p + 0.05 * move))
        else:
            T = (gait.stair_stride_time_s if stair else gait.level_stride_time_s) * jit
            T *= 1.25 if kind == "obstacle" else 1.0
            T /= gait.cadence_scale
            beta = gait.stance_fraction_stair if stair else gait.stance_fraction_level
            f = dict(
                flat=(0.12 if landing == "toe" else 0.09) * T,
                ho=(beta - 0.2 if stair else beta - 0.26) * T,
                to=beta * T,
                cc=0.5 * T,
                cm=0.8 * T,
                mid=0.3 * T,
            )
            f["rest"] = f["flat"] + 0.02 * T  # foot just flat, other foot about to leave
        strides.append(
            Stride(
                toe_xz_m=a,
                next_toe_xz_m=b,
                landing=landing,
                swing_kind=kind,
                arrive_kind=arrive,
                t_contact_s=t,
                t_flat_s=t + f["flat"],
                t_heel_off_s=t + f["ho"],
                t_toe_off_s=t + f["to"],
                t_next_s=t + T,
                contra_toe_xz_m=c,
                contra_landing=c_landing,
                contra_kind=c_kind,
                t_contra_contact_s=t + f["cc"],
                t_contra_mid_s=t + f["cm"],
                t_mid_s=t + f["mid"],
                t_rest_s=t + f["rest"],
                contra_joins=lead,
            )
        )
        arrive = kind
        t += T
        if t > duration_s + 0.5:
            break
    if not strides or (strides[-1].t_next_s < duration_s + _WALK_MARGIN_S and not allow_short):
        walked_s = strides[-1].t_next_s if strides else 0.0
        field = _end_length_field(terrain.kind)
        raise TerrainTooShortError(
            f"terrain too short for a {duration_s:.1f} s trial: its walk ends at "
            f"{walked_s:.2f} s and must go on to {duration_s + _WALK_MARGIN_S:.2f} s "
            f"({_WALK_MARGIN_S:.1f} s past the trial's end, for the last swing); lengthen "
            f"terrain.{field} (about {_metres_per_second(gait):.1f} m per extra second at "
            "this gait) or shorten duration_s",
            field,
        )
    # the final stride needs the next foothold for its swing
    return strides


# --------------------------------------------------------------------------- foot motion


def _landing_pitch(gait: GaitConfig, landing: str, kind: str) -> float:
    if landing == "heel":
        return -np.radians(gait.heel_strike_pitch_deg)
    extra = 6.0 if kind == "descent" else 0.0
    return np.radians(gait.forefoot_landing_pitch_deg + extra)


def _toe_off_pitch(gait: GaitConfig, kind: str) -> float:
    scale = {"level": 1.0, "obstacle": 1.0, "ascent": 0.56, "descent": 0.44}[kind]
    return np.radians(gait.toe_off_pitch_deg) * scale


def _end_length_field(kind: str) -> str:
    """The terrain field that lengthens the walk after the last feature."""
    return "landing_length_m" if kind in ("stair_up", "stair_down") else "exit_length_m"


def _metres_per_second(gait: GaitConfig) -> float:
    """Level walking speed (m/s) of the gait: stride length over stride time."""
    return gait.level_stride_length_m * gait.cadence_scale / gait.level_stride_time_s


def _pitch_function(strides: list[Stride], next_toes: list, gait: GaitConfig) -> BPoly:
    """C2 foot pitch: quintic pieces through the key poses with rate and acceleration."""
    knots: list[tuple[float, float, float]] = []
    for s, _next_toe in zip(strides, next_toes, strict=True):
        th_c = _landing_pitch(gait, s.landing, s.arrive_kind)
        th_to = _toe_off_pitch(gait, s.swing_kind)
        next_landing = "toe" if s.swing_kind in ("ascent", "descent") else "heel"
        th_next = _landing_pitch(gait, next_landing, s.swing_kind)
        t_ms = 0.5 * (s.t_toe_off_s + s.t_next_s)
        th_ms = {"level": -0.05, "obstacle": -0.05, "ascent": -0.2, "descent": 0.25}[s.swing_kind]
        rate = 0.6 * (th_next - th_to) / (s.t_next_s - s.t_toe_off_s)
        # joint_space: the foot still rolls over the toe at toe-off (the ankle leaves moving)
        rate_to = 0.0
        if gait.swing_model == "joint_space":
            rate_to = gait.toe_off_roll_fraction * th_to / (s.t_toe_off_s - s.t_heel_off_s)
        knots += [
            (s.t_contact_s, th_c, 0.0),
            (s.t_flat_s, 0.0, 0.0),
            (s.t_heel_off_s, 0.0, 0.0),
            (s.t_toe_off_s, th_to, rate_to),
            (t_ms, th_ms, rate),
        ]
    last = strides[-1]
    next_landing = "toe" if last.swing_kind in ("ascent", "descent") else "heel"
    knots.append((last.t_next_s, _landing_pitch(gait, next_landing, last.swing_kind), 0.0))
    tk = np.array([k[0] for k in knots])
    yk = [[k[1], k[2], 0.0] for k in knots]
    return BPoly.from_derivatives(tk, yk)


def _smoothstep5(x: NDArray) -> NDArray[np.float64]:
    """C2 ramp 0 -> 1 on [0, 1] (zero 1st and 2nd derivatives at both ends)."""
    x = np.clip(x, 0.0, 1.0)
    return x * x * x * (10.0 + x * (-15.0 + 6.0 * x))


class _SwingPitch:
    """Foot pitch (rad) with an anatomical ankle in swing.

    Outside swing it is the key-pose BPoly; inside swing it blends (C2 weight, zero at
    toe-off and landing) towards shank pitch + ``swing_ankle_deg`` (plantarflexion +), so the
    swing ankle follows the published ranges instead of a pitch chosen without the shank.
    ``shank`` is the shank pitch of the previous iteration (a spline over [t0, t1]).
    """

    def __init__(self, base: BPoly, strides: list[Stride], shank, t_range: tuple, gait):
        self._base = base
        self._shank = shank
        self._t0, self._t1 = t_range
        self._swings = [
            (s.t_toe_off_s, s.t_next_s, np.radians(gait.swing_ankle_deg[s.swing_kind]))
            for s in strides
            if gait.swing_ankle_deg.get(s.swing_kind) is not None
        ]
        self._ramp = gait.swing_ankle_blend_fraction
        self._swing_start_s = np.array([sw[0] for sw in self._swings])
        self._swing_end_s = np.array([sw[1] for sw in self._swings])

    def weight_and_target(self, t: NDArray) -> tuple[NDArray, NDArray]:
        w = np.zeros(t.shape)
        ankle = np.zeros(t.shape)
        swings = self._swings
        if t.size and not np.isnan(t).any():  # only the swings that reach into [min t, max t]
            near = (self._swing_end_s > t.min()) & (self._swing_start_s < t.max())
            swings = [swings[k] for k in np.flatnonzero(near)]  # in order: later ones win
        for t_to, t_nx, a in swings:
            m = (t > t_to) & (t < t_nx)
            if not np.any(m):
                continue
            f = (t[m] - t_to) / (t_nx - t_to)
            w[m] = _smoothstep5(f / self._ramp) * _smoothstep5((1.0 - f) / self._ramp)
            ankle[m] = a
        w[(t < self._t0) | (t > self._t1)] = 0.0
        return w, ankle

    def __call__(self, t_s):
        t = np.asarray(t_s, dtype=float)
        base = self._base(t)
        w, ankle = self.weight_and_target(np.atleast_1d(t))
        w, ankle = w.reshape(t.shape), ankle.reshape(t.shape)
        shank = self._shank(np.clip(t, self._t0, self._t1))
        return base + w * (shank + ankle - base)


def _swing_via(
    s: Stride,
    b: tuple[float, float],
    terrain: Terrain,
    gait: GaitConfig,
    leg: LegModel,
    pitch: BPoly,
) -> tuple[list[float], list[tuple[float, float]]]:
    """Toe via-points (fractions of the swing, positions) from toe-off to the next landing."""
    x0, z0 = s.toe_xz_m
    x1, z1 = b
    heel_to_toe = np.array(leg.toe_in_foot_xz_m) - np.array(leg.heel_in_foot_xz_m)

    def toe_for_heel(frac: float, heel_x: float, heel_z: float) -> tuple[float, float]:
        th = pitch(s.t_toe_off_s + frac * (s.t_next_s - s.t_toe_off_s))
        v = rot_xz(th, heel_to_toe)
        return (heel_x + float(v[0]), heel_z + float(v[1]))

    e = terrain.edges_xz_m
    between = e[(e[:, 0] > x0 - 0.05) & (e[:, 0] < x1 + 0.05)] if e.size else e.reshape(0, 2)
    if s.swing_kind == "level":
        c = gait.toe_clearance_level_m
        d = x1 - x0
        late = toe_for_heel(0.85, x1 - heel_to_toe[0] - 0.06, z1 + 0.02)
        lift = gait.early_swing_toe_lift_m
        return [0.25, 0.55, 0.85], [
            (x0 + 0.18 * d, z0 + lift),
            (x0 + 0.55 * d, z0 + c + 0.005),
            late,
        ]
    if s.swing_kind == "obstacle":
        c = gait.toe_clearance_obstacle_m
        xa, xb = between[:, 0].min(), between[:, 0].max()
        h = between[:, 1].max()
        over = toe_for_heel(0.7, xb + 0.05, h + 0.06)
        late = toe_for_heel(0.88, x1 - heel_to_toe[0] - 0.04, z1 + 0.03)
        return [0.3, 0.5, 0.7, 0.88], [(xa - 0.06, h + 0.8 * c), (xb + 0.06, h + c), over, late]
    c = gait.toe_clearance_nosing_m
    if s.swing_kind == "ascent":
        up = between[(between[:, 1] > z0 + 0.01) & (between[:, 1] <= z1 + 0.01)]
        xs = up[:, 0]
        first_x = xs.min()
        fr = [0.28]
        pts = [(max(x0 - 0.01, first_x - 0.08), up[:, 1].min() + c)]
        if len(xs) > 1:
            fr.append(0.58)
            pts.append((xs.max() - 0.03, z1 + c))
        fr.append(0.84)
        pts.append((x1 - 0.04, z1 + 0.035))
        return fr, pts
    # descent: own tread edge first, then each lower edge
    # window wider behind the toe: on short treads the toe overhangs its own nosing
    near = e[(e[:, 0] > x0 - 0.1) & (e[:, 0] < x1 + 0.05)] if e.size else e.reshape(0, 2)
    down = near[(near[:, 1] <= z0 + 0.01) & (near[:, 1] > z1 + 0.01)]
    xs = np.sort(down[:, 0])
    fr = [0.22]
    pts = [(max(x0 + 0.03, xs.min() + 0.05), z0 + 0.03)]
    if len(xs) > 1:
        fr.append(0.52)
        pts.append((xs.max() + 0.05, z1 + (z0 - z1) / len(xs) + c))
    fr.append(0.8)
    pts.append((x1 - 0.01, z1 + 0.05))
    return fr, pts


def _swing_lift(spl, pitch, s: Stride, terrain: Terrain, heel_f: NDArray, toe_f: NDArray):
    """Vertical lift (callable of t) of a swing whose sole would cut the terrain (high risers,
    short treads: the heel clips a nosing), else None. The lift is a C2 bump (zero rate and
    acceleration at toe-off and landing) scaled so the sole clears the terrain by 1 cm; it is
    computed on a fixed sampling of the swing, so it does not depend on the caller's grid."""
    t0, t1 = s.t_toe_off_s, s.t_next_s
    f = np.linspace(0.0, 1.0, 201)
    ts = t0 + f * (t1 - t0)
    th = pitch(ts)
    toe = spl(ts)
    heel = toe + rot_xz(th, heel_f - toe_f)
    w_sole = np.linspace(0.0, 1.0, 12)
    sole = heel[:, None, :] * (1 - w_sole[None, :, None]) + toe[:, None, :] * w_sole[None, :, None]
    gap = (sole[..., 1] - terrain.height_at(sole[..., 0].ravel()).reshape(sole.shape[:2])).min(1)
    if gap.min() > -1e-4:
        return None
    ramp = 0.3

    def bump(x: NDArray) -> NDArray:
        return _smoothstep5(x / ramp) * _smoothstep5((1.0 - x) / ramp)

    bad = gap < 0.0
    need = (0.01 - gap[bad]) / np.maximum(bump(f[bad]), 0.25)
    height = float(need.max())
    return lambda tt: height * bump((np.asarray(tt) - t0) / (t1 - t0))


class _TimeSpans:
    """The samples of a time grid t (N,) in [a, b) (or [a, b] with ``closed``): the boolean
    mask ``(t >= a) & (t < b)``, or, when t is sorted (the dense grids are), the same samples
    as a slice found by bisection (O(log N) instead of O(N) per stride phase)."""

    def __init__(self, t: NDArray) -> None:
        self._t = t
        self._sorted = bool(t.size == 0 or np.all(t[1:] >= t[:-1]))  # False with NaN

    def __call__(self, a: float, b: float, closed: bool = False) -> slice | NDArray[np.bool_]:
        t = self._t
        if not self._sorted:
            return (t >= a) & ((t <= b) if closed else (t < b))
        lo = int(np.searchsorted(t, a, side="left"))
        hi = int(np.searchsorted(t, b, side="right" if closed else "left"))
        return slice(lo, max(lo, hi))


def _foot_motion(
    t: NDArray,
    strides: list[Stride],
    next_toes: list,
    terrain: Terrain,
    gait: GaitConfig,
    leg: LegModel,
    pitch: BPoly,
) -> NDArray[np.float64]:
    """Ankle (N, 2) on the dense grid from the pivots (contact) and toe splines (swing)."""
    heel_f = np.array(leg.heel_in_foot_xz_m)
    toe_f = np.array(leg.toe_in_foot_xz_m)
    th = pitch(t)
    ankle = np.full((t.size, 2), np.nan)
    span = _TimeSpans(t)
    for s, b in zip(strides, next_toes, strict=True):
        toe_p = np.array(s.toe_xz_m)
        ankle_flat = toe_p - toe_f
        heel_p = ankle_flat + heel_f
        piv_land = heel_p if s.landing == "heel" else toe_p
        r_land = heel_f if s.landing == "heel" else toe_f
        m = span(s.t_contact_s, s.t_flat_s)
        ankle[m] = piv_land - rot_xz(th[m], r_land)
        m = span(s.t_flat_s, s.t_heel_off_s)
        ankle[m] = ankle_flat
        m = span(s.t_heel_off_s, s.t_toe_off_s)
        ankle[m] = toe_p - rot_xz(th[m], toe_f)
        fr, pts = _swing_via(s, b, terrain, gait, leg, pitch)
        next_landing = "toe" if s.swing_kind in ("ascent", "descent") else "heel"
        b_arr = np.array(b)
        th_next = pitch(s.t_next_s)
        if next_landing == "heel":
            toe_land = (b_arr - toe_f + heel_f) + rot_xz(th_next, toe_f - heel_f)
        else:
            toe_land = b_arr
        dur = s.t_next_s - s.t_toe_off_s
        ts = np.concatenate([[s.t_toe_off_s], s.t_toe_off_s + dur * np.asarray(fr), [s.t_next_s]])
        ps = np.vstack([toe_p, np.asarray(pts), toe_land])
        zero = np.zeros(2)
        spl = make_interp_spline(
            ts, ps, k=5, bc_type=([(1, zero), (2, zero)], [(1, zero), (2, zero)])
        )
        m = span(s.t_toe_off_s, s.t_next_s + 1e-12, closed=True)
        lift = _swing_lift(spl, pitch, s, terrain, heel_f, toe_f)
        ankle[m] = spl(t[m]) - rot_xz(th[m], toe_f)
        if lift is not None:
            ankle[m, 1] += lift(t[m])
    if np.any(np.isnan(ankle)):
        raise SimulationError("foot motion does not cover the trial")
    return ankle


# --------------------------------------------------------------------------- hip and IK


def _leg_distance(leg: LegModel, knee_rad: float) -> float:
    """Hip-ankle distance for a knee flexion (law of cosines)."""
    a, b = leg.thigh_length_m, leg.shank_length_m
    return float(np.sqrt(a * a + b * b + 2 * a * b * np.cos(knee_rad)))


def _hip_path(
    t: NDArray,
    ankle: NDArray,
    strides: list[Stride],
    gait: GaitConfig,
    leg: LegModel,
    pitch: BPoly,
) -> NDArray[np.float64]:
    """Hip (N, 2): C2 splines through key positions from knee-flexion targets."""
    toe_f = np.array(leg.toe_in_foot_xz_m)
    heel_f = np.array(leg.heel_in_foot_xz_m)

    def landing_ankle(toe_xz, landing: str, kind: str) -> NDArray:
        th = _landing_pitch(gait, landing, kind)
        toe = np.array(toe_xz)
        if landing == "heel":
            return toe - toe_f + heel_f - rot_xz(th, heel_f)
        return toe - rot_xz(th, toe_f)

    kx_t, kx_v = [], []
    for s in strides:
        k_in = _kind_class(s.swing_kind)
        k_c = _kind_class(s.contra_kind)
        kx_t += [s.t_mid_s, s.t_contra_mid_s]
        kx_v += [
            s.toe_xz_m[0] - toe_f[0] + gait.hip_ahead_midstance_m[k_in],
            s.contra_toe_xz_m[0] - toe_f[0] + gait.hip_ahead_midstance_m[k_c],
        ]
    # extrapolate one key before the start so the spline is well-behaved at t = 0
    v0 = (kx_v[1] - kx_v[0]) / (kx_t[1] - kx_t[0])
    kx_t = [kx_t[0] - 0.5, *kx_t]
    kx_v = [kx_v[0] - 0.5 * v0, *kx_v]
    hip_x = CubicSpline(kx_t, kx_v, bc_type="natural")

    kz: dict[float, float] = {}
    for s in strides:
        k_in, k_c = _kind_class(s.swing_kind), _kind_class(s.contra_kind)
        arr = _kind_class(s.arrive_kind)
        items = [
            (
                s.t_contact_s,
                landing_ankle(s.toe_xz_m, s.landing, s.arrive_kind),
                gait.knee_contact_deg[arr],
            ),
            (s.t_mid_s, np.array(s.toe_xz_m) - toe_f, gait.knee_midstance_deg[k_in]),
            (
                s.t_contra_contact_s,
                landing_ankle(s.contra_toe_xz_m, s.contra_landing, s.contra_kind),
                gait.knee_midstance_deg[k_c] if s.contra_joins else gait.knee_contact_deg[k_c],
            ),
            (s.t_contra_mid_s, np.array(s.contra_toe_xz_m) - toe_f, gait.knee_midstance_deg[k_c]),
        ]
        for tk, a, knee_deg in items:
            d = _leg_distance(leg, np.radians(knee_deg))
            dx = float(hip_x(tk)) - a[0]
            kz[tk] = a[1] + np.sqrt(max(d * d - dx * dx, (0.5 * d) ** 2))
    L = leg.thigh_length_m + leg.shank_length_m
    hx = hip_x(t)
    keys = sorted(kz)
    hz = CubicSpline(keys, [kz[k] for k in keys], bc_type="natural")(t)
    # repair: lower the hip smoothly where the instrumented leg would overstretch. The drop is
    # dilated over +-3 sigma and Gaussian-smoothed, so it still covers every violation.
    sigma_n = int(0.04 * DENSE_RATE_HZ)
    for _ in range(6):
        target = REPAIR_REACH_FRACTION * L
        dx = hx - ankle[:, 0]
        z_ok = ankle[:, 1] + np.sqrt(np.maximum(target**2 - dx * dx, 0.0))
        drop = np.maximum(hz - z_ok, 0.0)
        if not np.any(drop > 0):
            break
        drop = maximum_filter1d(drop, size=6 * sigma_n + 1, mode="nearest")
        hz = hz - gaussian_filter1d(drop, sigma_n, mode="nearest", truncate=3.0)
    ratio = np.hypot(hx - ankle[:, 0], hz - ankle[:, 1]) / L
    if ratio.max() >= MAX_REACH_FRACTION:
        raise SimulationError(f"hip-ankle distance {ratio.max():.3f} of the leg length")
    return np.stack([hx, hz], axis=1)


def _two_link_ik(
    hip: NDArray, ankle: NDArray, leg: LegModel
) -> tuple[NDArray[np.float64], NDArray[np.float64]]:
    """Knee position (N, 2) with the knee ahead of the hip-ankle line, and the reach ratio."""
    a, b = leg.thigh_length_m, leg.shank_length_m
    v = ankle - hip
    d = np.linalg.norm(v, axis=1)
    ratio = d / (a + b)
    if np.any(ratio >= 0.99) or np.any(d <= abs(a - b) + 1e-6):
        raise SimulationError(f"unreachable pose: max hip-ankle/leg = {ratio.max():.3f}")
    cos_al = np.clip((a * a + d * d - b * b) / (2 * a * d), -1.0, 1.0)
    al = np.arccos(cos_al)
    u = v / d[:, None]
    # rotate the hip->ankle direction towards +x (knee forward): angle -al about +y in x-z
    c, s = np.cos(al), np.sin(al)
    # rotation that turns a downward vector forward: x' = c x - s z, z' = s x + c z
    knee = hip + a * np.stack([c * u[:, 0] - s * u[:, 1], s * u[:, 0] + c * u[:, 1]], axis=1)
    return knee, ratio


def _spline(t: NDArray, y: NDArray):
    return make_interp_spline(t, y, k=5)


class _Evaluator:
    """Callable (t, deriv) -> values for a scipy BSpline."""

    def __init__(self, spl) -> None:
        self._spl = spl

    def __call__(self, t_s: NDArray, deriv: int = 0) -> NDArray[np.float64]:
        t = np.asarray(t_s, dtype=float)
        return self._spl(t, nu=deriv) if deriv else self._spl(t)


# --------------------------------------------------------------------------- joint-space swing

_END_FIT_S = 0.015  # stance samples used for the joint state at toe-off / landing
_LIFT_RAMP = 0.3  # the clearance bump ramps up / down over this fraction of the swing
_SOLE_MARGIN_M = 0.01  # the sole clears the terrain by this much where it would touch it
_EDGE_WINDOW = (0.1, 0.85)  # toe crossings of edges in this part of the swing get the clearance
_EARLY_SWING = 0.3  # the toe's first clearance comes from the foot pitch up to here
_EARLY_TOE_GAP_M = 0.004  # ... which keeps the sole this far above the ground
# terminal-swing via point by swing kind: (fraction of the swing, ankle offset from its
# landing position (x, z) in m); the late via points of the via-point swing
_TERMINAL_VIA = {
    "level": (0.85, (-0.06, 0.02)),
    "obstacle": (0.88, (-0.04, 0.03)),
    "ascent": (0.84, (-0.04, 0.035)),
    "descent": (0.8, (-0.01, 0.05)),
}
_FALLBACK_REACH = 0.988  # a joint-space swing reaching further (hard limit 0.99) keeps via points
_MAX_SWING_KNEE_DEG = 140.0  # a swing that would need more knee flexion keeps its via points
_THIGH_LEAD = 0.45  # share of the thigh's excursion done at the knee peak (0.35-0.55 tried)
_THIGH_LEAD_OBSTACLE = 1.5  # over an obstacle the hip flexes past its landing pitch (1.1-2.0 tried)
_THIGH_PEAK_RATE = 1.5  # thigh rate there / its mean rate up to the terminal via point


def _end_state(t: NDArray, y: NDArray, t_ev: float, side: int) -> NDArray[np.float64] | None:
    """Value, rate and acceleration of the samples y (N,) at t_ev from a quartic fitted to
    the samples on one side (side -1: [t_ev - _END_FIT_S, t_ev], +1: [t_ev, t_ev + ...]);
    None when there are too few samples there."""
    lo, hi = (t_ev - _END_FIT_S, t_ev) if side < 0 else (t_ev, t_ev + _END_FIT_S)
    i0, i1 = np.searchsorted(t, [lo, hi])
    if i1 - i0 < 12:
        return None
    p = np.polynomial.polynomial.polyfit(t[i0:i1] - t_ev, y[i0:i1], 4)
    return np.array([p[0], p[1], 2.0 * p[2]])


def _knee_peak_acc(k0: float, k_pk: float, k1: float, t0: float, t_pk: float, t1: float) -> float:
    """Knee acceleration at the peak: that of the flatter of the two parabolas with zero rate
    at the peak through the toe-off and landing values (no overshoot on either side)."""
    c = min((k_pk - k0) / (t_pk - t0) ** 2, (k_pk - k1) / (t1 - t_pk) ** 2)
    return -2.0 * max(c, 0.0)


def _lift_bump(x: NDArray, x_end: float) -> NDArray[np.float64]:
    """C2 plateau bump on the swing fraction x (0 with zero rate and acceleration at toe-off
    and from ``x_end`` on, the terminal-swing via point: the landing approach is left to it)."""
    return _smoothstep5(x / _LIFT_RAMP) * _smoothstep5((x_end - x) / _LIFT_RAMP)


def _knee_profile(
    k0: NDArray,
    k1: NDArray,
    k_pk: float,
    t0: float,
    t_pk: float,
    t1: float,
    terminal: tuple[float, float] | None,
) -> BPoly:
    """Swing knee flexion (rad, C2 quintic pieces) from the toe-off state k0 (value, rate,
    acceleration) through the peak k_pk (zero rate) at t_pk, then (``terminal`` = (time,
    flexion)) through the terminal-swing flexion that holds the ankle above its landing
    height, to the landing state k1."""
    k_pk = max(k_pk, k0[0], k1[0])
    ts = [t0, t_pk]
    ys = [list(k0), [k_pk, 0.0, _knee_peak_acc(k0[0], k_pk, k1[0], t0, t_pk, t1)]]
    if terminal is not None:
        t_v, k_v = terminal
        ts.append(t_v)
        ys.append(_via_to_landing(k_v, k1, t1 - t_v))
    ts.append(t1)
    ys.append(list(k1))
    return BPoly.from_derivatives(ts, ys)


def _terminal_pose(hip_xz: NDArray, ankle_xz: NDArray, leg: LegModel) -> tuple[float, float] | None:
    """Thigh pitch and knee flexion (rad) that put the ankle at ``ankle_xz`` below a hip at
    ``hip_xz`` (knee forward); None when out of the leg's reach (REPAIR_REACH_FRACTION)."""
    a, b = leg.thigh_length_m, leg.shank_length_m
    d = float(np.hypot(*(ankle_xz - hip_xz)))
    if not abs(a - b) + 0.05 < d < REPAIR_REACH_FRACTION * (a + b):
        return None
    knee, _ = _two_link_ik(hip_xz[None], ankle_xz[None], leg)
    thigh = float(np.arctan2(hip_xz[0] - knee[0, 0], hip_xz[1] - knee[0, 1]))
    shank = float(np.arctan2(knee[0, 0] - ankle_xz[0], knee[0, 1] - ankle_xz[1]))
    return thigh, shank - thigh


def _via_to_landing(v: float, y1: NDArray, dt: float) -> list[float]:
    """State (value, rate, acceleration) at a via point ``dt`` before a landing state y1 that
    reaches it with a constant acceleration."""
    r = 2.0 * (y1[0] - v) / dt - y1[1]
    return [v, r, (y1[1] - r) / dt]


class _ToeUpPitch:
    """A swing foot pitch with a C2 toe-up correction in early swing (rad, per swing window:
    zero at toe-off with zero rate and acceleration, full at 15 % of the swing, gone at 45 %)."""

    def __init__(self, pitch, windows_s: tuple, toe_up_rad: tuple) -> None:
        self._pitch = pitch
        self._fix = [(t0, t1, d) for (t0, t1), d in zip(windows_s, toe_up_rad, strict=True) if d]

    def __call__(self, t_s):
        t = np.asarray(t_s, dtype=float)
        out = self._pitch(t)
        for t0, t1, d in self._fix:
            out = out - d * _toe_up_shape((t - t0) / (t1 - t0))
        return out


def _toe_up_shape(f: NDArray) -> NDArray[np.float64]:
    """Shape of the early-swing toe-up correction on the swing fraction f: C2, 0 at toe-off,
    1 at 15 % of the swing, 0 again from 45 %."""
    return _smoothstep5(f / 0.15) * _smoothstep5((0.45 - f) / 0.3)


@dataclass(frozen=True)
class _JointSpaceSwing:
    """The swing ankle of ``gait.swing_model = joint_space`` over the motion-time grid:
    ``ankle`` (C5 spline) replaces the via-point ankle strictly inside each swing window."""

    windows_s: tuple[tuple[float, float], ...]
    ankle: object  # BSpline of the ankle (2,) over the motion-time grid

    def apply(self, t: NDArray, ankle: NDArray) -> NDArray[np.float64]:
        out = ankle.copy()
        for t0, t1 in self.windows_s:
            m = (t > t0) & (t < t1)
            if np.any(m):
                out[m] = self.ankle(t[m])
        return out


def _edge_requirements(
    s: Stride, terrain: Terrain, gait: GaitConfig
) -> list[tuple[float, float, float]]:
    """(edge x, edge z, clearance) of the edges the toe passes over in this swing."""
    e = terrain.edges_xz_m
    if not e.size:
        return []
    x0, x1 = s.toe_xz_m[0], s.next_toe_xz_m[0]
    c = gait.toe_clearance_obstacle_m if s.swing_kind == "obstacle" else gait.toe_clearance_nosing_m
    return [(float(x), float(z), c) for x, z in e if x0 < x < x1]


def _swing_shortfall(
    t: NDArray,
    hip: NDArray,
    ankle: NDArray,
    th: NDArray,
    s: Stride,
    terrain: Terrain,
    gait: GaitConfig,
    leg: LegModel,
) -> tuple[float, float]:
    """The lift (m, at the bump's plateau) the swing samples (t, ankle, foot pitch th) need:
    the sole at least _SOLE_MARGIN_M above the terrain where it would touch it, the toe
    the configured clearance above the edges it passes over (at least over each; negative,
    i.e. lower the swing, when it clears all of them by more) and above level ground in
    mid-swing; and the toe-up pitch correction (rad) that keeps the sole above the ground in
    early swing (f < _EARLY_SWING: the toe just off the ground gets a little less
    plantarflexion, not a fast lift of the leg)."""
    heel_f = np.array(leg.heel_in_foot_xz_m)
    toe_f = np.array(leg.toe_in_foot_xz_m)
    f = (t - s.t_toe_off_s) / (s.t_next_s - s.t_toe_off_s)
    f_end = _TERMINAL_VIA[s.swing_kind][0]
    w = np.maximum(_lift_bump(f, f_end), 0.25)
    heel = ankle + rot_xz(th, heel_f)
    toe = ankle + rot_xz(th, toe_f)
    fr = np.linspace(0.0, 1.0, 12)
    sole = heel[:, None, :] * (1 - fr[None, :, None]) + toe[:, None, :] * fr[None, :, None]
    gap = (sole[..., 1] - terrain.height_at(sole[..., 0].ravel()).reshape(sole.shape[:2])).min(1)
    need = 0.0
    early = f < _EARLY_SWING
    # early swing: the toe-up correction (shape _toe_up_shape, about 0.15 m of toe per rad)
    g = _toe_up_shape(f)
    ok = early & (g > 0.2)
    toe_up = 0.0
    if np.any(ok):
        toe_up = max(0.0, float(((_EARLY_TOE_GAP_M * g[ok] - gap[ok]) / (0.15 * g[ok])).max()))
    bad = (gap < -1e-5) & ~early
    if np.any(bad):
        need = max(need, float(((_SOLE_MARGIN_M - gap[bad]) / w[bad]).max()))
    mid = (f >= _EDGE_WINDOW[0]) & (f <= _EDGE_WINDOW[1])
    excess = np.inf  # the smallest surplus over an edge's clearance, per unit of lift
    for xe, ze, c in _edge_requirements(s, terrain, gait):
        # crossings of x = xe by the toe (sign changes), linearly interpolated
        d = toe[:, 0] - xe
        k = np.flatnonzero((d[:-1] < 0) & (d[1:] >= 0))
        for i in k:
            a = -d[i] / (d[i + 1] - d[i])
            fc = f[i] + a * (f[i + 1] - f[i])
            if not _EDGE_WINDOW[0] <= fc <= _EDGE_WINDOW[1]:
                continue
            zc = toe[i, 1] + a * (toe[i + 1, 1] - toe[i, 1])
            wc = max(float(_lift_bump(np.array(fc), f_end)), 0.25)
            if zc - ze < c:
                need = max(need, (c - (zc - ze)) / wc)
            excess = min(excess, (zc - ze - c) / wc)
    if s.swing_kind == "level":
        lm = mid & (f >= 0.4) & (f <= 0.7)
        if np.any(lm):
            clear = toe[lm, 1] - terrain.height_at(toe[lm, 0])
            short = gait.toe_clearance_level_m - clear
            if short.max() > 0:
                need = max(need, float((short / w[lm]).max()))
    if need <= 0.0 and np.isfinite(excess) and excess > 0.0:
        # more than the configured clearance over every edge: lower the swing to it, as far
        # as the sole keeps its margin above the terrain in mid-swing
        room = np.where(early, gap - _EARLY_TOE_GAP_M * g, gap - _SOLE_MARGIN_M)
        late = f > _EDGE_WINDOW[1]  # the foot coming down to its landing: half its gap
        room[late] = 0.5 * gap[late]
        # ... and as far as the leg reaches (REPAIR_REACH_FRACTION of thigh + shank)
        reach = REPAIR_REACH_FRACTION * (leg.thigh_length_m + leg.shank_length_m)
        dx = hip[:, 0] - ankle[:, 0]
        drop = np.sqrt(np.maximum(reach**2 - dx * dx, 0.0)) - (hip[:, 1] - ankle[:, 1])
        room = np.minimum(room, drop)
        wb = _lift_bump(f, f_end)
        eff = wb > 0.05  # where the bump moves the foot
        room_per_lift = float((room[eff] / wb[eff]).min()) if np.any(eff) else 0.0
        need = -max(0.0, min(excess, room_per_lift))
    return need, toe_up


def _joint_space_swing(
    t: NDArray,
    hip: NDArray,
    ankle_vp: NDArray,
    strides: list[Stride],
    terrain: Terrain,
    gait: GaitConfig,
    leg: LegModel,
    base_pitch: BPoly,
) -> tuple[_JointSpaceSwing, _ToeUpPitch]:
    """Joint-space swings on the uniform motion-time grid t (N,) with the hip path (N, 2) and
    the via-point ankle (N, 2) (whose stance samples are the stance): thigh and knee angles
    are C2 quintics (BPoly) from the toe-off state to the landing state through the peak knee
    flexion, the ankle follows by forward kinematics, and a C2 bump raises it (inverse
    kinematics: more hip and knee flexion) where the sole would miss its clearance. Returns
    the swing ankle and the foot pitch (swing-ankle rule on the new shank)."""
    a, b = leg.thigh_length_m, leg.shank_length_m
    knee_vp, _ = _two_link_ik(hip, ankle_vp, leg)
    thigh = np.arctan2(hip[:, 0] - knee_vp[:, 0], hip[:, 1] - knee_vp[:, 1])
    knee_flex = np.arctan2(knee_vp[:, 0] - ankle_vp[:, 0], knee_vp[:, 1] - ankle_vp[:, 1]) - thigh
    ankle = ankle_vp.copy()
    span = _TimeSpans(t)
    windows: list[tuple[float, float, slice | NDArray]] = []
    for s in strides:
        t0, t1 = s.t_toe_off_s, s.t_next_s
        m = span(t0 + 1e-9, t1)
        if t0 >= t[-1] or (isinstance(m, slice) and m.stop <= m.start):
            continue
        th0, k0 = _end_state(t, thigh, t0, -1), _end_state(t, knee_flex, t0, -1)
        th1, k1 = _end_state(t, thigh, t1, +1), _end_state(t, knee_flex, t1, +1)
        if th0 is None:
            continue  # toe-off before the grid's start: keep the via-point swing
        if th1 is None:  # no stance after the last landing: the via-point swing's arrival
            th1, k1 = _end_state(t, thigh, t1, -1), _end_state(t, knee_flex, t1, -1)
            if th1 is None:
                continue
        frac = gait.swing_peak_knee_fraction.get(s.swing_kind, 0.33)
        k_pk = np.radians(gait.swing_peak_knee_deg[s.swing_kind])
        t_pk = t0 + frac * (t1 - t0)
        # terminal swing: a joint-space via point from the ankle a little behind and above
        # its landing position (inverse kinematics under the hip there)
        f_v, offset = _TERMINAL_VIA[s.swing_kind]
        t_v = t0 + f_v * (t1 - t0)
        i_v = min(int(np.searchsorted(t, t_v)), t.size - 1)
        i_1 = min(int(np.searchsorted(t, t1)), t.size - 1)
        pose = _terminal_pose(hip[i_v], ankle_vp[i_1] + np.array(offset), leg)
        # the thigh swings forward fastest around the knee peak (hip flexion leads the knee's
        # extension): a C2 via point there, at _THIGH_LEAD of its excursion, at its peak rate
        th_end = th1[0] if pose is None else pose[0]
        d_th = th_end - th0[0]
        ts = [t0, t_pk]
        lead = _THIGH_LEAD_OBSTACLE if s.swing_kind == "obstacle" else _THIGH_LEAD
        ys = [th0, [th0[0] + lead * d_th, _THIGH_PEAK_RATE * d_th / (t_v - t0), 0.0]]
        if pose is not None:
            ts.append(t_v)
            ys.append(_via_to_landing(pose[0], th1, t1 - t_v))
        thigh_p = BPoly.from_derivatives([*ts, t1], [*ys, th1])
        knee_p = _knee_profile(k0, k1, k_pk, t0, t_pk, t1, None if pose is None else (t_v, pose[1]))
        tt = t[m]
        th_t = thigh_p(tt)
        sh_t = th_t + knee_p(tt)
        knee_xz = hip[m] - a * np.stack([np.sin(th_t), np.cos(th_t)], axis=1)
        ankle_s = knee_xz - b * np.stack([np.sin(sh_t), np.cos(sh_t)], axis=1)
        if np.linalg.norm(ankle_s - hip[m], axis=1).max() > _FALLBACK_REACH * (a + b):
            continue  # the knee profile would straighten the leg too far: via points
        ankle[m] = ankle_s
        windows.append((t0, t1, m))
    ankle_fk = ankle.copy()
    lift = np.zeros(len(windows))
    toe_up = np.zeros(len(windows))
    by_toe_off = {s.t_toe_off_s: s for s in strides}

    def swing_pitch(ankle: NDArray) -> _ToeUpPitch:
        knee, _ = _two_link_ik(hip, ankle, leg)
        shank = np.arctan2(knee[:, 0] - ankle[:, 0], knee[:, 1] - ankle[:, 1])
        sp = _SwingPitch(
            base_pitch, strides, make_interp_spline(t, shank, k=5), (t[0], t[-1]), gait
        )
        return _ToeUpPitch(sp, tuple((w[0], w[1]) for w in windows), tuple(toe_up.tolist()))

    a_b = leg.thigh_length_m + leg.shank_length_m
    d_min = _leg_distance(leg, np.radians(_MAX_SWING_KNEE_DEG))
    failed: set[int] = set()  # swings that keep their via points

    def lifted() -> NDArray:
        out = ankle_fk.copy()
        for j, (t0, t1, m) in enumerate(windows):
            if j in failed:
                out[m] = ankle_vp[m]
                toe_up[j] = 0.0
            else:
                f_end = _TERMINAL_VIA[by_toe_off[t0].swing_kind][0]
                out[m, 1] += lift[j] * _lift_bump((t[m] - t0) / (t1 - t0), f_end)
        return out

    def shortfalls(pitch) -> list[tuple[float, float]]:
        th = pitch(t)
        return [
            (0.0, 0.0)
            if j in failed
            else _swing_shortfall(t[m], hip[m], ankle[m], th[m], by_toe_off[t0], terrain, gait, leg)
            for j, (t0, _t1, m) in enumerate(windows)
        ]

    pitch = swing_pitch(ankle)
    for _ in range(12):
        grew = False
        for j, (need, more_toe_up) in enumerate(shortfalls(pitch)):
            if abs(need) > 5e-4 or need > 1e-4:
                lift[j] += need
                grew = True
            if more_toe_up > 2e-3:
                toe_up[j] += more_toe_up
                grew = True
        if not grew:
            break
        ankle = lifted()
        for j, (_t0, _t1, m) in enumerate(windows):  # too bent or too straight: via points
            d = np.linalg.norm(ankle[m] - hip[m], axis=1)
            if d.min() < d_min or d.max() > _FALLBACK_REACH * a_b:
                failed.add(j)
        ankle = lifted()
        pitch = swing_pitch(ankle)
    else:  # not converged: the swings still short of their clearance keep their via points
        for j, (need, more_toe_up) in enumerate(shortfalls(pitch)):
            if need > 2e-3 or more_toe_up > 2e-2:
                failed.add(j)
        ankle = lifted()
        pitch = swing_pitch(ankle)
    spl = make_interp_spline(t, ankle, k=5)
    kept = [j for j in range(len(windows)) if j not in failed]
    js = _JointSpaceSwing(tuple((windows[j][0], windows[j][1]) for j in kept), spl)
    return js, pitch


# --------------------------------------------------------------------------- pauses


def _ramp_integral(x: NDArray) -> NDArray[np.float64]:
    """Integral of _smoothstep5 from 0 to x (x clipped to [0, 1]; 0.5 at x = 1)."""
    x = np.clip(x, 0.0, 1.0)
    return x**4 * (2.5 + x * (-3.0 + x))


@dataclass(frozen=True)
class _Pauses:
    """Standing pauses as a time warp: the motion planned in "motion time" tau is replayed in
    real time t with tau(t) = t - sum_k B_k(t), where each pause k slows the motion to rest over
    ``ramp_s`` (C2 smoothstep of the speed), holds it for ``hold_s[k]`` and speeds it up again.
    During a hold the shank sways about the fixed ankle (weight shift)."""

    start_s: NDArray[np.float64]  # real time where pause k starts to decelerate
    hold_s: NDArray[np.float64]
    ramp_s: float
    sway_rad: NDArray[np.float64]
    sway_hz: NDArray[np.float64]

    def tau(self, t_s: NDArray) -> NDArray[np.float64]:
        t = np.asarray(t_s, dtype=float)
        out = t.copy()
        r = self.ramp_s
        for s0, h in zip(self.start_s, self.hold_s, strict=True):
            down = r * _ramp_integral((t - s0) / r)
            hold = np.clip(t - s0 - r, 0.0, h)
            up = r * (0.5 - _ramp_integral((s0 + 2 * r + h - t) / r))
            up = np.where(t > s0 + r + h, up, 0.0)
            out -= down + hold + up
        return out

    def sway(self, t_s: NDArray) -> NDArray[np.float64]:
        """Shank pitch offset (rad) during the holds: a windowed sine (C2, zero outside)."""
        t = np.asarray(t_s, dtype=float)
        out = np.zeros(t.shape)
        for s0, h, a, f in zip(self.start_s, self.hold_s, self.sway_rad, self.sway_hz, strict=True):
            t0 = s0 + self.ramp_s
            m = (t > t0) & (t < t0 + h)
            if h <= 0 or not np.any(m):
                continue
            edge = min(1.0, h / 3.0)
            x = t[m] - t0
            w = _smoothstep5(x / edge) * _smoothstep5((h - x) / edge)
            out[m] += a * w * np.sin(2 * np.pi * f * x)
        return out


def _draw_pauses(strides: list[Stride], gait: GaitConfig, rng: np.random.Generator) -> _Pauses:
    """One pause per stride at its rest instant, lengths uniform in gait.pause_range_s."""
    lo, hi = gait.pause_range_s  # type: ignore[misc]
    rest = np.array([s.t_rest_s for s in strides])
    gaps = np.diff(rest)
    r = min(gait.pause_ramp_s, 0.45 * float(gaps.min())) if gaps.size else gait.pause_ramp_s
    n = rest.size
    hold = rng.uniform(lo, hi, n)
    amp = np.radians(rng.uniform(*gait.pause_sway_deg, n)) * rng.choice([-1.0, 1.0], n)
    hz = rng.uniform(*gait.pause_sway_hz, n)
    keep = rest - 0.5 * r >= 0.0  # no pause before the motion has started
    rest, hold, amp, hz = rest[keep], hold[keep], amp[keep], hz[keep]
    # the hold is centred in tau on the rest instant: it starts decelerating at tau - r / 2
    shift = np.concatenate([[0.0], np.cumsum(hold + r)[:-1]])
    return _Pauses(rest - 0.5 * r + shift, hold, r, amp, hz)


def _retime(s: Stride, to_real) -> Stride:
    names = (
        "t_contact_s",
        "t_flat_s",
        "t_heel_off_s",
        "t_toe_off_s",
        "t_next_s",
        "t_contra_contact_s",
        "t_contra_mid_s",
        "t_mid_s",
        "t_rest_s",
    )
    return replace(s, **{k: float(to_real(getattr(s, k))) for k in names})


def simulate_gait(
    terrain: Terrain,
    gait: GaitConfig,
    rig: RigConfig,
    duration_s: float,
    rng: np.random.Generator,
) -> LegMotion:
    """Plan and generate the instrumented leg's motion over [0, duration_s + 0.2 s]."""
    leg = leg_model_for(rig)
    pausing = gait.pause_range_s is not None
    joint_space = gait.swing_model == "joint_space"
    rng_plan = copy.deepcopy(rng) if joint_space else None  # the same draws, planned again
    strides = plan_strides(terrain, gait, leg, duration_s, rng, allow_short=pausing)
    if rng_plan is not None:  # one more stride, if the terrain has it: the last swing in
        # the trial then lands on the grid (its landing state is known)
        more = plan_strides(terrain, gait, leg, duration_s + 0.6, rng_plan, allow_short=True)
        if len(more) > len(strides):
            strides = more
    pauses = _draw_pauses(strides, gait, rng) if pausing else None
    next_toes = [s.next_toe_xz_m for s in strides]
    base_pitch = _pitch_function(strides, next_toes, gait)
    if pauses is None:
        t_end = min(strides[-1].t_next_s, duration_s + 0.25)
    else:
        t_end = float(pauses.tau(np.array([duration_s + 0.25]))[0]) + 0.01
        if strides[-1].t_next_s < t_end + 0.05:
            field = _end_length_field(terrain.kind)
            raise TerrainTooShortError(
                f"terrain too short for a {duration_s:.1f} s trial with these pauses: "
                f"lengthen terrain.{field}, add steps / flights or shorten duration_s",
                field,
            )
    t_out_end = t_end
    if joint_space:  # the last swing's landing on the grid (cropped to t_end below)
        t_end = max(t_end, np.floor(strides[-1].t_next_s * DENSE_RATE_HZ) / DENSE_RATE_HZ)
    t = np.arange(0.0, t_end + 0.5 / DENSE_RATE_HZ, 1.0 / DENSE_RATE_HZ)
    pitch = base_pitch
    # fixed point: the swing foot pitch depends on the shank, the shank (through the ankle
    # position and the hip) on the foot pitch; the coupling is weak, 3 passes converge
    for _ in range(SWING_PITCH_ITERATIONS + 1):
        ankle = _foot_motion(t, strides, next_toes, terrain, gait, leg, pitch)
        hip = _hip_path(t, ankle, strides, gait, leg, pitch)
        knee, _ = _two_link_ik(hip, ankle, leg)
        shank_it = np.arctan2(knee[:, 0] - ankle[:, 0], knee[:, 1] - ankle[:, 1])
        foot_pitch = pitch(t)
        pitch_used = pitch
        pitch = _SwingPitch(
            base_pitch, strides, make_interp_spline(t, shank_it, k=5), (t[0], t[-1]), gait
        )
    js = None
    pitch_hip = pitch_used  # the hip path is the via-point construction's in both models
    if joint_space:
        js, pitch_used = _joint_space_swing(t, hip, ankle, strides, terrain, gait, leg, base_pitch)
        keep = t <= t_out_end + 0.5 / DENSE_RATE_HZ
        t, hip = t[keep], hip[keep]
        ankle = js.apply(t, ankle[keep])
        knee, _ = _two_link_ik(hip, ankle, leg)
        foot_pitch = pitch_used(t)
    if pauses is not None:  # replay in real time with the pauses, sway during the holds
        tau = t
        t = np.arange(0.0, duration_s + 0.25 + 0.5 / DENSE_RATE_HZ, 1.0 / DENSE_RATE_HZ)
        tau_t = np.minimum(pauses.tau(t), tau[-1])
        # the same construction evaluated at tau(t): contact pivots stay exact
        ankle = _foot_motion(tau_t, strides, next_toes, terrain, gait, leg, pitch_hip)
        hip = _hip_path(tau_t, ankle, strides, gait, leg, pitch_hip)
        if js is not None:
            ankle = js.apply(tau_t, ankle)
        foot_pitch = pitch_used(tau_t)
        knee, _ = _two_link_ik(hip, ankle, leg)
        shank_sway = np.arctan2(knee[:, 0] - ankle[:, 0], knee[:, 1] - ankle[:, 1])
        shank_sway = shank_sway + pauses.sway(t)
        holds = tuple(
            (float(s0 + pauses.ramp_s), float(s0 + pauses.ramp_s + h))
            for s0, h in zip(pauses.start_s, pauses.hold_s, strict=True)
            if s0 + pauses.ramp_s < t[-1]
        )
        knee_sway = ankle + rot_xz(shank_sway, np.array([0.0, leg.shank_length_m]))
        hip = hip + (knee_sway - knee)  # the thigh keeps its pitch: the hip shifts with it
        knee = knee_sway
        reach = np.linalg.norm(hip - ankle, axis=1) / (leg.thigh_length_m + leg.shank_length_m)
        if reach.max() >= MAX_REACH_FRACTION:
            raise SimulationError(f"pause sway overstretches the leg ({reach.max():.3f})")

        def to_real(tau_ev: float) -> float:
            if tau_ev >= tau_t[-1]:
                return float(t[-1] + tau_ev - tau_t[-1])
            return float(np.interp(tau_ev, tau_t, t))

        strides = [_retime(s, to_real) for s in strides]
    thigh_seg = np.arctan2(hip[:, 0] - knee[:, 0], hip[:, 1] - knee[:, 1])
    shank = np.arctan2(knee[:, 0] - ankle[:, 0], knee[:, 1] - ankle[:, 1])
    hip_flex = -thigh_seg
    knee_flex = shank - thigh_seg
    ankle_pf = foot_pitch - shank
    heel = ankle + rot_xz(foot_pitch, np.array(leg.heel_in_foot_xz_m))
    toe = ankle + rot_xz(foot_pitch, np.array(leg.toe_in_foot_xz_m))
    splines = {
        "shank": _Evaluator(_spline(t, shank)),
        "foot": _Evaluator(_spline(t, foot_pitch)),
        "ankle": _Evaluator(_spline(t, ankle)),
        "hip_flex": _Evaluator(_spline(t, hip_flex)),
        "knee": _Evaluator(_spline(t, knee_flex)),
        "ankle_angle": _Evaluator(_spline(t, ankle_pf)),
    }
    return LegMotion(
        leg=leg,
        t_s=t,
        hip_xz_m=hip,
        knee_xz_m=knee,
        ankle_xz_m=ankle,
        heel_xz_m=heel,
        toe_xz_m=toe,
        thigh_pitch_rad=hip_flex,
        knee_rad=knee_flex,
        ankle_rad=ankle_pf,
        shank_pitch_rad=shank,
        foot_pitch_rad=foot_pitch,
        strides=tuple(strides),
        _splines=splines,
        holds_s=holds if pauses is not None else (),
    )
