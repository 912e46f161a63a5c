"""A smoothed mode's keyframe profiles at that mode's own keyframe attitude
(``FrameLog.profiles_of``), and the safety replay of that mode on them
(vio_graph/evaluation/safety.py ``replay_safety``; docs/method.md, "The smoothed modes' map
and clearance")."""

from __future__ import annotations

import math

import numpy as np

from vio_graph.evaluation.safety import replay_safety
from vio_graph.geometry import rotate_xz
from vio_graph.replay import FrameLog
from vio_graph.safety.config import SafetyConfig

CORR_RAD = math.radians(0.6)  # the refined minus the filter's shank pitch


def _flat_ground_trial(n: int = 90):
    """A camera 1 m above flat ground (z = 0) moving 2 cm a frame, the foot 8 cm above the
    ground below it (no stance); a keyframe profile every other frame, made by a filter
    whose pitch is CORR_RAD below the refined one (which is the true one here)."""
    lg = FrameLog()
    t = np.arange(n) / 30.0
    for v in t:
        lg.t_s.append(float(v))
        lg.shank_pitch_imu.append(0.1)
    cam = np.c_[0.02 * np.arange(n), np.full(n, 1.0)]
    path = {"camera": cam, "heel": cam + [-0.05, -0.92], "toe": cam + [0.15, -0.92]}
    xs = np.linspace(0.3, 1.5, 120)
    true_rel = np.c_[xs, np.full(xs.size, -1.0)]  # the ground seen from the camera
    lg.profiles = {k: rotate_xz(-CORR_RAD, true_rel) for k in range(0, n, 2)}
    lg.shank_pitch_by_mode["smoother"] = np.full(n, 0.1 + CORR_RAD)
    return lg, t, path, [np.eye(2) * 1e-6] * n, [False] * n, true_rel


def test_profiles_of_turns_by_the_modes_pitch_correction():
    """Known answer: each profile turned back by the refined minus the filter's pitch is the
    true camera-relative ground; the filter (no own pitch) gets the profiles as they are,
    and a NaN correction leaves that keyframe's profile as it is."""
    lg, *_, true_rel = _flat_ground_trial()
    turned = lg.profiles_of("smoother")
    assert turned.keys() == lg.profiles.keys()
    for p in turned.values():
        np.testing.assert_allclose(p, true_rel, atol=1e-12)
    assert lg.profiles_of("filter") is lg.profiles
    lg.shank_pitch_by_mode["smoother"][4] = np.nan
    assert lg.profiles_of("smoother")[4] is lg.profiles[4]


def test_replay_at_the_modes_attitude_gives_the_true_clearance():
    """Known answer: the foot 8 cm above flat ground, so the clearance is 8 cm minus the
    sole. The filter's profiles at the refined position (the filter's pitch, 0.6 deg off)
    put the mapped ground up to 1.5 m x 0.6 deg = 16 mm too high (11 mm median error); at
    the mode's own attitude they are exact."""
    cfg = SafetyConfig()
    lg, t, path, cov, stance, _ = _flat_ground_trial()
    want = 0.08 - cfg.sole_thickness_m
    own = replay_safety(cfg, t, path, cov, stance, lg.profiles_of("smoother"))
    as_is = replay_safety(cfg, t, path, cov, stance, lg.profiles)
    c_own, c_as_is = own.column("clearance_m"), as_is.column("clearance_m")
    ok = np.isfinite(c_own)
    assert ok.sum() > 30  # the foot is over mapped ground for most of the trial
    np.testing.assert_allclose(c_own[ok], want, atol=1e-9)
    assert np.median(np.abs(c_as_is[ok] - want)) > 5e-3


def test_profiles_of_is_kept_while_its_inputs_are_the_same():
    """profiles_of turns every keyframe once a mode (the safety replay and the map both ask):
    asked again it returns the same dict, while the turns and the profile arrays are the
    same; a pitch changed in place, a profile replaced or a keyframe added is turned anew,
    and every answer equals a fresh FrameLog's bit for bit."""
    lg, *_ = _flat_ground_trial()
    first = lg.profiles_of("smoother")
    assert lg.profiles_of("smoother") is first

    def fresh() -> dict:
        other = FrameLog()
        other.t_s, other.shank_pitch_imu = lg.t_s, lg.shank_pitch_imu
        other.profiles = dict(lg.profiles)
        other.shank_pitch_by_mode = {"smoother": lg.shank_pitch_by_mode["smoother"].copy()}
        return other.profiles_of("smoother")

    def same(a: dict, b: dict) -> bool:
        return a.keys() == b.keys() and all(np.array_equal(a[k], b[k]) for k in a)

    lg.shank_pitch_by_mode["smoother"][6] += 1e-3  # in place: the same array object
    changed = lg.profiles_of("smoother")
    assert changed is not first and same(changed, fresh())
    assert not np.array_equal(changed[6], first[6]) and changed[8] is not first[8]
    lg.profiles[8] = lg.profiles[8] + 1e-3  # a profile replaced by another array
    replaced = lg.profiles_of("smoother")
    assert replaced is not changed and same(replaced, fresh())
    lg.t_s.append(3.0)
    lg.shank_pitch_imu.append(0.1)
    lg.shank_pitch_by_mode["smoother"] = np.append(lg.shank_pitch_by_mode["smoother"], 0.2)
    lg.profiles[90] = lg.profiles[0]
    added = lg.profiles_of("smoother")
    assert added is not replaced and 90 in added and same(added, fresh())
    assert lg.profiles_of("smoother") is added
