import numpy as np

from vio_graph.keyframes import KeyframeConfig, KeyframeSelector


def test_keyframes_by_displacement_and_time() -> None:
    sel = KeyframeSelector(KeyframeConfig(min_displacement_m=0.01, max_interval_s=0.25))
    assert sel.is_keyframe(0.0, np.zeros(2))
    assert not sel.is_keyframe(0.033, np.array([0.005, 0.0]))  # 5 mm: too little
    assert sel.is_keyframe(0.066, np.array([0.012, 0.0]))  # 12 mm since last keyframe
    assert not sel.is_keyframe(0.1, np.array([0.013, 0.0]))
    assert sel.is_keyframe(0.4, np.array([0.013, 0.0]))  # standing still, forced by time
    assert sel.is_keyframe(0.433, np.array([0.2, 0.0]))  # a big jump is still a keyframe
    assert sel.count == 4 and sel.over_max == 1
