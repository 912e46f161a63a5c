"""Simulated recordings are reused only when config, seed and simulator code all match."""

from __future__ import annotations

from pathlib import Path

import pytest

from vio_graph.sim import cache as sim_cache
from vio_graph.sim import load_scenario


@pytest.fixture(scope="module")
def short_cfg():
    return load_scenario("upstair").model_copy(update={"duration_s": 1.0})


def test_fingerprint_is_stable_and_in_the_provenance(short_cfg, tmp_path: Path) -> None:
    from vio_graph.recording import Recording

    fp = sim_cache.simulator_fingerprint()
    assert len(fp) == 12 and int(fp, 16) >= 0
    sim_cache.simulator_fingerprint.cache_clear()
    assert sim_cache.simulator_fingerprint() == fp  # the same sources, the same digest
    rec = sim_cache.simulate_cached(short_cfg, 3, tmp_path / "r")
    assert fp in Recording.open(rec).metadata.provenance.software


def test_a_recording_is_reused_only_for_the_same_config_seed_and_simulator(
    short_cfg, tmp_path: Path, monkeypatch: pytest.MonkeyPatch
) -> None:
    rec = tmp_path / "r"
    assert not sim_cache.recording_is_current(rec, short_cfg, 3)  # nothing there
    sim_cache.simulate_cached(short_cfg, 3, rec)
    stamp = (rec / "metadata.yaml").stat().st_mtime_ns
    assert sim_cache.recording_is_current(rec, short_cfg, 3)
    assert not sim_cache.recording_is_current(rec, short_cfg, 4)  # another seed
    other = short_cfg.model_copy(update={"duration_s": 1.5})
    assert not sim_cache.recording_is_current(rec, other, 3)  # another config
    sim_cache.simulate_cached(short_cfg, 3, rec)  # reused: not written again
    assert (rec / "metadata.yaml").stat().st_mtime_ns == stamp
    # the simulator's code changed since: the folder is simulated anew
    monkeypatch.setattr(sim_cache, "simulator_fingerprint", lambda: "0123456789ab")
    assert not sim_cache.recording_is_current(rec, short_cfg, 3)
    sim_cache.simulate_cached(short_cfg, 3, rec)
    assert (rec / "metadata.yaml").stat().st_mtime_ns != stamp
    assert sim_cache.recording_is_current(rec, short_cfg, 3)


def test_a_broken_folder_is_not_current(short_cfg, tmp_path: Path) -> None:
    bad = tmp_path / "bad"
    bad.mkdir()
    (bad / "metadata.yaml").write_text("format_version: [\n")
    assert not sim_cache.recording_is_current(bad, short_cfg, 3)
    sim_cache.simulate_cached(short_cfg, 3, bad)  # replaced by a valid recording
    assert sim_cache.recording_is_current(bad, short_cfg, 3)
