import numpy as np
import pytest
from pydantic import ValidationError

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


def _stance_between_keyframes(stance_keyframes: int) -> tuple[list[bool], KeyframeSelector]:
    """30 fps, a camera moving 3 mm per frame (a keyframe every 4th frame by displacement)
    and a stance anchored at frames 5-8 (stance id 7): frames 5-7 fall between the
    keyframes 4 and 8."""
    sel = KeyframeSelector(
        KeyframeConfig(min_displacement_m=0.01, stance_keyframes=stance_keyframes)
    )
    out = []
    for k in range(13):
        stance_id = 7 if 5 <= k <= 8 else None
        out.append(sel.is_keyframe(k / 30.0, np.array([0.003 * k, 0.0]), stance_id))
    return out, sel


def test_a_stance_between_keyframes_is_lost_without_stance_keyframes() -> None:
    out, sel = _stance_between_keyframes(0)
    assert [k for k, kf in enumerate(out) if kf] == [0, 4, 8, 12]
    assert sel.stance_count == 0


def test_stance_keyframes_take_the_first_anchored_frames() -> None:
    out, sel = _stance_between_keyframes(2)
    # frames 5 and 6 (the stance's first two anchored frames) become keyframes; the
    # displacement rule then counts from frame 6 (9 mm to frame 9, 12 mm to frame 10)
    assert [k for k, kf in enumerate(out) if kf] == [0, 4, 5, 6, 10]
    assert sel.stance_count == 2 and sel.count == 5


def test_a_stance_keyframe_by_motion_counts_towards_the_stance() -> None:
    """A stance whose first frame is a keyframe anyway needs only one more."""
    sel = KeyframeSelector(KeyframeConfig(stance_keyframes=2))
    assert sel.is_keyframe(0.0, np.zeros(2), 0)  # first frame, in stance 0
    assert sel.is_keyframe(0.033, np.zeros(2), 0)  # the stance's second keyframe
    assert not sel.is_keyframe(0.066, np.zeros(2), 0)  # two are enough
    assert sel.is_keyframe(0.1, np.zeros(2), 1)  # a new stance starts over
    assert sel.stance_count == 2


def test_stance_keyframes_must_not_be_negative() -> None:
    with pytest.raises(ValidationError):
        KeyframeConfig(stance_keyframes=-1)
