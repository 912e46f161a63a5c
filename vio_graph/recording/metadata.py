"""The recording's ``metadata.yaml`` as validated pydantic models (format version 1)."""

from __future__ import annotations

from typing import Any, Literal

import numpy as np
from pydantic import BaseModel, ConfigDict, Field, field_validator

FORMAT_VERSION = 1


class _Strict(BaseModel):
    model_config = ConfigDict(extra="forbid", frozen=True)


class CameraModel(_Strict):
    """Pinhole ToF camera. Depth is stored as uint16 in units of ``depth_unit_m``."""

    width_px: int = Field(gt=0)
    height_px: int = Field(gt=0)
    fx_px: float = Field(gt=0)
    fy_px: float = Field(gt=0)
    cx_px: float
    cy_px: float
    depth_unit_m: float = Field(gt=0, description="metres per stored depth unit (0.001 = mm)")
    min_range_m: float = Field(ge=0)
    max_range_m: float = Field(gt=0)
    frame_rate_hz: float = Field(gt=0)
    model: str = "pmd CamBoard pico flexx2 (simulated)"

    def intrinsic_matrix(self) -> np.ndarray:
        return np.array(
            [[self.fx_px, 0.0, self.cx_px], [0.0, self.fy_px, self.cy_px], [0.0, 0.0, 1.0]]
        )


class ImuModel(_Strict):
    """IMU rates and datasheet noise (continuous-time densities)."""

    rate_hz: float = Field(gt=0)
    accel_noise_density_mps2_per_sqrt_hz: float = Field(ge=0)
    gyro_noise_density_radps_per_sqrt_hz: float = Field(ge=0)
    accel_bias_random_walk_mps3_per_sqrt_hz: float = Field(ge=0)
    gyro_bias_random_walk_radps2_per_sqrt_hz: float = Field(ge=0)
    orientation_rms_rad: float = Field(ge=0, description="vendor roll/pitch error, RMS")
    accel_range_mps2: float = Field(gt=0)
    gyro_range_radps: float = Field(gt=0)
    model: str = "Xsens MTi-1 series (simulated)"


def _check_transform(value: Any) -> list[list[float]]:
    arr = np.asarray(value, dtype=float)
    if arr.shape != (4, 4):
        raise ValueError(f"must be a 4x4 matrix, got shape {arr.shape}")
    if not np.all(np.isfinite(arr)):
        raise ValueError("contains NaN or inf")
    R = arr[:3, :3]
    if not np.allclose(R @ R.T, np.eye(3), atol=1e-6) or np.linalg.det(R) < 0:
        raise ValueError("rotation block is not a proper rotation")
    if not np.allclose(arr[3], [0, 0, 0, 1]):
        raise ValueError("last row must be [0, 0, 0, 1]")
    return arr.tolist()


class Extrinsics(_Strict):
    """Rigid transforms, 4x4 row-major; ``a_T_b`` maps points in b into a."""

    imu_T_cam: list[list[float]]
    knee_T_cam: list[list[float]] = Field(
        description="shank frame (origin at the knee joint centre) <- camera"
    )

    _v = field_validator("imu_T_cam", "knee_T_cam")(classmethod(lambda cls, v: _check_transform(v)))

    def imu_T_cam_matrix(self) -> np.ndarray:
        return np.asarray(self.imu_T_cam, dtype=float)

    def knee_T_cam_matrix(self) -> np.ndarray:
        return np.asarray(self.knee_T_cam, dtype=float)


class LegGeometry(_Strict):
    """Link model of the instrumented leg (see vio_graph.kinematics.LegModel)."""

    rig: Literal["able_bodied", "prosthesis"]
    thigh_length_m: float = Field(gt=0)
    shank_length_m: float = Field(gt=0, description="knee joint centre to ankle joint centre")
    heel_in_foot_xz_m: tuple[float, float]
    toe_in_foot_xz_m: tuple[float, float]

    def leg_model(self):  # noqa: ANN201 - avoids an import cycle in annotations
        from vio_graph.kinematics import LegModel

        return LegModel(
            thigh_length_m=self.thigh_length_m,
            shank_length_m=self.shank_length_m,
            heel_in_foot_xz_m=self.heel_in_foot_xz_m,
            toe_in_foot_xz_m=self.toe_in_foot_xz_m,
        )


class TerrainInfo(_Strict):
    """What the camera walks over. ``profile_xz_m`` is the true sagittal profile (polyline in
    the world x-z plane, x increasing) where known; ``edges_xz_m`` the true convex corners
    (stair nosings, obstacle top edges)."""

    kind: Literal["stair_up", "stair_down", "obstacle", "level", "unknown"]
    params: dict[str, float | int | str] = Field(default_factory=dict)
    profile_xz_m: list[tuple[float, float]] = Field(default_factory=list)
    edges_xz_m: list[tuple[float, float]] = Field(default_factory=list)


class ContactModel(_Strict):
    """The optional foot-contact channel (``contact.csv``)."""

    kind: Literal["load_cell", "switch"] = Field(
        description="load_cell: pylon axial force in N (e.g. the Open Source Leg's); switch: "
        "heel / foot switch, force_n 1 closed and 0 open"
    )
    threshold_n: float = Field(
        gt=0, description="the foot is loaded at or above this force_n (a switch: 0.5)"
    )


class Provenance(_Strict):
    source: Literal["simulator", "device"]
    scenario: str | None = None
    seed: int | None = None
    config: dict[str, Any] = Field(default_factory=dict)
    software: str = ""
    created_utc: str = ""
    notes: str = ""


class RecordingMetadata(_Strict):
    """Contents of ``metadata.yaml``."""

    format_version: int
    duration_s: float = Field(ge=0)
    camera: CameraModel
    imu: ImuModel
    joint_rate_hz: float = Field(gt=0)
    groundtruth_rate_hz: float | None = Field(default=None, gt=0)
    extrinsics: Extrinsics
    leg: LegGeometry
    terrain: TerrainInfo
    provenance: Provenance
    contact: ContactModel | None = Field(
        default=None, description="the contact channel, if the recording has contact.csv"
    )

    @field_validator("format_version")
    @classmethod
    def _known_version(cls, v: int) -> int:
        if v != FORMAT_VERSION:
            raise ValueError(f"unknown format version {v}; this vio_graph reads {FORMAT_VERSION}")
        return v
