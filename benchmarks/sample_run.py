"""A sampling profile of a whole ``vio-graph`` command: where its CPU time goes by stage of a
run and by module, without cProfile's per-call overhead (which inflates the many small calls
of a replay several times over).

The command line's entry point runs in this process; every ``--interval-ms`` of CPU time
(``setitimer(ITIMER_PROF)``; the kernel rounds it to its tick, ~4 ms here) a SIGPROF handler
looks at the Python stack. Per sample it counts the stage of a run the stack is in (the
online estimator's frames or IMU samples, reading a frame, the replay's own loop, building
the estimators, the start and end of ``run``, or the rest: interpreter, imports, command
line), every module on the stack once (inclusive) and the innermost frame's module and
function (self). Compiled (numba) kernels are not Python frames: their time is counted where
the interpreter resumes, mostly numba's ``_numba_unpickle``, which a kernel calls when it
boxes a returned array.

    python benchmarks/sample_run.py run REC --out OUT --mode filter --no-rerun --no-plots

Prints the tables (shares of the samples) on standard error; the command's own output goes
to standard output as usual.
"""

from __future__ import annotations

import argparse
import collections
import re
import signal
import sys
import time

import _common  # noqa: F401, I001 - before numpy: pins the thread pools numpy reads on import

#: (file name ending, function) -> stage; the innermost match on the stack wins
STAGES = (
    ("estimator.py", "process_frame", "online estimator: frames"),
    ("estimator.py", "add_imu", "online estimator: IMU samples"),
    ("reader.py", "frame", "reading depth frames"),
    ("replay.py", "__init__", "start-up: estimators and first kernels (Replay)"),
    ("replay.py", "_pass", "replay: other estimators, loop, frame log"),
    ("pipeline.py", "_run_into", "run: start and end (recording, map, metrics, files)"),
)
_PACKAGE = re.compile(r"(vio_graph/[\w/]+)\.py|site-packages/(\w+)")
_STDLIB = re.compile(r"python3\.\d+/(\w+)")


def _module(filename: str) -> str:
    m = _PACKAGE.search(filename)
    if m is not None:
        return m.group(1) or m.group(2)
    m = _STDLIB.search(filename)
    return filename.rsplit("/", 1)[-1] if m is None else "stdlib " + m.group(1)


class Sampler:
    def __init__(self) -> None:
        self.n = 0
        self.stages: collections.Counter[str] = collections.Counter()
        self.inclusive: collections.Counter[str] = collections.Counter()
        self.own: collections.Counter[str] = collections.Counter()
        self.functions: collections.Counter[tuple[str, str]] = collections.Counter()

    def __call__(self, signum, frame) -> None:
        if frame is None:
            return
        self.n += 1
        mod = _module(frame.f_code.co_filename)
        self.own[mod] += 1
        self.functions[(mod, frame.f_code.co_name)] += 1
        seen = set()
        stage = None
        f = frame
        while f is not None:
            code = f.f_code
            m = _module(code.co_filename)
            if m not in seen:
                seen.add(m)
                self.inclusive[m] += 1
            if stage is None:
                for ending, name, label in STAGES:
                    if code.co_name == name and code.co_filename.endswith(ending):
                        stage = label
                        break
            f = f.f_back
        self.stages[stage or "interpreter, imports, command line"] += 1

    def table(self, title: str, counts: collections.Counter, top: int) -> str:
        rows = [f"| {title} | samples | share |", "|---|---|---|"]
        for key, v in counts.most_common(top):
            name = key if isinstance(key, str) else " ".join(key)
            rows.append(f"| {name} | {v} | {100.0 * v / max(self.n, 1):.1f} % |")
        return "\n".join(rows)


def main() -> None:
    ap = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    ap.add_argument("--interval-ms", type=float, default=1.0)
    ap.add_argument("--top", type=int, default=25)
    ap.add_argument("command", nargs=argparse.REMAINDER, help="the vio-graph arguments")
    args = ap.parse_args()
    sampler = Sampler()
    signal.signal(signal.SIGPROF, sampler)
    s = args.interval_ms / 1e3
    t0 = time.process_time()
    signal.setitimer(signal.ITIMER_PROF, s, s)
    try:
        from vio_graph.cli import main as cli_main

        sys.argv = ["vio-graph", *args.command]
        try:
            cli_main()
        except SystemExit:
            pass
    finally:
        signal.setitimer(signal.ITIMER_PROF, 0.0, 0.0)
    cpu = time.process_time() - t0
    out = [
        f"{sampler.n} samples over {cpu:.2f} s CPU",
        sampler.table("stage", sampler.stages, args.top),
        sampler.table("module (inclusive)", sampler.inclusive, args.top),
        sampler.table("module (self)", sampler.own, args.top),
        sampler.table("function (self)", sampler.functions, args.top),
    ]
    sys.stderr.write("\n\n".join(out) + "\n")


if __name__ == "__main__":
    main()
