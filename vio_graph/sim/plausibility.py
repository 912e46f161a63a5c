"""Plausibility check of a simulated leg motion: the shank must not accelerate faster than a
human shank does.

The joint-space swing gives a specific force of 2-11 g at the shank IMU on every sweep
condition and the via-point stress swing up to ~14 g (docs/simulator.md, "Obstacles stepped
over or onto"); shank-mounted accelerometers read a few g in swing and 5-10 g at heel strike
in walking (the simulator has no heel-strike impact). A motion whose IMU specific force peaks
above ``gait.max_shank_specific_force_g`` (:data:`MAX_SHANK_SPECIFIC_FORCE_G` by default) is
a construction failure (a foothold the leg cannot
reach, a swing folded back on itself), not a gait: the trial is refused with an error naming
the terrain or gait parameters of the stride where it happened.
"""

from __future__ import annotations

import numpy as np
from numpy.typing import NDArray

from vio_graph.errors import ImplausibleMotionError
from vio_graph.geometry import GRAVITY_MPS2
from vio_graph.sim.config import GaitConfig
from vio_graph.sim.gait import LegMotion, Stride, steps_onto_obstacle
from vio_graph.sim.terrain import Terrain

#: default bound on the specific force (g) at the shank IMU, analytic at the 1 kHz gait samples
MAX_SHANK_SPECIFIC_FORCE_G: float = GaitConfig.model_fields["max_shank_specific_force_g"].default


def shank_specific_force_g(
    motion: LegMotion, point_in_shank_xz_m: NDArray, duration_s: float
) -> tuple[NDArray[np.float64], NDArray[np.float64]]:
    """Times (N,) of the motion's samples in [0, duration_s] and the norm of the specific force
    (acceleration minus gravity, g) of the shank-fixed point there."""
    t = motion.t_s[motion.t_s <= duration_s]
    a = motion.shank_point(t, np.asarray(point_in_shank_xz_m, dtype=float), 2)
    return t, np.hypot(a[:, 0], a[:, 1] + GRAVITY_MPS2) / GRAVITY_MPS2


def check_plausible_motion(
    motion: LegMotion,
    point_in_shank_xz_m: NDArray,
    duration_s: float,
    terrain: Terrain,
    gait: GaitConfig,
    bound_g: float = MAX_SHANK_SPECIFIC_FORCE_G,
) -> float:
    """The peak specific force (g) of the shank point over [0, duration_s]; raises
    ImplausibleMotionError naming the stride and its parameters when it exceeds ``bound_g``."""
    t, f = shank_specific_force_g(motion, point_in_shank_xz_m, duration_s)
    if not f.size:
        return 0.0
    i = int(np.argmax(f))
    peak = float(f[i])
    if peak <= bound_g:
        return peak
    t_pk = float(t[i])
    stride = _stride_at(motion.strides, t_pk)
    where = "" if stride is None else f" in {_phase(stride, t_pk)}"
    raise ImplausibleMotionError(
        f"implausible shank motion: the specific force at the IMU peaks at {peak:.0f} g at "
        f"t = {t_pk:.2f} s{where} (gait.max_shank_specific_force_g = {bound_g:.0f} g, a human "
        f"shank stays well below it); "
        f"{_cause(terrain, gait)}",
        peak,
        t_pk,
    )


def _stride_at(strides: tuple[Stride, ...], t_s: float) -> Stride | None:
    for s in strides:
        if s.t_contact_s <= t_s < s.t_next_s:
            return s
    return None


def _phase(s: Stride, t_s: float) -> str:
    (x0, z0), (x1, z1) = s.toe_xz_m, s.next_toe_xz_m
    if t_s < s.t_toe_off_s:
        return f"the stance on the foothold at x = {x0:.2f} m, z = {z0:.2f} m"
    return (
        f"the {s.swing_kind} swing from the foothold at x = {x0:.2f} m, z = {z0:.2f} m to "
        f"x = {x1:.2f} m, z = {z1:.2f} m ({x1 - x0:.2f} m of toe travel)"
    )


def _cause(terrain: Terrain, gait: GaitConfig) -> str:
    """The parameters that shape the stride, with what to change."""
    prm = terrain.params
    parts = []
    if terrain.kind == "obstacle":
        size = (
            f"terrain.obstacle_height_m = {prm['height_m']:.2f} m, "
            f"terrain.obstacle_depth_m = {prm['depth_m']:.2f} m"
        )
        if steps_onto_obstacle(terrain, gait):
            parts.append(
                f"the obstacle ({size}) is stepped onto (deeper than "
                f"gait.obstacle_step_on_depth_m = {gait.obstacle_step_on_depth_m:.2f} m): a "
                "lower obstacle gives a plausible step up and down"
            )
        else:
            parts.append(
                f"the obstacle ({size}) is stepped over (not deeper than "
                f"gait.obstacle_step_on_depth_m = {gait.obstacle_step_on_depth_m:.2f} m): "
                "a lower or shallower obstacle, or a smaller gait.obstacle_step_on_depth_m "
                "(step onto it), gives a plausible swing"
            )
    elif terrain.kind in ("stair_up", "stair_down"):
        parts.append(
            f"the stair (terrain.stair_rise_m = {prm['rise_m']:.3f} m, "
            f"terrain.stair_tread_m = {prm['tread_m']:.3f} m) sets the swing's path"
        )
    else:
        parts.append(
            f"the level stride (gait.level_stride_length_m = {gait.level_stride_length_m:.2f} "
            f"m, gait.level_stride_time_s = {gait.level_stride_time_s:.2f} s) is too fast"
        )
    if gait.cadence_scale != 1.0:
        parts.append(
            f"gait.cadence_scale = {gait.cadence_scale:g} (accelerations grow with its square)"
        )
    if gait.swing_model != "joint_space":
        parts.append(f"gait.swing_model = {gait.swing_model} (joint_space is gentler)")
    return "; ".join(parts)
