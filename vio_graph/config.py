"""Pipeline configuration: one pydantic model per section, defaults in code, YAML overrides.

``configs/default.yaml`` holds the defaults a user edits; the used config is saved beside the
results (``config.yaml``) so every run can be reproduced.
"""

from __future__ import annotations

from pathlib import Path
from typing import Literal

import yaml
from pydantic import BaseModel, ConfigDict, Field

from vio_graph.config_files import (
    configs_dir,
    load_yaml_mapping,
    resolve_config_path,
    validate_model,
)
from vio_graph.filter.config import FilterConfig
from vio_graph.frontend.config import FrontendConfig
from vio_graph.keyframes import KeyframeConfig
from vio_graph.mapping.config import MappingConfig
from vio_graph.safety.config import SafetyConfig
from vio_graph.smoother.config import SmootherConfig


class _Section(BaseModel):
    model_config = ConfigDict(extra="forbid", frozen=True)


class KinematicsConfig(_Section):
    """Where the leg chain's angles come from (paper Section II.D, Fig. 3)."""

    shank_pitch_source: Literal["encoders", "imu"] = Field(
        default="imu",
        description="'imu': the shank/knee IMU's attitude at the frame time (gyro-integrated, "
        "filter/attitude.py); 'encoders': thigh IMU pitch minus the knee encoder, as in the "
        "paper (Fig. 3). The IMU default halved the toe error on simulated trials whose thigh "
        "IMU has the MTi's 1 deg pitch error (docs/method.md)",
    )


class OutputConfig(_Section):
    rerun: bool = Field(default=True, description="write a rerun .rrd of the run")
    plots: bool = Field(
        default=True, description="write the PNG figures (plots/, map/map.png); --no-plots"
    )
    cloud_every_n_frames: int = Field(default=3, ge=1, description="3D cloud logging stride")
    cloud_pixel_stride: int = Field(default=3, ge=1, description="pixel subsampling of the cloud")


class InjectedFaultsConfig(_Section):
    """Front-end failures injected in the replay, to test robustness (off by default).

    Sensor faults are simulated in the recording (``vio_graph.sim`` ``faults``); a wrong
    corner association is a failure of our own front end, so it is injected here: with
    probability ``wrong_association_rate`` an accepted displacement is shifted by one whole
    stair step (``step_xz_m``, sign chosen at random), exactly what locking onto the
    neighbouring nosing produces.
    """

    wrong_association_rate: float = Field(default=0.0, ge=0, le=1)
    step_xz_m: tuple[float, float] = Field(default=(0.28, 0.147), description="tread, rise (m)")
    seed: int = Field(default=0, description="random seed of the injection")


class PipelineConfig(_Section):
    frontend: FrontendConfig = FrontendConfig()
    filter: FilterConfig = FilterConfig()
    keyframes: KeyframeConfig = KeyframeConfig()
    kinematics: KinematicsConfig = KinematicsConfig()
    smoother: SmootherConfig = SmootherConfig()
    mapping: MappingConfig = MappingConfig()
    output: OutputConfig = OutputConfig()
    inject: InjectedFaultsConfig = InjectedFaultsConfig()
    safety: SafetyConfig = SafetyConfig()


def load_config(path: str | Path | None = None) -> PipelineConfig:
    """Load a pipeline config: a YAML path, a name in configs/, or None for configs/default.yaml
    (or the in-code defaults if that file is absent)."""
    if path is None:
        candidate = configs_dir() / "default.yaml"
        if not candidate.is_file():
            return PipelineConfig()
        path = candidate
    p = resolve_config_path(path)
    return validate_model(PipelineConfig, load_yaml_mapping(p), p)


def dump_config(config: PipelineConfig) -> str:
    return yaml.safe_dump(config.model_dump(mode="json"), sort_keys=False)
