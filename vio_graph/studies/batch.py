"""``vio-graph batch``: every recording x mode x config as one task, one summary.

Layout of ``--out DIR``::

    DIR/runs/<config>/<trial>/<mode>/   the results folder of one task (what `vio-graph run`
                                        writes, without run.rrd); <config> is `base` or the
                                        grid point, e.g. `smoother.window_s-1.5`
    DIR/summary.csv                     one row per task (columns: SUMMARY_COLUMNS)
    DIR/summary.md                      the same as a table, failed tasks with their error line
    DIR/summary.png                     toe ATE (x and z, cm) per trial and mode

A task is complete when its ``metrics.json`` (written last, atomically) exists and its
``config.yaml`` is the task's config; ``--resume`` skips complete tasks and reads their
numbers from disk, so a resumed study has the same summary as one run in a single go.
``summary.csv`` holds no timings or absolute paths: the same study gives the same file
whatever ran it (serially, on a local cluster, on a remote one).
"""

from __future__ import annotations

import csv
import io
import json
import logging
import math
from collections.abc import Callable, Sequence
from dataclasses import dataclass
from pathlib import Path
from typing import Any

from vio_graph.config import PipelineConfig, dump_config
from vio_graph.errors import VioGraphError
from vio_graph.evaluation.tables import report_header
from vio_graph.io_utils import atomic_write_text
from vio_graph.studies.engine import run_tasks
from vio_graph.studies.grid import GridPoint

log = logging.getLogger(__name__)

SUMMARY_COLUMNS = (
    "trial",
    "mode",
    "config",
    "params",
    "status",
    "ate",
    "toe_x_cm",
    "toe_z_cm",
    "camera_x_cm",
    "camera_z_cm",
    "map_rise_error_mm",
    "map_tread_error_mm",
    "results",
    "error",
)


@dataclass(frozen=True)
class BatchTask:
    """One trial x mode x config. Paths are strings so that a remote worker gets them as
    given (the client and the workers must see the same file system)."""

    trial: str
    recording: str
    mode: str
    config_tag: str
    params_json: str
    config_json: str
    out_dir: str

    @property
    def name(self) -> str:
        return f"{self.config_tag}/{self.trial}/{self.mode}"


def trial_names(recordings: Sequence[Path]) -> list[str]:
    """Folder names, or (if two recordings share a name) their paths below the deepest common
    folder with ``/`` as ``__``."""
    paths = [Path(r) for r in recordings]
    names = [p.name for p in paths]
    if len(set(names)) == len(names):
        return names
    resolved = [p.resolve() for p in paths]
    if len(set(resolved)) != len(resolved):
        dup = sorted({str(p) for p in paths if resolved.count(p.resolve()) > 1})
        raise VioGraphError(f"recording given twice: {', '.join(dup)}")
    import os

    common = Path(os.path.commonpath([str(p) for p in resolved]))
    return ["__".join(p.relative_to(common).parts) for p in resolved]


def make_tasks(
    recordings: Sequence[Path], modes: Sequence[str], grid: Sequence[GridPoint], out_dir: Path
) -> list[BatchTask]:
    # absolute: a worker resolves paths in its own working directory (on a remote machine,
    # the shared file system must be mounted at the same path as here)
    names = trial_names(recordings)
    recordings = [Path(r).resolve() for r in recordings]
    out_dir = Path(out_dir).resolve()
    tasks = []
    for point in grid:
        cfg_json = point.config.model_dump_json()
        params_json = json.dumps(point.params, sort_keys=False)
        for trial, rec in zip(names, recordings, strict=True):
            for mode in modes:
                tasks.append(
                    BatchTask(
                        trial=trial,
                        recording=str(rec),
                        mode=mode,
                        config_tag=point.tag,
                        params_json=params_json,
                        config_json=cfg_json,
                        out_dir=str(Path(out_dir) / "runs" / point.tag / trial / mode),
                    )
                )
    return tasks


def _row(
    task: BatchTask, metrics: dict[str, Any] | None, error: str | None, study_dir: Path
) -> dict[str, Any]:
    from vio_graph.evaluation.run_metrics import ate_key

    row: dict[str, Any] = {
        "trial": task.trial,
        "mode": task.mode,
        "config": task.config_tag,
        "params": task.params_json if task.params_json != "{}" else "",
        "status": "ok" if error is None else "failed",
        "results": Path(task.out_dir).relative_to(Path(study_dir).resolve()).as_posix(),
        "error": error or "",
    }
    if metrics is not None:
        key = ate_key(metrics)
        table = (metrics.get(key) or {}).get(task.mode)
        row["ate"] = key if table else "no ground truth"
        for body in ("toe", "camera"):
            for ax in ("x", "z"):
                row[f"{body}_{ax}_cm"] = table[body][ax] if table else None
        mp = metrics.get("map", {})
        row["map_rise_error_mm"] = mp.get("rise_error_mm")
        row["map_tread_error_mm"] = mp.get("tread_error_mm")
    return row


def task_complete(task: BatchTask) -> dict[str, Any] | None:
    """The task's metrics if its outputs are complete (metrics.json written last, same
    config, the mode was run), else None."""
    out = Path(task.out_dir)
    try:
        metrics = json.loads((out / "metrics.json").read_text())
        config_text = (out / "config.yaml").read_text()
    except (OSError, ValueError):
        return None
    cfg = PipelineConfig.model_validate_json(task.config_json)
    if config_text != dump_config(cfg) or task.mode not in metrics.get("modes", []):
        return None
    return metrics


def run_batch_task(task: BatchTask) -> dict[str, Any]:
    """Run one task (on a worker): the pipeline on one recording in one mode with one config.
    Returns the metrics (the outputs are in ``task.out_dir``)."""
    from vio_graph.pipeline import run_recording

    out = Path(task.out_dir)
    (out / "metrics.json").unlink(missing_ok=True)  # incomplete until rewritten
    cfg = PipelineConfig.model_validate_json(task.config_json)
    return run_recording(
        task.recording,
        out,
        cfg,
        modes=(task.mode,),
        overwrite=True,
        visualize=False,
        progress=False,
    ).metrics


def run_batch(
    tasks: Sequence[BatchTask],
    study_dir: Path,
    scheduler: str | None = None,
    workers: int | None = None,
    resume: bool = False,
    progress: Callable[[int], None] | None = None,
) -> list[dict[str, Any]]:
    """Run the tasks (skipping complete ones with ``resume``); one summary row per task, in
    the tasks' order."""
    done: dict[int, dict[str, Any]] = {}
    if resume:
        for k, t in enumerate(tasks):
            m = task_complete(t)
            if m is not None:
                done[k] = m
    todo = [k for k in range(len(tasks)) if k not in done]
    n_done = len(done)
    if progress and n_done:
        progress(n_done)  # resumed tasks count as finished

    def step(n: int) -> None:
        if progress:
            progress(n_done + n)

    outcomes = (
        run_tasks(
            run_batch_task,
            [tasks[k] for k in todo],
            scheduler,
            workers,
            step,
            names=[tasks[k].name for k in todo],
        )
        if todo
        else []
    )
    rows: list[dict[str, Any] | None] = [None] * len(tasks)
    for k, m in done.items():
        rows[k] = _row(tasks[k], m, None, study_dir)
    for k, o in zip(todo, outcomes, strict=True):
        rows[k] = _row(tasks[k], o.value if o.ok else None, o.error, study_dir)
    log.info(
        "%d tasks: %d resumed, %d run, %d failed",
        len(tasks),
        len(done),
        len(todo),
        sum(1 for r in rows if r and r["status"] != "ok"),
    )
    return [r for r in rows if r is not None]


# ----------------------------------------------------------------------------- summary
def _cell(v: Any) -> str:
    if v is None or (isinstance(v, float) and not math.isfinite(v)):
        return ""
    return f"{v:.4f}" if isinstance(v, float) else str(v)


def summary_csv(rows: Sequence[dict[str, Any]]) -> str:
    buf = io.StringIO()
    w = csv.writer(buf, lineterminator="\n")
    w.writerow(SUMMARY_COLUMNS)
    for r in rows:
        w.writerow([_cell(r.get(c)) for c in SUMMARY_COLUMNS])
    return buf.getvalue()


def read_summary_csv(path: Path) -> list[dict[str, str]]:
    with open(path, newline="") as f:
        return list(csv.DictReader(f))


def summary_markdown(rows: Sequence[dict[str, Any]], command: str) -> str:
    def f2(v: Any) -> str:
        return "—" if v is None or (isinstance(v, float) and not math.isfinite(v)) else f"{v:.2f}"

    failed = [r for r in rows if r["status"] != "ok"]
    configs = list(dict.fromkeys(r["config"] for r in rows))
    lines = [
        *report_header("Batch summary", command),
        f"{len(rows)} tasks (trial x mode x config), {len(rows) - len(failed)} ok, "
        f"{len(failed)} failed. ATE in cm (first pose anchored, RMSE per axis; obstacle "
        "trials over the frames with the obstacle in view), map errors in mm against the "
        "recording's true stair. Per-task results: `runs/<config>/<trial>/<mode>/`.",
        "",
    ]
    for cfg in configs:
        rs = [r for r in rows if r["config"] == cfg]
        params = rs[0]["params"]
        lines += [
            f"## Config `{cfg}`" + (f" ({params})" if params else ""),
            "",
            "| trial | mode | toe x | toe z | camera x | camera z | rise err. | "
            "tread err. | status |",
            "|---|---|---|---|---|---|---|---|---|",
        ]
        for r in rs:
            status = "ok" if r["status"] == "ok" else f"**failed**: {r['error']}"
            lines.append(
                f"| {r['trial']} | {r['mode']} | {f2(r.get('toe_x_cm'))} | "
                f"{f2(r.get('toe_z_cm'))} | {f2(r.get('camera_x_cm'))} | "
                f"{f2(r.get('camera_z_cm'))} | {f2(r.get('map_rise_error_mm'))} | "
                f"{f2(r.get('map_tread_error_mm'))} | {status} |"
            )
        lines.append("")
    if failed:
        lines += ["## Failed tasks", ""]
        lines += [f"- {r['config']}/{r['trial']}/{r['mode']}: {r['error']}" for r in failed]
        lines.append("")
    lines += ["![toe ATE per trial and mode](summary.png)", ""]
    return "\n".join(lines)


def write_summary(rows: Sequence[dict[str, Any]], study_dir: Path, command: str) -> dict[str, Path]:
    """summary.csv, summary.md and summary.png in ``study_dir`` (each written atomically)."""
    from vio_graph.viz.plots import plot_batch_summary

    study_dir = Path(study_dir)
    study_dir.mkdir(parents=True, exist_ok=True)
    written = {
        "csv": study_dir / "summary.csv",
        "markdown": study_dir / "summary.md",
        "plot": study_dir / "summary.png",
    }
    atomic_write_text(written["csv"], summary_csv(rows))
    atomic_write_text(written["markdown"], summary_markdown(rows, command))
    plot_batch_summary(written["plot"], rows)
    return written
