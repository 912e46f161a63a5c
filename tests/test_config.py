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


# ------------------------------------------------------------------ where config files are found
ROOT = Path(__file__).resolve().parents[1]


def _folder(path: Path, files: dict[str, str]) -> Path:
    path.mkdir(parents=True)
    for name, text in files.items():
        (path / name).write_text(text)
    return path


def test_checkout_reads_the_top_level_configs_folder() -> None:
    from vio_graph import config_files

    assert config_files.source_configs_dir() == ROOT / "configs"
    assert config_files.configs_dir() == ROOT / "configs"
    assert config_files.resolve_config_path("upstair") == ROOT / "configs" / "upstair.yaml"


def test_explicit_paths_are_used_as_given(tmp_path: Path) -> None:
    from vio_graph.config_files import resolve_config_path

    mine = tmp_path / "upstair.yaml"
    assert resolve_config_path(mine) == mine
    assert resolve_config_path("my/upstair") == Path("my/upstair")
    assert resolve_config_path("upstair.yml") == Path("upstair.yml")


def test_names_search_the_checkout_then_the_packaged_copy(tmp_path: Path, monkeypatch) -> None:
    from vio_graph import config_files
    from vio_graph.sim import load_scenario

    repo = _folder(tmp_path / "repo", {"both.yaml": "", "repo_only.yaml": ""})
    pkg = _folder(tmp_path / "pkg", {"both.yaml": "", "pkg_only.yaml": ""})
    monkeypatch.setattr(config_files, "source_configs_dir", lambda: repo)
    monkeypatch.setattr(config_files, "packaged_configs_dir", lambda: pkg)
    assert config_files.resolve_config_path("both") == repo / "both.yaml"
    assert config_files.resolve_config_path("repo_only") == repo / "repo_only.yaml"
    assert config_files.resolve_config_path("pkg_only") == pkg / "pkg_only.yaml"
    assert config_files.resolve_config_path("nowhere") == repo / "nowhere.yaml"
    with pytest.raises(ConfigError, match=r"repo/nowhere.yaml: scenario file not found"):
        load_scenario("nowhere")


def test_installed_package_reads_its_packaged_copy(tmp_path: Path, monkeypatch) -> None:
    """No checkout (a wheel install): scenarios and the default config come from the package."""
    from vio_graph import config_files
    from vio_graph.sim import load_scenario

    pkg = _folder(
        tmp_path / "pkg",
        {
            "default.yaml": "smoother:\n  window_s: 1.25\n",
            "upstair.yaml": (ROOT / "configs" / "upstair.yaml").read_text(),
        },
    )
    monkeypatch.setattr(config_files, "source_configs_dir", lambda: None)
    monkeypatch.setattr(config_files, "packaged_configs_dir", lambda: pkg)
    assert config_files.configs_dir() == pkg
    assert load_config().smoother.window_s == 1.25
    assert load_scenario("upstair").name == "upstair"


def test_site_packages_configs_is_not_a_checkout(tmp_path: Path, monkeypatch) -> None:
    """A stray top-level site-packages/configs (some other distribution's) is never read."""
    import vio_graph
    from vio_graph import config_files

    site = tmp_path / "site-packages"
    _folder(site / "configs", {"upstair.yaml": "name: other\n"})
    _folder(site / "vio_graph", {"__init__.py": ""})
    monkeypatch.setattr(vio_graph, "__file__", str(site / "vio_graph" / "__init__.py"))
    assert config_files.source_configs_dir() is None
    (site / "pyproject.toml").write_text("")
    assert config_files.source_configs_dir() == site / "configs"


def test_packaged_copy_inside_a_zip_is_extracted(tmp_path: Path) -> None:
    import zipfile

    from vio_graph.config_files import _extracted, load_yaml_mapping

    archive = tmp_path / "vio_graph.zip"
    with zipfile.ZipFile(archive, "w") as z:
        z.writestr("vio_graph/configs/upstair.yaml", "name: upstair\n")
    folder = zipfile.Path(archive, "vio_graph/configs/")
    out = _extracted(str(archive), folder)
    assert load_yaml_mapping(out / "upstair.yaml") == {"name": "upstair"}
    assert _extracted(str(archive), zipfile.Path(archive, "vio_graph/configs/")) == out
