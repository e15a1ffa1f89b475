"""The two measurement methods behind one interface, feeding the analysis' one shared tail.

A :class:`MeasurementMethod` turns a session's frames into motion samples and hands each to the tail's
:class:`Outputs` as soon as it is final: the consecutive pairs' motion, every span's motion (chained, or registered
directly where the plan says), the motion from the reference frame where the method measures it directly, frame
flags, and its own tables in the results file (features and trajectories, or flow fields).
:func:`~skinstretch.experiments.analysis.pipeline.analyze` resolves the plan, runs the method, then the shared tail
(strain tables, cumulative tables, derived motion, movie, summary), whatever the method.
"""

from __future__ import annotations

import time
from collections import deque
from collections.abc import Iterator
from concurrent.futures import Executor, ThreadPoolExecutor
from contextlib import ExitStack
from dataclasses import dataclass
from typing import Any, Protocol

import numpy as np

from skinstretch.experiments.analysis.cumulative import feature_cumulative_samples, flow_cumulative_samples
from skinstretch.experiments.analysis.derive import chain_flows, rectified_sample
from skinstretch.experiments.analysis.frames import FrameReader
from skinstretch.experiments.analysis.measure import MeasurementRun, measure_features, measure_flow
from skinstretch.experiments.analysis.plan import AnalysisPlan
from skinstretch.experiments.analysis.trajectories import TrajectoryStore
from skinstretch.experiments.results_file import TRACK_DTYPE, ResultsWriter
from skinstretch.processing.displacement_refinement import SubpixelRefiner
from skinstretch.processing.feature_table import FEATURE_DTYPE, validate_features
from skinstretch.processing.pixel_scale import Calibration
from skinstretch.processing.span_registration import SampleUncertainty, SpanFrames, SpanRegistration
from skinstretch.processing.tracking import TRAJECTORY_DTYPE, MotionSample, Trajectories
from skinstretch.processing.trajectory_anchoring import KeyframeAnchoring

__all__ = ["Outputs", "MeasurementMethod", "FeatureMethod", "FlowMethod", "measurement_method",
           "SPAN_REGISTRATION_BATCH"]

#: Pairs whose longer spans are registered together (SpanRegistration.refine_all, on the run's worker count of
#: threads): their prepared frames, about this many plus the longest span, are held at once.
SPAN_REGISTRATION_BATCH = 16


class _SampleSink(Protocol):
    def add(self, sample: MotionSample) -> None: ...


class _SpanSink(Protocol):
    def add(self, span: int, sample: MotionSample) -> None: ...


@dataclass
class Outputs:
    """Where a method's results go (the shared tail's tables), and what it measures with."""

    writer: ResultsWriter
    motion: Any  # consecutive pairs: add(sample), flush()
    strain: _SpanSink
    cumulative: Any  # from the reference frame: add(sample); written, batch
    flags: list[str]
    calibration: Calibration
    mapping: Any
    spans: list[int]
    executor: Executor
    stack: ExitStack
    progress: bool = False

    def rectified(self, sample: MotionSample) -> MotionSample:
        """``sample`` on the skin (seed 3.4) when the session has a geometric mapping, else as it is."""
        return rectified_sample(sample, self.mapping, self.calibration.px_per_mm)


class MeasurementMethod(Protocol):
    """A measurement method: :meth:`measure` feeds ``out`` as it goes; :meth:`cumulative_samples` gives the motion
    from the reference frame that the method did not hand over while measuring (read from the results file)."""

    name: str

    def measure(self, reader: FrameReader, *, n: int, params, plan: AnalysisPlan, out: Outputs) -> MeasurementRun: ...

    def cumulative_samples(self, *, n: int, params, out: Outputs) -> Iterator[MotionSample]: ...


class FeatureMethod:
    """Seed 5.1: features tracked frame to frame, refined to sub-pixel, their trajectories stored; the motion of
    every span follows from the trajectories (a longer span registered directly between its frames, key frames
    anchoring the chained positions, as the plan says)."""

    name = "features"
    keyframe_interval: int | None = None  # the key frames' interval the trajectories were anchored at (measure)

    def measure(self, reader: FrameReader, *, n: int, params, plan: AnalysisPlan, out: Outputs) -> MeasurementRun:
        calibration, writer = out.calibration, out.writer
        n_features = 0
        store = out.stack.enter_context(TrajectoryStore(n_frames=n, params=params.tracking,
                                                        scratch_dir=writer.scratch_dir))

        def on_frames(first: int, tables: list, chunk_flags: list) -> None:
            nonlocal n_features
            sizes = [t.shape[0] for t in tables]
            feats = validate_features(np.concatenate(tables)) if tables else np.zeros(0, FEATURE_DTYPE)
            feats["frame"] = np.repeat(np.arange(first, first + len(tables), dtype=np.int32), sizes)
            feats["id"] = np.arange(n_features, n_features + feats.shape[0])
            n_features += feats.shape[0]
            writer.append("features", feats)
            out.flags[first : first + len(chunk_flags)] = chunk_flags

        m = measure_features(reader, n_frames=n, calibration=calibration, params=params, executor=out.executor,
                             on_frames=on_frames, on_tracked=store.add, progress=out.progress)
        t0 = time.perf_counter()
        span_registration = anchoring = None
        refiner = SubpixelRefiner(calibration=calibration, params=params.subpixel)
        frames = SpanFrames(reader, refiner.prepare, keep=SPAN_REGISTRATION_BATCH)
        if plan.keyframe_smoothing_key_frames is not None:
            anchoring = KeyframeAnchoring(
                refiner, reader, interval=params.tracking.keyframe_interval_frames,
                reference_span=params.tracking.keyframe_reference_frames,
                smoothing=plan.keyframe_smoothing_key_frames)
            store.anchor(anchoring)
            self.keyframe_interval = anchoring.interval
        if plan.span_registration:
            span_registration = SpanRegistration(refiner, reader, frames=frames)
        _trajectories_and_motion(store, out, n=n, span_registration=span_registration,
                                 threads=1 if params.execution.kind == "serial" else params.execution.workers,
                                 uncertainty=SampleUncertainty(refiner, frames))
        store.close()  # its scratch file
        timing = dict(m.timing)
        timing["tracking_s"] += time.perf_counter() - t0
        # the stages' own shares of it (the bench's stages table)
        timing["keyframes_s"] = anchoring.seconds if anchoring is not None else 0.0
        timing["span_registration_s"] = span_registration.seconds if span_registration is not None else 0.0
        return MeasurementRun(timing, m.parallel)

    def cumulative_samples(self, *, n: int, params, out: Outputs) -> Iterator[MotionSample]:
        return feature_cumulative_samples(out.writer.file, n_frames=n, keyframe_interval=self.keyframe_interval)


class FlowMethod:
    """The dense flow between consecutive frames; a longer span is the composed consecutive fields, refined by
    registering its own two frames where the plan says (composing alone adds up every step's smoothing bias), and
    the motion from the reference frame is registered directly as the fields arrive."""

    name = "flow"

    def measure(self, reader: FrameReader, *, n: int, params, plan: AnalysisPlan, out: Outputs) -> MeasurementRun:
        calibration, writer, flags = out.calibration, out.writer, out.flags
        recent: deque = deque(maxlen=max(out.spans))
        stride = params.strain.flow_stride
        refiner = None
        reference: list = [None]  # the field from the reference frame to the newest frame (with a refiner)
        stack = ExitStack()
        if plan.span_refiner:
            from skinstretch.processing.flow import DenseFlow, ReferenceRefiner, SpanRefiner  # noqa: PLC0415

            flow = DenseFlow(calibration=calibration, params=params.flow)
            frames = flow.span_frames(reader, keep=max(out.spans))  # each frame prepared once for both refiners
            refiner = SpanRefiner(flow, reader, frames=frames)
            reference_refiner = ReferenceRefiner(flow, reader, frames=frames)
            # The spans are refined on a thread of their own while this one registers from the reference frame:
            # the two are independent, their kernels release the GIL, and this process would otherwise run them
            # one after the other while the pairs' workers wait.
            spans_thread = stack.enter_context(ThreadPoolExecutor(1, thread_name_prefix="span-refiner"))

        def on_field(f) -> None:
            if not recent:  # the first field
                writer.start_flow(f.grid_x, f.grid_y)
            writer.append_flow(f.displacement, f.valid)
            if f.status != "ok" and not any(f.frame_flags):
                flags[f.frame_a] = f.status
            for k, refused in zip((f.frame_a, f.frame_b), f.frame_flags):  # the texture gate names each frame's
                flags[k] = refused or flags[k]                              # reason
            recent.append(f)
            out.motion.add(out.rectified(f.motion()))
            refined = {}
            if refiner is not None:
                due = {span: list(recent)[len(recent) - span:]
                       for span in out.spans if span > 1 and len(recent) >= span}
                for steps in due.values():  # frames are read and prepared here, on the one thread that reads
                    frames.pair(int(steps[0].frame_a), int(f.frame_b))
                refined = {span: spans_thread.submit(refiner.refine, steps) for span, steps in due.items()}
                # Cumulative (DIC's reference frame): the reference field composed with this one, registered
                # from the reference frame to frame b directly; chaining alone adds up each step's bias.
                measured = None
                if reference[0] is not None:
                    reference[0], measured = reference_refiner.advance(reference[0], f)
                elif int(f.valid[::stride, ::stride].sum()) >= 3:
                    reference[0] = measured = f
                if measured is not None and measured.valid.any():  # else a frame refused: no row
                    out.cumulative.add(out.rectified(measured.motion(stride=stride)))
            for span in out.spans:
                if len(recent) >= span:
                    chained = (refined[span].result().motion(stride=stride) if span in refined
                               else chain_flows(list(recent)[len(recent) - span:], stride=stride))
                    out.strain.add(span, out.rectified(chained))

        from skinstretch.processing.flow import DenseFlow  # noqa: PLC0415

        coupling = DenseFlow(calibration=calibration, params=params.flow)  # the nodes' errors are correlated
        for span in out.spans:
            out.strain.regularisation[span] = coupling.regularisation(span=refiner is not None and span > 1)
        with stack:
            m = measure_flow(reader, n_frames=n, calibration=calibration, flow_params=params.flow,
                             executor=out.executor, on_field=on_field, progress=out.progress)
        out.motion.flush()
        timing = dict(m.timing)
        timing["span_refiner_s"] = refiner.seconds if refiner is not None else 0.0  # its share of flow_s
        return MeasurementRun(timing, m.parallel)

    def cumulative_samples(self, *, n: int, params, out: Outputs) -> Iterator[MotionSample]:
        if out.cumulative.written or out.cumulative.batch:  # registered from the reference frame while measuring
            return iter(())
        return flow_cumulative_samples(out.writer.file, stride=params.strain.flow_stride, mapping=out.mapping,
                                       px_per_mm=out.calibration.px_per_mm)


_METHODS: dict[str, type] = {"features": FeatureMethod, "flow": FlowMethod}


def measurement_method(name: str) -> MeasurementMethod:
    """The method called ``name`` (one of :data:`~skinstretch.experiments.analysis.parameters.METHODS`)."""
    return _METHODS[name]()


def _rectify_rows(rows: np.ndarray, mapping, px_per_mm: float) -> None:
    """Image px -> skin px for every position of trajectory rows (seed 3.4)."""
    for a, b in (("x", "y"), ("raw_x", "raw_y")):
        xy = np.column_stack([rows[a], rows[b]])
        moved = np.asarray(mapping.image_to_surface(xy), dtype=np.float64) * px_per_mm
        rows[a], rows[b] = moved[:, 0], moved[:, 1]


def _trajectories_and_motion(store: TrajectoryStore, out: Outputs, *, n: int,
                             span_registration: SpanRegistration | None = None, threads: int = 1,
                             uncertainty: SampleUncertainty | None = None) -> None:
    """The stored trajectories written a block of frames at a time, and the motion of every span that follows from
    them: pair (k, k + 1) and (k, k + span) as soon as the block holding frame k + the longest span is built. With
    ``span_registration``, a longer span's chained motion is refined by registering its two frames (in image
    pixels, before the mapping to the skin), a batch of pairs at a time on ``threads`` threads; ``uncertainty``
    gives every point of every span its predicted standard error."""
    measured = uncertainty if uncertainty is not None else (lambda sample: sample)
    writer, spans, mapping = out.writer, out.spans, out.mapping
    longest = max(spans)
    kinds = store.kinds
    carry = np.zeros(0, TRAJECTORY_DTYPE)  # rows of the frames later pairs still need (image pixels)
    first = 0  # the next pair (first, first + 1)
    for block in store.blocks():
        rows = block.rows
        if mapping is not None:
            written = rows.copy()
            _rectify_rows(written, mapping, out.calibration.px_per_mm)
            writer.append("trajectories", written)
        else:
            writer.append("trajectories", rows)
        tr = Trajectories(n_frames=block.stop, rows=np.concatenate([carry, rows]), kind=kinds)
        last = n - 2 if block.stop == n else block.stop - 1 - longest  # the last pair whose frames are all built
        for k0 in range(first, last + 1, SPAN_REGISTRATION_BATCH):
            longer: list[tuple[int, MotionSample]] = []  # (span, chained motion) of this batch, registered together
            for k in range(k0, min(last + 1, k0 + SPAN_REGISTRATION_BATCH)):
                s = out.rectified(measured(tr.motion(k, k + 1)))
                out.motion.add(s)
                for span in spans:
                    if span == 1:
                        out.strain.add(1, s)
                    elif k + span < n:
                        longer.append((span, tr.motion(k, k + span)))
            if span_registration is not None and longer:
                refined = span_registration.refine_all([c for _, c in longer], threads=threads)
                longer = [(span, r) for (span, _), r in zip(longer, refined)]
            for span, chained in longer:
                out.strain.add(span, out.rectified(measured(chained)))
        first = max(first, last + 1)
        carry = tr.rows[tr.rows["frame"] >= first]
    out.motion.flush()
    table = store.track_table()
    tracks = np.zeros(table["kind"].size, dtype=TRACK_DTYPE)
    tracks["track"] = np.arange(tracks.size)
    for name, column in table.items():
        tracks[name] = column
    writer.append("tracks", tracks)
