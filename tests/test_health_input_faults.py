"""health.input_fault_context: the input faults named after an innovation inconsistency."""

from __future__ import annotations

from vio_graph.health import input_fault_context


def test_clean_inputs_name_nothing() -> None:
    clean = {"accel_saturated_samples": 0, "gyro_saturated_samples": 0}
    assert input_fault_context(clean, {"stamps": "as recorded", "switches": 0}) == []
    assert input_fault_context(clean, None) == []
    assert input_fault_context({}, None) == []


def test_clipped_samples_are_counted_per_sensor() -> None:
    one = input_fault_context({"accel_saturated_samples": 1, "gyro_saturated_samples": 0}, None)
    assert len(one) == 1
    assert one[0].startswith("1 accelerometer sample at the IMU's declared range")
    both = input_fault_context({"accel_saturated_samples": 3, "gyro_saturated_samples": 2}, None)
    assert both[0].startswith("3 accelerometer samples and 2 gyroscope samples at")


def test_a_stamp_test_that_switched_to_the_clock_line_is_named() -> None:
    faults = {"accel_saturated_samples": 0, "gyro_saturated_samples": 0}
    found = input_fault_context(faults, {"stamps": "clock line", "switches": 1})
    assert len(found) == 1 and "switched 1 time(s)" in found[0]
    # switched there and back: still named (the stamps were in doubt during the run)
    back = input_fault_context(faults, {"stamps": "as recorded", "switches": 2})
    assert len(back) == 1 and "switched 2 time(s)" in back[0]
    clipped = {"accel_saturated_samples": 1, "gyro_saturated_samples": 0}
    assert len(input_fault_context(clipped, {"stamps": "clock line", "switches": 1})) == 2
