from pathlib import Path

import pytest

from vio_graph.config import PipelineConfig, dump_config, load_config
from vio_graph.errors import ConfigError


def test_default_yaml_loads_to_code_defaults() -> None:
    assert load_config() == PipelineConfig()


def test_round_trip(tmp_path: Path) -> None:
    p = tmp_path / "c.yaml"
    p.write_text(dump_config(PipelineConfig()))
    assert load_config(p) == PipelineConfig()


def test_errors_name_file_and_field(tmp_path: Path) -> None:
    p = tmp_path / "bad.yaml"
    p.write_text("smoother:\n  window_s: -1\n")
    with pytest.raises(ConfigError, match=r"bad.yaml: smoother.window_s"):
        load_config(p)
    p.write_text("nonsense_section: {}\n")
    with pytest.raises(ConfigError, match="nonsense_section"):
        load_config(p)
    with pytest.raises(ConfigError, match="not found"):
        load_config(tmp_path / "missing.yaml")
