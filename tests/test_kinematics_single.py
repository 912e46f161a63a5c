"""The online estimator's one-pose kinematics (vio_graph/kinematics.py ``leg_points_single``)
gives the vectorised chain's floats (``knee_from_camera`` then ``leg_points_from_knee``) bit
for bit: knee, ankle, heel and toe over random poses, with the IMU's shank pitch or another
one for the chain below the knee."""

from __future__ import annotations

import numpy as np

from vio_graph.kinematics import (
    LegModel,
    knee_from_camera,
    leg_points_from_knee,
    leg_points_single,
)


def test_single_pose_equals_the_vectorised_chain_bit_for_bit() -> None:
    rng = np.random.default_rng(8)
    n_other = 0
    for k in range(2000):
        leg = LegModel(
            float(rng.uniform(0.3, 0.5)),
            float(rng.uniform(0.3, 0.5)),
            (float(rng.normal(-0.05, 0.02)), float(rng.normal(-0.07, 0.02))),
            (float(rng.normal(0.2, 0.03)), float(rng.normal(-0.07, 0.02))),
        )
        cam = rng.normal(0.0, 2.0, 2)
        cis = rng.normal(0.0, 0.2, 2)
        imu = float(rng.uniform(-np.pi, np.pi)) if k % 7 else float(rng.choice([0.0, -0.0]))
        chain = imu if k % 3 else imu + float(rng.normal(0.0, 0.05))
        ankle = float(rng.normal(0.0, 0.3)) if k % 5 else 0.0
        n_other += chain != imu
        knee = knee_from_camera(cam, imu, cis)
        want = leg_points_from_knee(leg, knee, chain, ankle)
        got = leg_points_single(leg, cam, cis, imu, chain, ankle)
        for name in ("knee_xz_m", "ankle_xz_m", "heel_xz_m", "toe_xz_m"):
            a, b = getattr(got, name), getattr(want, name)
            assert a.shape == b.shape == (1, 2), name
            assert a.tobytes() == b.tobytes(), (k, name, a, b)
    assert n_other > 500  # the chain's own pitch was exercised


def test_rig_one_pose_follows_leg_points_rule_for_the_chain_pitch() -> None:
    """RigGeometry.leg_points_one (the online estimator's) gives RigGeometry.leg_points's
    floats with either source of the shank pitch below the knee."""
    from vio_graph.estimator import RigGeometry
    from vio_graph.geometry import make_transform

    R_s_c = np.array([[0.0, 0.0, 1.0], [-1.0, 0.0, 0.0], [0.0, -1.0, 0.0]])
    leg = LegModel(0.42, 0.4, (-0.05, -0.07), (0.2, -0.07))
    rig = RigGeometry(
        np.eye(3),
        make_transform(R_s_c, [0.02, 0.0, 0.01]),
        make_transform(R_s_c, [0.07, 0.0, -0.05]),
        leg,
    )
    cam, imu, chain, ankle = np.array([0.3, 0.45]), 0.31, 0.27, -0.12
    for use_enc in (False, True):
        want = rig.leg_points(cam, imu, chain, ankle, use_enc)
        got = rig.leg_points_one(cam, imu, chain, ankle, use_enc)
        for name in ("knee_xz_m", "ankle_xz_m", "heel_xz_m", "toe_xz_m"):
            assert getattr(got, name).tobytes() == getattr(want, name).tobytes(), (use_enc, name)
    a = rig.leg_points_one(cam, imu, chain, ankle, False).toe_xz_m
    b = rig.leg_points_one(cam, imu, chain, ankle, True).toe_xz_m
    assert not np.array_equal(a, b)  # the rule picks a different pitch
