"""Property-based fuzzing of the recording reader (hypothesis).

Each test mutates a tiny valid recording (0.3 s, 16 x 12 px, 9 frames; tests/conftest.py) in a
fresh temporary folder and opens it. The only acceptable outcomes are a valid recording (opens,
summarises, every frame reads) or a ``RecordingError`` whose message is one line naming a path
inside the recording folder. Any other exception (numpy, pydantic, yaml, OSError, ...) fails.

Five mutation families, 210 examples each (1050 per run, counted and asserted): raw bytes
(flips, truncations, insertions, emptied files), CSV cells (NaN, inf, text, empty, huge,
negative, unit scalings, swapped/duplicated/deleted rows and columns), metadata.yaml (deleted
keys, wrong types, extra keys, non-finite numbers, versions, unsafe tags, garbage), .npy headers
and arrays (dtype, shape, byte order, Fortran order, pickled objects, .npz, corrupt headers) and
the file system (deleted files and folders, folders for files, symlinks inside, outside,
dangling and looping).
"""

from __future__ import annotations

import io
import os
import shutil
import tempfile
from collections import Counter
from collections.abc import Callable
from pathlib import Path

import numpy as np
import pytest
import yaml
from hypothesis import HealthCheck, given, settings
from hypothesis import strategies as st

from tests.conftest import tiny_metadata, tiny_streams
from vio_graph.errors import RecordingError
from vio_graph.recording import Recording, write_recording

# VIO_GRAPH_FUZZ_EXAMPLES raises the count for a longer local or nightly run
EXAMPLES_PER_FAMILY = max(210, int(os.environ.get("VIO_GRAPH_FUZZ_EXAMPLES", "210")))
FAMILIES = 5
MIN_TOTAL_EXAMPLES = 1000
FUZZ_SETTINGS = settings(
    max_examples=EXAMPLES_PER_FAMILY,
    deadline=None,
    database=None,  # nothing written into the checkout; failures print a reproducible example
    suppress_health_check=[
        HealthCheck.too_slow,
        HealthCheck.data_too_large,
        HealthCheck.function_scoped_fixture,
    ],
)
RUN_COUNTS: Counter[str] = Counter()  # examples run per family, checked by the last test

CSV_FILES = ("imu.csv", "joints.csv", "depth/timestamps.csv", "groundtruth/frames.csv")
TUM_FILES = tuple(f"groundtruth/{b}.tum" for b in ("camera", "knee", "ankle", "heel", "toe"))
NPY_FILES = ("depth/depth_mm.npy", "depth/confidence.npy")


# --------------------------------------------------------------------------- the base recording
@pytest.fixture(scope="module")
def base_files(tmp_path_factory: pytest.TempPathFactory) -> dict[str, bytes]:
    """The tiny valid recording as {relative path: bytes}."""
    meta = tiny_metadata().model_copy(update={"duration_s": 0.3})
    imu, joints, gt, t_frames, frames = tiny_streams(meta, duration_s=0.3)
    root = write_recording(
        tmp_path_factory.mktemp("fuzz_base") / "rec", meta, imu, joints, gt, t_frames, iter(frames)
    )
    files = {p.relative_to(root).as_posix(): p.read_bytes() for p in root.rglob("*") if p.is_file()}
    assert set(CSV_FILES + TUM_FILES + NPY_FILES) < set(files)
    _check_outcome(root)  # the base itself is valid
    return files


def _fast_tmp() -> str | None:
    """A RAM-backed temporary folder where there is one (creating and deleting 1000 small
    folders on a disk costs seconds), else the default."""
    shm = Path("/dev/shm")
    return str(shm) if shm.is_dir() and os.access(shm, os.W_OK) else None


class _Workspace:
    """Writes the base recording into a fresh folder per example and removes it afterwards."""

    def __init__(self, files: dict[str, bytes], family: str) -> None:
        self.files = files
        self.family = family
        self.top = Path(tempfile.mkdtemp(prefix=f"vio_fuzz_{family}_", dir=_fast_tmp()))
        self.n = 0

    def run(self, mutate: Callable[[Path, Path], None]) -> str:
        """Materialise, mutate (given the recording folder and a scratch folder outside it),
        open; return the outcome ("valid" or "error")."""
        self.n += 1
        case = self.top / str(self.n)
        root, outside = case / "rec", case / "outside"
        outside.mkdir(parents=True)
        for rel, data in self.files.items():
            p = root / rel
            p.parent.mkdir(parents=True, exist_ok=True)
            p.write_bytes(data)
        try:
            mutate(root, outside)
            outcome = _check_outcome(root)
        finally:
            shutil.rmtree(case, ignore_errors=True)
        RUN_COUNTS[self.family] += 1
        return outcome

    def close(self) -> None:
        shutil.rmtree(self.top, ignore_errors=True)


def _check_outcome(root: Path) -> str:
    """Open the recording and use all of it; only RecordingError may escape, and it must be one
    line naming a path inside ``root``."""
    try:
        rec = Recording.open(root)
        summary = rec.summary()
        assert summary["frames"] == rec.num_frames > 0
        for f in rec.frames():
            assert f.depth_m.dtype == np.float32 and np.all(np.isfinite(f.depth_m))
            assert f.depth_m.shape == f.confidence.shape
        return "valid"
    except RecordingError as exc:
        msg = str(exc)
        assert "\n" not in msg, msg
        assert exc.path == str(root) or exc.path.startswith(str(root) + os.sep), msg
        return "error"


@pytest.fixture
def workspace(base_files: dict[str, bytes], request: pytest.FixtureRequest):
    ws = _Workspace(base_files, request.node.name.removeprefix("test_fuzz_"))
    yield ws
    ws.close()


def _assert_ran(ws: _Workspace, outcomes: Counter[str], min_errors: int) -> None:
    assert ws.n == EXAMPLES_PER_FAMILY, f"only {ws.n} examples ran"
    print(f"{ws.family}: {dict(outcomes)}")  # shown with pytest -s
    # the mutations must bite: a fuzzer whose every case is still valid proves nothing
    assert outcomes["error"] >= min_errors, outcomes


# --------------------------------------------------------------------------- 1. raw bytes
BYTE_OPS = ("flip", "truncate", "insert", "delete", "empty", "append", "overwrite_head")


def test_fuzz_bytes(workspace: _Workspace, base_files: dict[str, bytes]) -> None:
    outcomes: Counter[str] = Counter()
    names = sorted(base_files)

    @FUZZ_SETTINGS
    @given(
        rel=st.sampled_from(names),
        op=st.sampled_from(BYTE_OPS),
        pos=st.integers(0, 2**31 - 1),
        junk=st.binary(min_size=1, max_size=24),
        bit=st.integers(0, 7),
    )
    def check(rel: str, op: str, pos: int, junk: bytes, bit: int) -> None:
        def mutate(root: Path, _: Path) -> None:
            p = root / rel
            data = bytearray(p.read_bytes())
            i = pos % max(len(data), 1)
            if op == "flip" and data:
                data[i] ^= 1 << bit
            elif op == "truncate":
                data = data[:i]
            elif op == "insert":
                data[i:i] = junk
            elif op == "delete":
                del data[i : i + len(junk)]
            elif op == "empty":
                data = bytearray()
            elif op == "append":
                data += junk
            elif op == "overwrite_head":
                data[: len(junk)] = junk
            p.write_bytes(bytes(data))

        outcomes[workspace.run(mutate)] += 1

    check()
    _assert_ran(workspace, outcomes, min_errors=EXAMPLES_PER_FAMILY // 2)


# --------------------------------------------------------------------------- 2. CSV cells
CELL_VALUES = (
    "nan",
    "NaN",
    "inf",
    "-inf",
    "",
    " ",
    "abc",
    "1e400",
    "-1e400",
    "1e308",
    "-5",
    "1,2",
    "0x10",
    "1.0.0",
    "--1",
    "\t",
    "#",
    "None",
    "true",
    '"1"',
    "9" * 400,
    "0",
    "-0",
)
CSV_OPS = (
    "cell",
    "cell_text",
    "negate",
    "scale",
    "swap_rows",
    "dup_row",
    "del_row",
    "del_column",
    "reverse",
    "header_cell",
)


def _split(line: str, sep: str) -> list[str]:
    return line.split(sep) if sep == "," else line.split()


def test_fuzz_csv(workspace: _Workspace) -> None:
    outcomes: Counter[str] = Counter()

    @FUZZ_SETTINGS
    @given(
        rel=st.sampled_from(CSV_FILES + TUM_FILES),
        op=st.sampled_from(CSV_OPS),
        row=st.integers(0, 10**6),
        col=st.integers(0, 10**6),
        other=st.integers(0, 10**6),
        value=st.sampled_from(CELL_VALUES),
        text=st.text(max_size=8),
        factor=st.sampled_from((1e3, 1e-3, 57.2958, 1 / 9.81, 1e9, -1.0, 0.0)),
    )
    def check(
        rel: str, op: str, row: int, col: int, other: int, value: str, text: str, factor: float
    ) -> None:
        def mutate(root: Path, _: Path) -> None:
            p = root / rel
            sep = "," if rel.endswith(".csv") else " "
            lines = p.read_text(encoding="utf-8").splitlines()
            first = 1  # the header (CSV) or the comment line (TUM)
            body = lines[first:]
            r, r2 = row % len(body), other % len(body)
            cells = _split(body[r], sep)
            c = col % len(cells)
            if op in ("cell", "cell_text", "negate", "scale"):
                if op == "cell":
                    cells[c] = value
                elif op == "cell_text":
                    cells[c] = text
                elif op == "negate":
                    cells[c] = cells[c][1:] if cells[c].startswith("-") else "-" + cells[c]
                else:  # a unit mistake in one whole column
                    for k, line in enumerate(body):
                        cs = _split(line, sep)
                        cs[c] = repr(float(cs[c]) * factor)
                        body[k] = sep.join(cs)
                    cells = _split(body[r], sep)
                body[r] = sep.join(cells)
            elif op == "swap_rows":
                body[r], body[r2] = body[r2], body[r]
            elif op == "dup_row":
                body.insert(r, body[r])
            elif op == "del_row":
                del body[r]
            elif op == "del_column":
                body = [sep.join(cs[:c] + cs[c + 1 :]) for cs in (_split(b, sep) for b in body)]
            elif op == "reverse":
                body = body[::-1]
            elif op == "header_cell":
                head = lines[0].split(",")
                head[c % len(head)] = text
                lines[0] = ",".join(head)
            p.write_text("\n".join(lines[:first] + body) + "\n", encoding="utf-8")

        outcomes[workspace.run(mutate)] += 1

    check()
    _assert_ran(workspace, outcomes, min_errors=EXAMPLES_PER_FAMILY // 2)


# --------------------------------------------------------------------------- 3. metadata.yaml
def _paths(node: object, prefix: tuple = ()) -> list[tuple]:
    out = [prefix] if prefix else []
    if isinstance(node, dict):
        for k, v in node.items():
            out += _paths(v, (*prefix, k))
    elif isinstance(node, list):
        for i, v in enumerate(node):
            out += _paths(v, (*prefix, i))
    return out


WRONG_VALUES = st.one_of(
    st.none(),
    st.booleans(),
    st.integers(-(2**70), 2**70),
    st.floats(allow_nan=True, allow_infinity=True),
    st.text(max_size=12),
    st.sampled_from(["../imu.csv", "/etc/passwd", "depth/depth_mm.npy", "1e3", "30 Hz", ""]),
    st.lists(st.integers(), max_size=4),
    st.dictionaries(st.text(max_size=4), st.integers(), max_size=2),
)
YAML_TEXT_EDITS = (
    "!!python/object/apply:os.system ['echo pwned']\n",
    "camera: !!python/name:os.system\n",
    "format_version: 1\nformat_version: 2\n",
    "imu_file: ../outside/imu.csv\n",
    "files: {imu: /etc/passwd}\n",
    "%YAML 9.9\n---\n",
    "[" * 2000,
    "a: &x [*x]\n",
    "- just\n- a list\n",
    "\t:\n",
    "",
)
YAML_OPS = ("delete", "set", "extra_key", "version", "text_append", "text_replace", "flow_garble")


def test_fuzz_yaml(workspace: _Workspace, base_files: dict[str, bytes]) -> None:
    outcomes: Counter[str] = Counter()
    base = yaml.safe_load(base_files["metadata.yaml"])
    paths = _paths(base)

    @FUZZ_SETTINGS
    @given(
        op=st.sampled_from(YAML_OPS),
        path=st.sampled_from(paths),
        value=WRONG_VALUES,
        key=st.text(min_size=1, max_size=10),
        version=st.integers(-3, 10**12),
        edit=st.sampled_from(YAML_TEXT_EDITS),
        pos=st.integers(0, 10**6),
    )
    def check(
        op: str, path: tuple, value: object, key: str, version: int, edit: str, pos: int
    ) -> None:
        def mutate(root: Path, _: Path) -> None:
            p = root / "metadata.yaml"
            if op in ("text_append", "text_replace", "flow_garble"):
                text = p.read_text(encoding="utf-8")
                if op == "text_append":
                    text += edit
                elif op == "text_replace":
                    text = edit
                else:  # a stray YAML indicator in the middle of the text
                    i = pos % len(text)
                    text = text[:i] + "{[:&*!|>'\"%@`"[pos % 13] + text[i:]
                p.write_text(text, encoding="utf-8")
                return
            doc = yaml.safe_load(p.read_text(encoding="utf-8"))
            parent = doc
            for k in path[:-1]:
                parent = parent[k]
            if op == "delete":
                del parent[path[-1]]
            elif op == "set":
                parent[path[-1]] = value
            elif op == "extra_key":
                target = parent[path[-1]] if isinstance(parent[path[-1]], dict) else parent
                if isinstance(target, dict):
                    target[key] = value
                else:
                    doc[key] = value
            elif op == "version":
                doc["format_version"] = version
            p.write_text(yaml.safe_dump(doc), encoding="utf-8")

        outcomes[workspace.run(mutate)] += 1

    check()
    _assert_ran(workspace, outcomes, min_errors=EXAMPLES_PER_FAMILY // 2)


# --------------------------------------------------------------------------- 4. .npy files
NPY_DTYPES = (
    "<u2",
    ">u2",
    "u1",
    "<i2",
    "<u4",
    "<f4",
    ">f4",
    "<f8",
    "?",
    "<c8",
    "S2",
    "U1",
    "V2",
    "<u2,<u2",
)
NPY_OPS = (
    "dtype",
    "shape",
    "fortran",
    "pickle",
    "npz",
    "header_byte",
    "magic",
    "version",
    "header_len",
    "zero_frames",
    "values",
)


def test_fuzz_npy(workspace: _Workspace) -> None:
    outcomes: Counter[str] = Counter()

    @FUZZ_SETTINGS
    @given(
        rel=st.sampled_from(NPY_FILES),
        op=st.sampled_from(NPY_OPS),
        dtype=st.sampled_from(NPY_DTYPES),
        shape_delta=st.tuples(st.integers(-2, 2), st.integers(-2, 2), st.integers(-2, 2)),
        extra_dims=st.integers(-2, 1),
        pos=st.integers(0, 10**6),
        byte=st.integers(0, 255),
        fill=st.sampled_from((0, 1, 65535, 50, 2400, 5000, 255)),
    )
    def check(
        rel: str,
        op: str,
        dtype: str,
        shape_delta: tuple[int, int, int],
        extra_dims: int,
        pos: int,
        byte: int,
        fill: int,
    ) -> None:
        def mutate(root: Path, _: Path) -> None:
            p = root / rel
            arr = np.load(p, allow_pickle=False)
            if op == "dtype":
                np.save(
                    p,
                    arr.astype(np.dtype(dtype))
                    if dtype not in ("V2", "<u2,<u2")
                    else np.zeros(arr.shape, dtype=np.dtype(dtype)),
                )
            elif op == "shape":
                shape = tuple(max(0, s + d) for s, d in zip(arr.shape, shape_delta, strict=True))
                shape = (
                    shape[: len(shape) + extra_dims]
                    if extra_dims < 0
                    else shape + (1,) * extra_dims
                )
                np.save(p, np.resize(arr, shape))
            elif op == "fortran":
                np.save(p, np.asfortranarray(arr))
            elif op == "pickle":
                np.save(p, np.array([{"a": 1}, None], dtype=object), allow_pickle=True)
            elif op == "npz":
                buf = io.BytesIO()
                np.savez(buf, arr)
                p.write_bytes(buf.getvalue())
            elif op == "zero_frames":
                np.save(p, arr[:0])
            elif op == "values":
                np.save(p, np.full_like(arr, fill % (np.iinfo(arr.dtype).max + 1)))
            else:  # edits inside the header: magic, version, header length, header text
                data = bytearray(p.read_bytes())
                header_len = int.from_bytes(data[8:10], "little")
                if op == "magic":
                    data[pos % 6] = byte
                elif op == "version":
                    data[6 + pos % 2] = byte
                elif op == "header_len":
                    data[8 + pos % 2] = byte
                else:
                    data[10 + pos % header_len] = byte
                p.write_bytes(bytes(data))

        outcomes[workspace.run(mutate)] += 1

    check()
    _assert_ran(workspace, outcomes, min_errors=EXAMPLES_PER_FAMILY // 2)


# --------------------------------------------------------------------------- 5. file system
FS_OPS = (
    "delete",
    "dir_for_file",
    "symlink_outside",
    "symlink_inside",
    "symlink_dangling",
    "symlink_loop",
    "symlink_dir_outside",
    "delete_dir",
    "extra_file",
    "root_is_file",
    "root_symlink",
    "fifo_for_file",
    "hardlink_inside",
)


def test_fuzz_filesystem(workspace: _Workspace, base_files: dict[str, bytes]) -> None:
    outcomes: Counter[str] = Counter()
    names = sorted(base_files)

    @FUZZ_SETTINGS
    @given(
        op=st.sampled_from(FS_OPS),
        rel=st.sampled_from(names),
        other=st.sampled_from(names),
        folder=st.sampled_from(("depth", "groundtruth")),
        junk=st.binary(max_size=16),
        then_flip=st.integers(-1, 10**6),
    )
    def check(op: str, rel: str, other: str, folder: str, junk: bytes, then_flip: int) -> None:
        def mutate(root: Path, outside: Path) -> None:
            p = root / rel
            if op == "delete":
                p.unlink()
            elif op == "dir_for_file":
                p.unlink()
                p.mkdir()
            elif op == "symlink_outside":  # same bytes, but the link leaves the folder
                copy = outside / p.name
                shutil.copy(p, copy)
                p.unlink()
                p.symlink_to(copy)
            elif op == "symlink_inside":
                p.unlink()
                p.symlink_to(os.path.relpath(root / other, p.parent))
            elif op == "symlink_dangling":
                p.unlink()
                p.symlink_to(root / "does_not_exist")
            elif op == "symlink_loop":
                p.unlink()
                p.symlink_to(p.name)
            elif op == "symlink_dir_outside":
                shutil.move(root / folder, outside / folder)
                (root / folder).symlink_to(outside / folder, target_is_directory=True)
            elif op == "delete_dir":
                shutil.rmtree(root / folder)
            elif op == "extra_file":
                (root / folder / f"extra_{len(junk)}.bin").write_bytes(junk)
            elif op == "root_is_file":
                shutil.rmtree(root)
                root.write_bytes(junk)
            elif op == "root_symlink":
                real = outside / "real_rec"
                shutil.move(root, real)
                root.symlink_to(real, target_is_directory=True)
            elif op == "fifo_for_file":
                p.unlink()
                os.mkfifo(p)
            elif op == "hardlink_inside":
                p.unlink()
                os.link(root / other, p) if other != rel else p.write_bytes(junk)
            if then_flip >= 0 and op in ("extra_file", "root_symlink") and rel.endswith(".csv"):
                q = root / rel
                data = bytearray(q.read_bytes())
                data[then_flip % len(data)] ^= 0x10
                q.write_bytes(bytes(data))

        outcomes[workspace.run(mutate)] += 1

    check()
    _assert_ran(workspace, outcomes, min_errors=EXAMPLES_PER_FAMILY // 3)


def test_fuzz_total_examples() -> None:
    """Runs after the five families (file order): proves >= 1000 mutated recordings per run."""
    if len(RUN_COUNTS) < FAMILIES:
        pytest.skip("run the whole module to count examples")
    assert sum(RUN_COUNTS.values()) >= MIN_TOTAL_EXAMPLES, RUN_COUNTS


# --------------------------------------------------------------------------- known gaps
# Explicit cases for problems the reader did not catch before this file existed (several were
# found by the families above): each must raise RecordingError naming the file and the problem.
def _edit_rows(rel: str, fn: Callable[[list[list[str]]], None]) -> Callable[[Path], None]:
    def mutate(root: Path) -> None:
        lines = (root / rel).read_text().splitlines()
        rows = [line.split(",") for line in lines[1:]]
        fn(rows)
        (root / rel).write_text("\n".join([lines[0]] + [",".join(r) for r in rows]) + "\n")

    return mutate


def _set_meta(fn: Callable[[dict], None]) -> Callable[[Path], None]:
    def mutate(root: Path) -> None:
        d = yaml.safe_load((root / "metadata.yaml").read_text())
        fn(d)
        (root / "metadata.yaml").write_text(yaml.safe_dump(d))

    return mutate


def _swap_times(rows: list[list[str]]) -> None:
    rows[2][1], rows[3][1] = rows[3][1], rows[2][1]


def _shift_times(rows: list[list[str]]) -> None:
    for r in rows:
        r[0] = repr(float(r[0]) + 100.0)


def _npz(root: Path) -> None:
    buf = io.BytesIO()
    np.savez(buf, depth=np.load(root / "depth/depth_mm.npy"))
    (root / "depth/depth_mm.npy").write_bytes(buf.getvalue())


def _header_len(root: Path) -> None:
    p = root / "depth/depth_mm.npy"
    data = bytearray(p.read_bytes())
    data[8] = 1  # header length 1 + 256 * data[9]: the header text is cut inside its dict
    p.write_bytes(bytes(data))


def _symlink_loop(root: Path) -> None:
    (root / "joints.csv").unlink()
    (root / "joints.csv").symlink_to("joints.csv")


def _fifo(root: Path) -> None:
    (root / "imu.csv").unlink()
    os.mkfifo(root / "imu.csv")  # opening it for reading would block forever


GAPS = {
    "depth timestamps backwards": (
        _edit_rows("depth/timestamps.csv", _swap_times),
        "timestamps.csv",
        "backwards",
    ),
    "frames.csv flag not 0/1": (
        _edit_rows("groundtruth/frames.csv", lambda rows: rows[1].__setitem__(2, "5")),
        "frames.csv",
        "0 or 1",
    ),
    "frames.csv other times": (
        _edit_rows("groundtruth/frames.csv", _swap_times),
        "frames.csv",
        "backwards",
    ),
    "joints on another clock": (
        _edit_rows("joints.csv", _shift_times),
        "joints.csv",
        "different clocks",
    ),
    "imu truncated at a row": (
        _edit_rows("imu.csv", lambda rows: rows.__delitem__(slice(len(rows) // 2, None))),
        "imu.csv",
        "declares duration_s",
    ),
    "npz named .npy": (_npz, "depth_mm.npy", "not a .npy array"),
    "npy header cut": (_header_len, "depth_mm.npy", "not a readable .npy array"),
    "pickled npy": (
        lambda r: np.save(r / "depth/confidence.npy", np.array([{}, None]), allow_pickle=True),
        "confidence.npy",
        "not a readable",
    ),
    "metres stored in mm units": (
        _set_meta(lambda d: d["camera"].update(depth_unit_m=1e-6)),
        "depth_mm.npy",
        "below half the camera's min range",
    ),
    "all frames empty": (
        lambda r: np.save(
            r / "depth/depth_mm.npy", np.zeros(np.load(r / "depth/depth_mm.npy").shape, np.uint16)
        ),
        "depth_mm.npy",
        "empty frames",
    ),
    "yaml nan": (
        _set_meta(lambda d: d["camera"].update(fx_px=float("nan"))),
        "metadata.yaml",
        "[camera.fx_px]: NaN",
    ),
    "yaml recursive alias": (
        lambda r: (r / "metadata.yaml").write_text(
            (r / "metadata.yaml").read_text() + "loop: &x [*x]\n"
        ),
        "metadata.yaml",
        "nested too deeply",
    ),
    "yaml newline key": (
        _set_meta(lambda d: d.update({"a\nb": 1})),
        "metadata.yaml",
        "[a\\nb]: Extra inputs",
    ),
    "yaml python tag": (
        lambda r: (r / "metadata.yaml").write_text("!!python/object/apply:os.system ['true']\n"),
        "metadata.yaml",
        "not valid YAML",
    ),
    "yaml names a file": (
        _set_meta(lambda d: d.update(imu_file="/etc/passwd")),
        "metadata.yaml",
        "[imu_file]: Extra inputs are not permitted",
    ),
    "symlink loop": (_symlink_loop, "joints.csv", "cannot be opened"),
    "fifo": (_fifo, "imu.csv", "not a regular file"),
    "NUL bytes": (
        lambda r: (r / "joints.csv").write_bytes((r / "joints.csv").read_bytes()[:60] + b"\0\0\0"),
        "joints.csv",
        "NUL bytes",
    ),
}


@pytest.mark.parametrize("case", list(GAPS))
def test_known_gap_rejected(tiny_recording: Path, case: str) -> None:
    mutate, fname, words = GAPS[case]
    mutate(tiny_recording)
    with pytest.raises(RecordingError) as exc:
        Recording.open(tiny_recording)
    msg = str(exc.value)
    assert fname in msg and words in msg and "\n" not in msg, msg


def test_metadata_cannot_redirect_reads(tiny_recording: Path, tmp_path: Path) -> None:
    """Free-form metadata (provenance.config) may mention paths; the reader still reads only
    its fixed file names inside the folder."""
    original = Recording.open(tiny_recording).imu.accel_mps2
    decoy = tmp_path / "decoy"
    shutil.copytree(tiny_recording, decoy)
    _edit_rows("imu.csv", lambda rows: [r.__setitem__(3, repr(float(r[3]) + 0.5)) for r in rows])(
        decoy
    )
    _set_meta(
        lambda d: d["provenance"]["config"].update(
            imu_file=str(decoy / "imu.csv"), recording=str(decoy), depth="../decoy/depth"
        )
    )(tiny_recording)
    rec = Recording.open(tiny_recording)
    np.testing.assert_array_equal(rec.imu.accel_mps2, original)
    assert rec.metadata.provenance.config["imu_file"] == str(decoy / "imu.csv")


def test_spreadsheet_bom_accepted(tiny_recording: Path) -> None:
    p = tiny_recording / "joints.csv"
    p.write_bytes(b"\xef\xbb\xbf" + p.read_bytes())
    assert len(Recording.open(tiny_recording).joints) == 100
