"""Reuse of simulated recordings between runs (evaluate, sweep, robustness, demo).

A recording folder is reused only if it was simulated from the same scenario config and seed
*by the same simulator code*: its ``metadata.provenance.software`` carries a fingerprint of
the simulator's source files (:func:`simulator_fingerprint`). Without the fingerprint a
cache keyed on the config alone silently kept recordings from an older simulator, and
tables regenerated on them compared today's estimator with another day's data.
"""

from __future__ import annotations

import hashlib
import json
from collections.abc import Callable
from functools import lru_cache
from pathlib import Path

from vio_graph.sim.config import ScenarioConfig

#: the simulator's own sources (this package), the recording writer and geometry
_SOURCES = ("sim", "recording/writer.py", "geometry.py")


@lru_cache(maxsize=1)
def simulator_fingerprint() -> str:
    """12 hex digits of the SHA-256 over the simulator's source files (``vio_graph/sim/*.py``,
    the recording writer and the geometry helpers it uses), in a fixed order: a change of the
    simulator's code changes it, a change elsewhere in the package does not."""
    root = Path(__file__).resolve().parents[1]
    files: list[Path] = []
    for rel in _SOURCES:
        p = root / rel
        files.extend(sorted(p.glob("*.py")) if p.is_dir() else [p])
    h = hashlib.sha256()
    for f in files:
        h.update(f.relative_to(root).as_posix().encode())
        h.update(f.read_bytes())
    return h.hexdigest()[:12]


def software_tag() -> str:
    """``metadata.provenance.software`` of a simulated recording."""
    import vio_graph

    return f"vio_graph {vio_graph.__version__}, simulator {simulator_fingerprint()}"


def recording_is_current(rec_dir: Path, config: ScenarioConfig, seed: int) -> bool:
    """True if ``rec_dir`` holds a complete, valid recording simulated from ``config`` and
    ``seed`` by this simulator code (:func:`simulator_fingerprint`)."""
    from vio_graph.errors import VioGraphError
    from vio_graph.recording import Recording
    from vio_graph.sim.trial import provenance_config

    try:
        prov = Recording.open(Path(rec_dir)).metadata.provenance
    except (VioGraphError, OSError, ValueError):
        return False
    return (
        prov.source == "simulator"
        and prov.seed == seed
        and prov.software == software_tag()
        and json.dumps(prov.config, sort_keys=True)
        == json.dumps(provenance_config(config), sort_keys=True)
    )


def simulate_cached(
    config: ScenarioConfig,
    seed: int,
    rec_dir: Path,
    progress: Callable[[int], None] | None = None,
) -> Path:
    """``rec_dir`` as it is if :func:`recording_is_current`, else simulated anew (replacing
    whatever the folder held)."""
    from vio_graph.sim.trial import simulate

    if recording_is_current(rec_dir, config, seed):
        return Path(rec_dir)
    return simulate(config, seed, Path(rec_dir), progress=progress, overwrite=True)
