"""File names and CSV columns of the on-disk recording format (version 1).

See docs/recording-format.md for the human description.
"""

from __future__ import annotations

METADATA_FILE = "metadata.yaml"
IMU_FILE = "imu.csv"
JOINTS_FILE = "joints.csv"
DEPTH_DIR = "depth"
DEPTH_TIMESTAMPS_FILE = "depth/timestamps.csv"
DEPTH_MM_FILE = "depth/depth_mm.npy"  # uint16, (N, H, W), units of camera.depth_unit_m
DEPTH_M_FILE = "depth/depth_m.npy"  # alternative: float32 metres, (N, H, W)
CONFIDENCE_FILE = "depth/confidence.npy"  # uint8, (N, H, W)
CONTACT_FILE = "contact.csv"  # optional: foot contact (load cell / heel switch)
GT_DIR = "groundtruth"
GT_IMU_STATE_FILE = "groundtruth/imu_state.csv"
GT_FRAMES_FILE = "groundtruth/frames.csv"

IMU_COLUMNS = (
    "timestamp_s",
    "acc_x_mps2",
    "acc_y_mps2",
    "acc_z_mps2",
    "gyr_x_radps",
    "gyr_y_radps",
    "gyr_z_radps",
    "q_w",
    "q_x",
    "q_y",
    "q_z",
)
JOINT_COLUMNS = ("timestamp_s", "thigh_pitch_rad", "knee_rad", "ankle_rad")
DEPTH_TIMESTAMP_COLUMNS = ("frame", "timestamp_s")
CONTACT_COLUMNS = ("timestamp_s", "force_n")
GT_IMU_STATE_COLUMNS = (
    "timestamp_s",
    "p_x_m",
    "p_y_m",
    "p_z_m",
    "v_x_mps",
    "v_y_mps",
    "v_z_mps",
    "q_w",
    "q_x",
    "q_y",
    "q_z",
    "ba_x_mps2",
    "ba_y_mps2",
    "ba_z_mps2",
    "bg_x_radps",
    "bg_y_radps",
    "bg_z_radps",
)
GT_FRAME_COLUMNS = ("frame", "timestamp_s", "edge_visible")


def gt_trajectory_file(body: str) -> str:
    return f"{GT_DIR}/{body}.tum"
