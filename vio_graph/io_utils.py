"""Atomic file output: write to a temporary name in the same folder, then rename."""

from __future__ import annotations

import contextlib
import json
import os
import re
import tempfile
from collections.abc import Iterator
from pathlib import Path
from typing import Any

import numpy as np


@contextlib.contextmanager
def atomic_path(path: Path, suffix: str = ".tmp") -> Iterator[Path]:
    """Yield a temporary path beside ``path``; rename it onto ``path`` only on success.

    ``suffix`` ends the temporary name; writers that infer the format from the extension
    (open3d, matplotlib) need e.g. ``suffix=path.suffix``.
    """
    path = Path(path)
    path.parent.mkdir(parents=True, exist_ok=True)
    fd, tmp = tempfile.mkstemp(prefix=f".{path.name}.", suffix=suffix, dir=path.parent)
    tmp_path = Path(tmp)
    try:
        try:
            os.fchmod(fd, 0o666 & ~_umask())  # mkstemp creates 0600; outputs get the usual mode
        finally:
            os.close(fd)
        yield tmp_path
        os.replace(tmp_path, path)
    finally:
        if tmp_path.exists():
            tmp_path.unlink()


# Temporary names: atomic_path's ".<name>.<8 random chars><suffix>" and ".<name>.partial"
# (the rerun logger, the recording writer's folder).
_TEMPORARY_NAME = re.compile(r"\..+\.(?:[a-z0-9_]{8}(?:\.\w+)?|\w*partial)")


def _umask() -> int:
    mask = os.umask(0)
    os.umask(mask)
    return mask


def remove_temporaries(folder: Path) -> list[Path]:
    """Delete the temporary files atomic writers leave behind if a process is interrupted
    between creating and renaming them (in ``folder`` and below); returns what was removed."""
    removed = []
    for p in sorted(Path(folder).rglob(".*")):
        if p.is_file() and not p.is_symlink() and _TEMPORARY_NAME.fullmatch(p.name):
            p.unlink(missing_ok=True)
            removed.append(p)
    return removed


def atomic_write_text(path: Path, text: str) -> None:
    with atomic_path(path) as tmp:
        tmp.write_text(text, encoding="utf-8")


#: a heading containing this starts the hand-written part of a generated document
HAND_WRITTEN_MARK = "(written by hand"


def write_generated_doc(path: Path, generated: str) -> None:
    """Write a generated Markdown document, keeping the hand-written tail of the existing
    file: everything from the first heading that contains ``HAND_WRITTEN_MARK``."""
    path = Path(path)
    tail = ""
    if path.is_file():
        lines = path.read_text(encoding="utf-8").splitlines(keepends=True)
        for i, line in enumerate(lines):
            if line.startswith("#") and HAND_WRITTEN_MARK in line:
                tail = "".join(lines[i:])
                break
    text = generated if not tail else generated.rstrip("\n") + "\n\n" + tail
    atomic_write_text(path, text)


def atomic_write_json(path: Path, obj: Any) -> None:
    atomic_write_text(
        path, json.dumps(obj, indent=2, sort_keys=False, default=_json_default) + "\n"
    )


def _json_default(obj: Any) -> Any:
    if isinstance(obj, np.ndarray):
        return obj.tolist()
    if isinstance(obj, np.generic):
        return obj.item()
    if isinstance(obj, Path):
        return str(obj)
    raise TypeError(f"not JSON serialisable: {type(obj).__name__}")
