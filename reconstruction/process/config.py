"""The settings of ``skycap process`` (:class:`ProcessConfig`, TOML-loadable and ``--set`` overridable; saved beside
the outputs as ``process.toml``)."""

from __future__ import annotations

import dataclasses

from reconstruction.keypoints import KEYPOINT_MODELS
from reconstruction.monocular.reconstruct import MonocularRunConfig
from reconstruction.multiview.run import MultiviewConfig
from reconstruction.process.events import ProcessError

__all__ = ["BoxesConfig", "ExportConfig", "KEYPOINT_SOURCES", "KeypointsConfig", "ProcessConfig", "WindowsConfig"]

#: ``models``: the shipped keypoint models on the recorded images (default); ``sim``: the simulator's noisy true
#: keypoints recorded in the flight (``sim/keypoints2d``), for evaluation.
KEYPOINT_SOURCES = ("models", "sim")


@dataclasses.dataclass
class BoxesConfig:
    """The person's box per frame: the drone's recorded detections (``detections``, else the simulator's
    ``sim/detections``), the offline smoother's track to choose among several boxes and to fill frames without
    one (``use_smoother``), the ONNX person detector re-run on the frames still without a box (``detector_fill``)."""

    min_score: float = 0.3  #: recorded boxes below this score are left out
    use_smoother: bool = True
    detector_fill: bool = True
    detector_threads: int = 1  #: onnxruntime intra-op threads of the person detector
    #: drones whose box choice and detector re-runs run at once after the smoother (threads, each with its own
    #: detector at ``detector_threads``); not part of the cache key (the same boxes)
    workers: int = 2
    #: re-run the detector in gaps between boxed frames up to this long (s); longer gaps are left without a box
    detector_max_gap_s: float = 2.0


@dataclasses.dataclass
class KeypointsConfig:
    """The 2D keypoint step: ``source`` (:data:`KEYPOINT_SOURCES`), the models (>= 2 by default, fused per joint
    with their confidences), onnxruntime ``threads`` per model, crops per model call (``batch_size``, also how often
    ``cancel`` is checked) and frames per cached chunk (``chunk_frames``: what a resumed run does not redo)."""

    source: str = "models"
    #: MoveNet Lightning + BlazePose Lite: the pair that processes a 3-drone 10 Hz flight at >= 1x real time on a
    #: 2-core CPU (0.96 s per flight second; with ``blazepose_full`` 1.11). Over six demo flights (ellipsoid and Anny
    #: persons) Lite's steady-orbit MPJPE was -5.6 to +6.3 mm from Full's (mean +1.0; PA +0.8, W +2.1), its
    #: whole-flight MPJPE +0.5 to +9.3 mm (mean +4.9: take-off and approach, where the person is small):
    #: ``--models movenet_lightning,blazepose_full`` where accuracy matters more than time (reconstruction/process/
    #: README.md, "Where it stands"). Lightning + Full was as accurate as Thunder + Full at 0.6x its keypoint time.
    models: list[str] = dataclasses.field(default_factory=lambda: ["movenet_lightning", "blazepose_lite"])
    #: onnxruntime intra-op threads per model (and per worker, see ``workers``)
    threads: int = 1
    crop_scale: float = 1.25
    batch_size: int = 16
    chunk_frames: int = 64
    #: BlazePose in MediaPipe's video mode: a frame's landmark region from the previous frame's landmarks, the pose
    #: detector only on the first frame of a run and where the track is lost (False: the detector on every frame)
    track_rois: bool = True
    #: drones whose keypoints are computed at once (threads, each with its own models at ``threads`` onnxruntime
    #: threads): 2 x 1 thread keeps both cores of a 2-core machine busy better than 1 x 2 threads
    workers: int = 2
    #: fuse the models into one detector per camera (False: each model is a detector of its own in the fit)
    fuse: bool = True
    #: two models agree on a joint when their points lie within this fraction of the box's longer side
    agree_fraction: float = 0.15
    #: a model's joint below this confidence does not vote
    min_confidence: float = 0.05


@dataclasses.dataclass
class WindowsConfig:
    """A long flight is fitted in overlapping windows of ``window_s`` (the last ``overlap_s`` of one window are
    the first of the next), cross-faded over the overlap into one motion: memory and time per window stay bounded."""

    window_s: float = 60.0
    overlap_s: float = 6.0
    #: frames and poses this much beyond a window are given to its fit (the interpolation at its ends)
    margin_s: float = 1.0


@dataclasses.dataclass
class ExportConfig:
    """Outputs: ``motion.{bvh,npz,csv,trc}`` (+ ``motion.rrd`` with ``rrd``), and the named ``extra`` exporters
    registered with :func:`reconstruction.process.export.register_exporter` (default: ``foxglove``, the processed
    flight as ``flight.foxglove.mcap``); the rerun recording and the extra exporters run in ``workers`` threads or
    processes (``pool``) beside the motion files (:func:`reconstruction.process.export.export_all`)."""

    rrd: bool = True
    extra: list[str] = dataclasses.field(default_factory=lambda: ["foxglove"])
    #: workers that write the rerun recording and the extra exporters' files while the motion files are written
    #: (the outputs do not depend on it); 0 = everything in the calling thread, one after the other
    workers: int = 2
    #: "threads" (default: no start-up cost; the Rust writers of rerun and Foxglove, file I/O and decompression run
    #: beside Python) or "processes" (spawned: every exporter's Python in parallel, but each worker first imports
    #: numpy / scipy / rerun / foxglove, seconds on a loaded machine)
    pool: str = "threads"
    #: with ``pool="threads"``: exporters that need the motion only at their end (the Foxglove MCAP) start before the
    #: fit and write everything else while it runs (the same files; not in the export step's cache key)
    early: bool = True
    #: where they run: "processes" (each spawned: its Python does not compete with the fit's for the GIL) or "threads"
    early_pool: str = "processes"


@dataclasses.dataclass
class ProcessConfig:
    """``skycap process`` settings. ``method``: "multiview" / "monocular" / "" (multiview with >= 2 readable
    drones, else monocular); ``sortie``: 0 = the whole flight, N = only sortie N; ``out_dir``: "" = the method's
    folder of the flight; ``cache``: read and write the ``processing/`` step cache."""

    method: str = ""
    sortie: int = 0
    out_dir: str = ""
    cache: bool = True
    boxes: BoxesConfig = dataclasses.field(default_factory=BoxesConfig)
    keypoints: KeypointsConfig = dataclasses.field(default_factory=KeypointsConfig)
    windows: WindowsConfig = dataclasses.field(default_factory=WindowsConfig)
    multiview: MultiviewConfig = dataclasses.field(default_factory=MultiviewConfig)
    monocular: MonocularRunConfig = dataclasses.field(default_factory=MonocularRunConfig)
    export: ExportConfig = dataclasses.field(default_factory=ExportConfig)

    def validate(self) -> "ProcessConfig":
        k, w = self.keypoints, self.windows
        if self.method not in ("", "multiview", "monocular"):
            raise ProcessError(f"method={self.method!r}: use 'multiview', 'monocular' or '' (chosen by the drones)")
        if k.source not in KEYPOINT_SOURCES:
            raise ProcessError(f"keypoints.source={k.source!r}: use one of {', '.join(KEYPOINT_SOURCES)}")
        bad = [m for m in k.models if m not in KEYPOINT_MODELS]
        if k.source == "models" and (not k.models or bad):
            raise ProcessError(f"keypoints.models={k.models}: name at least one of {', '.join(KEYPOINT_MODELS)}")
        if self.export.early_pool not in ("threads", "processes"):
            raise ProcessError(f"export.early_pool={self.export.early_pool!r}: use 'processes' or 'threads'")
        if self.boxes.workers < 1 or self.boxes.detector_threads < 1:
            raise ProcessError(f"boxes.workers={self.boxes.workers} and boxes.detector_threads="
                               f"{self.boxes.detector_threads} must be >= 1")
        if k.threads < 1 or k.workers < 1 or k.batch_size < 1 or k.chunk_frames < 1:
            raise ProcessError("keypoints.threads, workers, batch_size and chunk_frames must be >= 1")
        if not (w.window_s > 0 and 0 <= w.overlap_s < w.window_s and w.margin_s >= 0):
            raise ProcessError(f"windows: window_s={w.window_s} must be > 0 and 0 <= overlap_s={w.overlap_s} < "
                               "window_s, margin_s >= 0")
        if self.sortie < 0:
            raise ProcessError(f"sortie={self.sortie}: 0 for the whole flight or a sortie number >= 1")
        return self

    @property
    def sortie_or_none(self) -> int | None:
        return self.sortie or None
