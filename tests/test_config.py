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


def test_filter_ablation_variants_are_valid_and_switch_what_they_say() -> None:
    from vio_graph.config import PipelineConfig
    from vio_graph.experiments import FILTER_ABLATION_VARIANTS, filter_ablation_config

    base = PipelineConfig()
    cfgs = {n: filter_ablation_config(base, o) for n, o in FILTER_ABLATION_VARIANTS.items()}
    paper = next(c for n, c in cfgs.items() if n.startswith("paper"))
    assert paper.filter.measurement_model == "position_pseudo"
    assert paper.filter.attitude.source == "vendor"
    assert not paper.filter.level_aiding.enabled and not paper.filter.corner_landmarks
    # nested overrides keep the other fields of the section
    assert paper.filter.level_aiding.max_tilt_deg == base.filter.level_aiding.max_tilt_deg
    default = next(c for n, c in cfgs.items() if n.endswith("(default)"))
    assert default == base
    assert sum(not c.filter.level_aiding.enabled for c in cfgs.values()) == len(cfgs) - 1
