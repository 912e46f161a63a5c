"""The replay: one recording's streams in time order through every estimator.

The online estimator (front end + SP-ESKF, vio_graph/estimator.py) turns each IMU sample and
each depth frame into the records of the estimator protocol (vio_graph/protocol.py); every
estimator of the run -- the filter's own track, the IMU-only and ICP-only baselines, and, if
asked for, the fixed-lag and batch smoothers -- takes the same records through the same
calls. The per-frame quantities the outputs need are collected in a :class:`FrameLog`.

Retroactive re-run: once the camera-IMU offset is applied early in the trial
(``filter.time_offset.rerun_window_s``), every estimator starts again from the first event
with the offset applied from the first frame (:meth:`Replay._restart`), so the written
trajectories do not keep what was fused with the wrong offset; the first pass's filter
estimates for those frames (what an online consumer got) are kept beside them.
"""

from __future__ import annotations

import dataclasses
import logging
import math
from collections.abc import Callable, Iterator
from dataclasses import dataclass, field
from typing import Any

import numpy as np
from numpy.typing import NDArray

from vio_graph.config import PipelineConfig
from vio_graph.errors import EstimationError
from vio_graph.estimator import OnlineEstimator, RigGeometry
from vio_graph.filter.baselines import IcpOdometry, ImuDeadReckoning
from vio_graph.filter.time_offset import centred_clock_line
from vio_graph.frontend.icp import AUTO_COMPILED_MIN_FRAMES, use_compiled_by_default
from vio_graph.geometry import rotate_xz
from vio_graph.growable import GrowableArray
from vio_graph.memory import return_free_heap
from vio_graph.protocol import Estimator, FilterTrack, FrameRecord, ImuStep
from vio_graph.recording.reader import Recording
from vio_graph.recording.streams import ImuTable
from vio_graph.safety.online import SafetyLog
from vio_graph.types import Displacement2D
from vio_graph.viz.run_view import RunView

log = logging.getLogger(__name__)

MODES = ("filter", "smoother", "batch")
#: modes run only when named (never by ``--mode all``): GTSAM's legged-robot InEKF as a peer
PEER_MODES = ("gtsam_legged",)
BASELINES = ("imu_only", "icp_only")


class TimingTable:
    """Per-frame stage timings (ms): one float64 column per stage, grown by doubling, so a
    long trial keeps 8 bytes a value instead of a dict a frame (~1 KB). Reads like the list
    of dicts it replaces: ``table[k]`` is frame k's ``{stage: ms}`` (stages that frame did not
    time left out), iteration yields those dicts; :meth:`column` gives one stage as an array
    (NaN where not timed)."""

    def __init__(self) -> None:
        self._cols: dict[str, NDArray[np.float64]] = {}
        self._n = 0
        self._cap = 0

    def append(self, row: dict[str, float]) -> None:
        if self._n == self._cap:
            self._cap = max(64, 2 * self._cap)
            for name, col in self._cols.items():
                grown = np.full(self._cap, np.nan)
                grown[: self._n] = col[: self._n]
                self._cols[name] = grown
        for name, ms in row.items():
            if name not in self._cols:
                self._cols[name] = np.full(self._cap, np.nan)
            self._cols[name][self._n] = ms
        self._n += 1

    def __len__(self) -> int:
        return self._n

    def __getitem__(self, k: int) -> dict[str, float]:
        if not -self._n <= k < self._n:
            raise IndexError(f"frame {k} of {self._n}")
        k %= self._n
        return {name: float(col[k]) for name, col in self._cols.items() if not np.isnan(col[k])}

    def __iter__(self):
        return (self[k] for k in range(self._n))

    def column(self, name: str) -> NDArray[np.float64]:
        """Stage ``name`` (ms) at every frame, NaN where it was not timed."""
        col = self._cols.get(name)
        return np.full(self._n, np.nan) if col is None else col[: self._n].copy()


def _rows_2x2() -> GrowableArray:
    return GrowableArray((2, 2))


@dataclass
class FrameLog:
    """Per-frame quantities collected during the replay (one entry per depth frame; the
    numbers in float64 columns, vio_graph/growable.py, the rest in lists); ``camera_xz``
    holds every estimator's camera path once the replay has finished."""

    t_s: GrowableArray = field(default_factory=GrowableArray)
    camera_xz: dict[str, NDArray[np.float64]] = field(default_factory=dict)
    #: shank pitch (N,) rad of the modes whose leg kinematics use their own attitude
    #: (keyframe smoothers with ``smoother.leg_attitude: smoothed``); others use shank_pitch_imu
    shank_pitch_by_mode: dict[str, NDArray[np.float64]] = field(default_factory=dict)
    shank_pitch_imu: GrowableArray = field(default_factory=GrowableArray)
    shank_pitch_chain: GrowableArray = field(default_factory=GrowableArray)
    ankle_rad: GrowableArray = field(default_factory=GrowableArray)
    status: list[str] = field(default_factory=list)
    terrain: list[str] = field(default_factory=list)
    displacement_ok: list[bool] = field(default_factory=list)
    rejection: list[str] = field(default_factory=list)
    is_keyframe: list[bool] = field(default_factory=list)
    profiles: dict[int, NDArray[np.float64]] = field(default_factory=dict)  # keyframes only
    timings_ms: TimingTable = field(default_factory=TimingTable)
    in_stance: list[bool] = field(default_factory=list)  # stance anchor used at this frame
    displacements: list[Displacement2D] = field(default_factory=list)  # the front end's
    safety: SafetyLog = field(default_factory=SafetyLog)  # SafetyEstimate | None per frame
    cov_position_m2: GrowableArray = field(default_factory=_rows_2x2)  # filter, m^2
    #: :meth:`profiles_of`'s answers by mode, with what each was computed from
    _turned: dict[str, tuple[bytes, list, dict[int, NDArray[np.float64]]]] = field(
        default_factory=dict, repr=False, compare=False
    )

    def add(self, record: FrameRecord) -> None:
        est, res = record.estimate, record.frontend
        self.t_s.append(est.timestamp_s)
        self.shank_pitch_imu.append(record.shank_pitch_imu_rad)
        self.shank_pitch_chain.append(record.shank_pitch_chain_rad)
        self.ankle_rad.append(record.ankle_rad)
        self.status.append(est.status.value)
        self.terrain.append(res.terrain.value)
        self.displacement_ok.append(record.displacement is not None)
        if record.displacement is not None:
            self.displacements.append(record.displacement)
        self.in_stance.append(record.in_stance)
        self.rejection.append(res.rejection_reason or "")
        self.is_keyframe.append(est.is_keyframe)
        if est.is_keyframe:
            self.profiles[len(self.t_s) - 1] = res.profile_xz_m
        self.timings_ms.append(est.timings_ms)
        self.safety.append(est.safety)
        self.cov_position_m2.append(est.cov_position_m2)

    def profiles_of(self, mode: str) -> dict[int, NDArray[np.float64]]:
        """The keyframe profiles (frame index -> (M, 2), camera-relative, m) at ``mode``'s
        own keyframe attitude, to be placed at that mode's camera positions.

        ``profiles`` are camera-relative in ground axes: turned by the filter's attitude at
        the keyframe. A mode with its own attitude (``shank_pitch_by_mode``: a keyframe
        smoother's refined pitch, which its heel and toe use) turns each profile about the
        camera by its pitch minus the filter's (rot_y; the camera is on the shank). Without
        it, the profile sits at the smoothed position with the filter's pitch, a pose no
        estimator made: 0.3 deg moves a point 1 m ahead of the camera by 5 mm vertically
        (docs/method.md, "The smoothed modes' map and clearance"). Other modes, and frames
        without a finite correction: the profiles as they are (the same arrays). Asked again
        with the same turns and profile arrays, a mode gets the dict of its first call (not
        to be changed by the caller; nor may the profile arrays be changed in place)."""
        pitch = self.shank_pitch_by_mode.get(mode)
        if pitch is None:
            return self.profiles
        turn = np.asarray(pitch, dtype=float) - np.asarray(self.shank_pitch_imu, dtype=float)
        # asked for by the safety replay and by the map (a batch run's map is the batch's):
        # every keyframe turned once (~12,000 on a 10-minute trial; ~25 us each), the answer
        # kept while the turns are the same bits and the keyframes the same profile arrays
        source = list(self.profiles.items())
        done = self._turned.get(mode)
        if (
            done is not None
            and done[0] == turn.tobytes()
            and len(done[1]) == len(source)
            and all(k == j and p is q for (k, p), (j, q) in zip(source, done[1], strict=True))
        ):
            return done[2]
        out: dict[int, NDArray[np.float64]] = {}
        for k, prof in source:
            a = float(turn[k])
            out[k] = rotate_xz(a, prof) if math.isfinite(a) and a != 0.0 else prof
        self._turned[mode] = (turn.tobytes(), source, out)
        return out


def replay_order(rec: Recording) -> tuple[NDArray[np.int8], NDArray[np.int64]]:
    """Event order by time: (kind, index) with kind 0 = IMU, 1 = joints, 2 = depth frame,
    3 = contact sample (recordings with ``contact.csv``).

    On equal timestamps IMU comes first, then joints, then contact, then the frame (no
    look-ahead: a frame only sees sensor data stamped at or before it).
    """
    times = [rec.imu.timestamp_s, rec.joints.timestamp_s, rec.frame_timestamps_s]
    if rec.contact is not None:
        times.append(rec.contact.timestamp_s)
    kinds = np.concatenate([np.full(t.shape[0], k, np.int8) for k, t in enumerate(times)])
    idx = np.concatenate([np.arange(t.shape[0]) for t in times])
    priority = np.array([0, 1, 3, 2], np.int8)[kinds]  # contact before the frame
    order = np.lexsort((priority, np.concatenate(times)))
    return kinds[order], idx[order]


def frames_due(rec: Recording, online: OnlineEstimator) -> Iterator[int]:
    """Feed ``online`` the IMU, joint and contact samples of ``rec`` in time order
    (:func:`replay_order`) and yield the index of each depth frame as it falls due, once the
    estimator is initialised; the caller processes it (``online.add_frame``). The plain loop
    of the diagnostic benchmarks: no camera-IMU offset and no frame held for a repaired IMU
    packet (:class:`Replay` does both)."""
    kinds, idx = replay_order(rec)
    for kind, i in zip(kinds.tolist(), idx.tolist(), strict=True):
        if kind == 0:
            online.add_imu(rec.imu.sample(i))
        elif kind == 1:
            online.add_joints(rec.joints.sample(i))
        elif kind == 3:
            assert rec.contact is not None
            online.add_contact(rec.contact.sample(i))
        elif online.initialised:
            yield i


def sensor_data_bound(rec: Recording, kinds: NDArray[np.int8], idx: NDArray[np.int64]):
    """For each event of :func:`replay_order`, the stamp (s) of the first IMU, joint or
    contact event at or after it (inf after the last). Every sensor sample stamped before
    that bound has been taken when the event is reached, and none after it: a frame whose
    capture time is below the bound sees exactly the samples stamped at or before it, as a
    frame in the recorded order does."""
    streams = [rec.imu.timestamp_s, rec.joints.timestamp_s, rec.frame_timestamps_s]
    streams.append(rec.contact.timestamp_s if rec.contact is not None else np.empty(0))
    stamps = np.empty(kinds.size)
    for k, t in enumerate(streams):
        sel = kinds == k
        stamps[sel] = np.asarray(t, dtype=float)[idx[sel]]
    stamps[kinds == 2] = np.inf
    return np.minimum.accumulate(stamps[::-1])[::-1]


def make_estimators(
    config: PipelineConfig, rig: RigGeometry, modes: set[str], p0: NDArray[np.float64]
) -> dict[str, Estimator]:
    """The estimators of a run, by mode name: the filter's track and the two baselines
    always, the fixed-lag (``smoother``) and batch smoothers and the GTSAM legged peer
    (``gtsam_legged``, vio_graph/filter/legged_peer.py) when ``modes`` asks for them."""
    estimators: list[Estimator] = [
        FilterTrack(),
        ImuDeadReckoning(config.filter, rig.shank_imu_T_cam, initial_camera_xz_m=p0),
        IcpOdometry(initial_camera_xz_m=p0),
    ]
    if "smoother" in modes:
        from vio_graph.smoother.sliding_window import SlidingWindowSmoother

        estimators.append(SlidingWindowSmoother(config.smoother, rig.shank_imu_T_cam))
    if "batch" in modes:
        from vio_graph.smoother.batch import BatchSmoother

        estimators.append(BatchSmoother(config.smoother, rig.shank_imu_T_cam))
    if "gtsam_legged" in modes:
        from vio_graph.filter.legged_peer import GtsamLeggedPeer

        estimators.append(GtsamLeggedPeer(rig.shank_imu_T_cam, initial_camera_xz_m=p0))
    return {e.name: e for e in estimators}


def _at_time(step: ImuStep, t_s: float) -> ImuStep:
    """``step`` with both its samples at time ``t_s`` (s)."""
    return ImuStep(
        shank=dataclasses.replace(step.shank, timestamp_s=t_s),
        corrected=dataclasses.replace(step.corrected, timestamp_s=t_s),
    )


def retimed_imu(
    rec: Recording, config: PipelineConfig, lookahead_s: float | None = None
) -> ImuTable | None:
    """The recording's IMU table with its stamps on their offline clock line
    (``filter.time_offset.imu_clock_offline_half_window``, filter/time_offset.py
    :func:`centred_clock_line`), or None when the stamps stay as recorded (no jitter, the
    option off, no IMU rate).

    Why: under stamp jitter the online clock model leaves the IMU samples 0.2-0.7 ms off
    their true times (one-sided fit, few samples at the start), and the smoothers' toe x
    error grows with that residual (obstacle seeds 1-5 under 2 ms of jitter 1.9x the clean
    run; with the true times given to the clock model, the clean run's; docs/robustness.md
    "Clock jitter in the smoothers"). A recording is replayed as a whole, so each stamp can
    take the line fitted on both sides of it (0.07-0.1 ms off the true times on the
    simulated trials). The smoothers (fixed-lag and batch) take these times; the
    filter, whose per-frame answer is what an online consumer gets, keeps the one-sided
    line, so its answer does not change. ``lookahead_s`` (s) caps the stamps used after each
    sample: the fixed-lag smoother's lag, since its estimate of a keyframe is frozen one lag
    after it; None for the batch smoother, which sees the whole recording."""
    half = config.filter.time_offset.imu_clock_offline_half_window
    rate = rec.metadata.imu.rate_hz
    if half <= 0 or not rate or not config.filter.time_offset.imu_clock_model:
        return None
    imu = rec.imu
    ahead = None if lookahead_s is None else int(lookahead_s * rate)
    line = centred_clock_line(
        imu.timestamp_s, 1.0 / rate, half, config.filter.time_offset.gap_periods, ahead=ahead
    )
    if line is None:
        return None
    return dataclasses.replace(imu, timestamp_s=line)


class Replay:
    """Drives the online estimator and every estimator of the run through one recording.

    ``viz`` receives the per-frame view (vio_graph/viz/run_view.py; a NullVisualizer logs
    nothing). After :meth:`run`, ``failed`` maps an estimator that raised EstimationError to
    when and why (it was fed nothing after that, and its answer holds what it solved).
    """

    def __init__(self, rec: Recording, config: PipelineConfig, modes: set[str], viz) -> None:
        #: the IMU stamps' offline clock line (:func:`retimed_imu`): RMS and largest move
        #: (s), None if the stamps were left as recorded
        self.imu_retimed: dict[str, float] | None = None
        imu = retimed_imu(rec, config)
        if imu is not None:
            moved = imu.timestamp_s - rec.imu.timestamp_s
            self.imu_retimed = {
                "rms_s": float(np.sqrt(np.mean(moved**2))),
                "max_s": float(np.max(np.abs(moved))),
            }
        # the smoothers' IMU times, by estimator name: the batch smoother's line uses the
        # whole recording, the fixed-lag smoother's looks ahead by its lag only; the online
        # estimator keeps its one-sided clock line, and every event keeps its recorded order
        self._imu_lines: dict[str, NDArray[np.float64]] = {}
        if imu is not None:
            self._imu_lines["batch"] = imu.timestamp_s
            lagged = retimed_imu(rec, config, config.smoother.smoother_lag_s())
            if lagged is not None:
                self._imu_lines["smoother"] = lagged.timestamp_s
        self.rec = rec
        self.config = config
        self.modes = modes
        # "auto": the compiled kernels for recordings long enough to win numba's start back,
        # decided per replay (not sticky), so that a run's answer never depends on what the
        # same process replayed before (serial and cluster studies give the same bits)
        use_compiled_by_default(rec.num_frames >= AUTO_COMPILED_MIN_FRAMES)
        self.rig = RigGeometry.from_metadata(rec.metadata)
        gt = rec.groundtruth
        p0 = None
        if gt is not None:  # place the estimate's origin at the true start (the paper's anchor)
            p0 = gt.trajectories["camera"].xz_at(rec.frame_timestamps_s[0])
        self.p0 = np.zeros(2) if p0 is None else p0
        self.online = OnlineEstimator(config, self.rig, p0)
        self.estimators = make_estimators(config, self.rig, modes, self.p0)
        self.view = RunView(
            viz, self.rig, rec.groundtruth, config.output, rec.metadata.camera.depth_unit_m
        )
        self.log = FrameLog()
        self._inject_rng = np.random.default_rng(config.inject.seed)
        self.injected_wrong_associations = 0
        self.failed: dict[str, dict[str, Any]] = {}
        #: the retroactive re-run (:meth:`_restart`): frames re-run, the last one's stamp,
        #: the offset applied and its sigma (s); None if there was none
        self.rerun: dict[str, Any] | None = None
        #: the filter's camera x-z (m) the first pass gave for those frames (what an online
        #: consumer received), None without a re-run
        self.first_pass_xz: NDArray[np.float64] | None = None
        #: the final pass (``time_offset.rerun_final``): frames of the pass before it, the
        #: offset held over it and the estimate and sigma it came from (s); None if none
        self.final_rerun: dict[str, Any] | None = None
        self._rerun_frame = -1
        self._first_imu_s: float | None = None  # stamp of the first IMU sample taken
        self._live: list[Estimator] = []  # :meth:`_running`'s answer for _live_key
        self._live_key: tuple[int, int, int] | None = None

    def run(self, progress: Callable[[int], Any] | None = None) -> FrameLog:
        """Every event of the recording in time order through every estimator. If the
        camera-IMU offset is applied early in the trial (``time_offset.rerun_window_s``), the
        replay restarts once from the first event with it applied from the start
        (:meth:`_restart`)."""
        kinds, idx = replay_order(self.rec)
        while not self._pass(kinds, idx, progress):
            self._restart()
        to_cfg = self.config.filter.time_offset
        if to_cfg.rerun_final and to_cfg.estimate and self.online.time_offset.latched:
            self._restart(final=True)
            if not self._pass(kinds, idx, progress):  # pragma: no cover - _rerun_due says no
                raise RuntimeError("the final pass asked for another re-run")
        self.rec.release_frame_pages()  # no frame is read again
        for e in self._running():
            self._guard(e, float("nan"), e.finish)
            if e.name == "batch":  # the solve's freed systems (a few hundred MiB on 10 min)
                return_free_heap()
        self.log.camera_xz = self.camera_paths()
        self.log.shank_pitch_by_mode = self.shank_pitch_paths()
        return self.log

    def _pass(
        self,
        kinds: NDArray[np.int8],
        idx: NDArray[np.int64],
        progress: Callable[[int], Any] | None,
    ) -> bool:
        """One pass over the events; False if it stopped for a retroactive re-run."""
        rec, online = self.rec, self.online
        imu, joints = rec.imu, rec.joints
        waiting: list[int] = []  # frames whose capture time the IMU has not reached yet
        bound = sensor_data_bound(rec, kinds, idx)
        # as Python ints and floats (the same values): ~100k events on a 10 min trial, where
        # numpy scalars cost ~0.1 us per comparison and per index
        events = zip(kinds.tolist(), idx.tolist(), bound.tolist(), strict=True)
        for kind, i, b in events:
            if kind != 2 and waiting and not self._release_frames(waiting, progress, b):
                return False
            if kind == 0:
                step = online.add_imu(imu.sample(i))
                if step is None:
                    continue  # stamp at or before the previous one: reported, not fused
                if self._first_imu_s is None:
                    self._first_imu_s = step.timestamp_s
                lines = self._imu_lines
                t_step = step.timestamp_s  # (a property: read once, not once per estimator)
                for e in self._running():
                    fed = step
                    if lines and e.name in lines:
                        fed = _at_time(step, float(lines[e.name][i]))
                    self._guard(e, t_step, e.add_imu, fed)
                # a frame held for a repaired packet (below) goes once this sample released it
                if waiting and not self._release_frames(waiting, progress, b):
                    return False
            elif kind == 1:
                online.add_joints(joints.sample(i))
            elif kind == 3:
                assert rec.contact is not None
                online.add_contact(rec.contact.sample(i))
            else:
                if not online.initialised and online.time_offset.applied_s >= 0:
                    continue  # frames before the first IMU sample cannot be placed
                # (with early camera stamps, td < 0, a frame stamped before the first IMU
                # sample may be captured after it: it waits like the others)
                waiting.append(i)
                if not self._release_frames(waiting, progress, b):
                    return False
        return self._release_frames(waiting, progress, np.inf)

    def _release_frames(
        self, waiting: list[int], progress: Callable[[int], Any] | None, bound_s: float
    ) -> bool:
        """Process the waiting frames whose capture time on the IMU clock (stamp minus the
        camera-IMU offset, filter/time_offset.py) is before ``bound_s``, the stamp of the next
        IMU, joint or contact sample (:func:`sensor_data_bound`): a frame then sees the
        samples stamped at or before its capture time and none after, as without an offset.
        A negative offset (early camera stamps) holds a frame until then. (Releasing it once
        the IMU was within one period of it gave it the IMU sample but not the joint sample
        of the same stamp, which comes next in the event order: the ankle encoder lagged the
        shank attitude by up to two periods, and at -30 ms the toe's foot-angle error doubled,
        downstair s1 0.80 -> 1.98 deg sd.) A frame captured after a repaired IMU packet that
        is still held back for the next sample (filter/imu_repair.py) waits for that sample
        too, instead of seeing the filter extrapolated across the packet. False if a
        retroactive re-run is due."""
        online = self.online
        while waiting:
            t_imu = online.last_imu_time_s
            if t_imu is None:  # only with td < 0: frames wait for the IMU to start
                return True
            t_cap = self.rec.frame_timestamps_s[waiting[0]] - online.time_offset.applied_s
            if t_cap >= bound_s:
                return True
            held = online.imu_held_back_s
            if held is not None and held <= t_cap and bound_s < np.inf:
                # a repaired IMU packet before the capture time waits for the next sample
                # (filter/imu_repair.py): the frame waits with it instead of extrapolating
                # the filter across the packet (a heel strike, 20 ms at 40 m/s^2: 8 mm)
                return True
            i = waiting.pop(0)
            if self._first_imu_s is not None and t_cap < self._first_imu_s:
                continue  # captured before the first IMU sample: cannot be placed
            self._frame(i)
            if progress is not None:
                progress(i + 1)
            if self._rerun_due(i):
                return False
        return True

    def _rerun_due(self, i: int) -> bool:
        """A retroactive re-run is due after frame ``i``: none yet, the time offset is applied
        (and, with ``rerun_sigma_s``, known to that sigma, or the window ends at the next
        frame), and frame ``i`` is within ``rerun_window_s`` of the first frame."""
        cfg = self.config.filter.time_offset
        to = self.online.time_offset
        if self.rerun is not None or self.final_rerun is not None:
            return False
        if cfg.rerun_window_s <= 0 or not to.latched:
            return False
        stamps = self.rec.frame_timestamps_s
        if stamps[i] - stamps[0] > cfg.rerun_window_s:
            return False
        self._rerun_frame = i
        if cfg.rerun_sigma_s is None or to.sigma_s <= cfg.rerun_sigma_s:
            return True
        nxt = stamps[i + 1] if i + 1 < stamps.size else np.inf
        return bool(nxt - stamps[0] > cfg.rerun_window_s)

    def _restart(self, final: bool = False) -> None:
        """Retroactive re-run: what the filter fused before the camera-IMU offset was known
        (slices rotated with the attitude at the wrong time, displacements at the wrong
        interval) would stay in its state, since nothing observes the absolute position
        afterwards. So every estimator starts again from the first event, the time-offset
        estimator carrying what it learnt (applied from the first frame, the tilts of the
        frames it has already used not counted twice). The per-frame estimates the first pass
        gave (what an online consumer received then) are kept in :attr:`first_pass_xz`.
        The estimators are built anew by :func:`make_estimators` (one added to
        :attr:`estimators` by hand is dropped, with a warning); the visualizer is sent the
        re-run frames again.

        ``final``: the pass after the last frame (``time_offset.rerun_final``). The early
        re-run starts with td known to ``rerun_sigma_s`` (1-3 ms off on downstair), and the
        frames before the estimate settles keep that error in the state; once every frame
        has been seen, the replay runs once more with td held at its final estimate
        (:meth:`TimeOffsetEstimator.final_offset_s`) from the first frame, counting no tilt
        again, so every frame is re-stamped by the same, best-known offset."""
        old = self.online
        to = old.time_offset
        t_s = np.asarray(self.log.t_s)
        if final:
            td = to.final_offset_s()
            self.final_rerun = {
                "frames": len(t_s),
                "applied_s": td,
                "estimate_s": to.td_s,
                "sigma_s": to.sigma_s,
            }
            stamp = np.inf  # no tilt counted again: td is held
        else:
            td = to.applied_s
            self.first_pass_xz = np.asarray(self.estimators["filter"].camera_path(t_s, t_s[:0]))
            stamp = float(self.rec.frame_timestamps_s[self._rerun_frame])
            self.rerun = {
                "frames": len(t_s),
                "until_stamp_s": stamp,
                "applied_s": td,
                "sigma_s": to.sigma_s,
            }
        gt = self.rec.groundtruth
        if gt is not None:  # the true camera at the first frame's capture time, as without td
            t0 = self.rec.frame_timestamps_s[0] - td
            self.p0 = gt.trajectories["camera"].xz_at(t0)
        self.online = OnlineEstimator(self.config, self.rig, self.p0)
        self.online.time_offset.carry_over(to)
        if final:
            self.online.time_offset.hold(td)
        self.online.td_counted_until_s = stamp
        estimators = make_estimators(self.config, self.rig, self.modes, self.p0)
        dropped = sorted(set(self.estimators) - set(estimators))
        if dropped:
            log.warning("re-run: estimators %s are not rebuilt and leave the run", dropped)
        self.estimators = estimators
        self._live_key = None
        self.log = FrameLog()
        self._inject_rng = np.random.default_rng(self.config.inject.seed)
        self.injected_wrong_associations = 0
        self.failed = {}

    def _frame(self, i: int) -> None:
        """One depth frame through the filter, then its record to every other estimator."""
        frame = self.rec.frame(i)
        record = self.online.process_frame(frame, transform_result=self._inject)
        self.log.add(record)
        t_s = record.timestamp_s
        for e in self._running():
            self._guard(e, t_s, e.add_frame, record)
        self.view.frame(i, frame, record)

    def camera_paths(self) -> dict[str, NDArray[np.float64]]:
        """Every estimator's camera x-z (N, 2) at the replayed frames, by mode; one without
        a usable answer gets the filter's."""
        t_s = np.asarray(self.log.t_s)
        filter_xz = self.estimators["filter"].camera_path(t_s, np.empty((0, 2)))
        out: dict[str, NDArray[np.float64]] = {}
        for name, e in self.estimators.items():
            try:  # a failed smoother still reports the keyframes it solved before failing
                out[name] = np.asarray(e.camera_path(t_s, filter_xz))
            except EstimationError as exc:
                log.warning("%s has no usable estimate: %s", name, exc)
                out[name] = filter_xz.copy()
        return out

    def shank_pitch_paths(self) -> dict[str, NDArray[np.float64]]:
        """Per-frame shank pitch (N,) rad of every keyframe smoother, from its own refined
        attitude (``smoother.leg_attitude: smoothed``; empty with ``filter``); a smoother
        without a usable answer is left out (its legs use the filter's pitch, as its camera
        path is the filter's)."""
        if self.config.smoother.leg_attitude != "smoothed":
            return {}
        t_s = np.asarray(self.log.t_s)
        pitch = np.asarray(self.log.shank_pitch_imu)
        out: dict[str, NDArray[np.float64]] = {}
        for name, e in self.estimators.items():
            path_of = getattr(e, "shank_pitch_path", None)
            if path_of is None:
                continue
            try:
                out[name] = np.asarray(path_of(t_s, pitch, self.rig.shank_pitch_rad))
            except EstimationError as exc:
                log.warning("%s has no usable attitude: %s", name, exc)
        return out

    def _running(self) -> list[Estimator]:
        """The estimators not failed, in order (a fresh list whenever the estimators or the
        failures change; asked once per event, ~100k times on a 10 min trial)."""
        key = (id(self.estimators), len(self.estimators), len(self.failed))
        if self._live_key != key:
            self._live = [e for name, e in self.estimators.items() if name not in self.failed]
            self._live_key = key
        return self._live

    def _guard(self, e: Estimator, t_s: float, fn: Callable[..., None], *args: Any) -> None:
        """Call an estimator; if it fails (e.g. GTSAM finds the system indeterminate), stop
        feeding it, keep what it solved, and record the failure instead of killing the run
        (the filter's answer stands in for the frames after it)."""
        try:
            fn(*args)
        except EstimationError as exc:
            log.warning("%s stopped at t=%.3f s: %s", e.name, t_s, str(exc).splitlines()[0])
            self.failed[e.name] = {"t_s": t_s, "error": str(exc).splitlines()[0]}

    def _inject(self, res):
        """Shift a displacement by a whole stair step (config.inject), for robustness tests."""
        inj = self.config.inject
        if res.displacement is None or inj.wrong_association_rate <= 0:
            return res
        if self._inject_rng.random() >= inj.wrong_association_rate:
            return res
        sign = 1.0 if self._inject_rng.random() < 0.5 else -1.0
        d = res.displacement
        bad = dataclasses.replace(d, delta_xz_m=d.delta_xz_m + sign * np.asarray(inj.step_xz_m))
        self.injected_wrong_associations += 1
        return dataclasses.replace(res, displacement=bad)
