"""``process(flight, cfg)``: a recorded flight -> its 3D body motion, one function per step over a typed config,
each step cached in the flight folder and resumable.

    from reconstruction.process import ProcessConfig, process

    res = process("flights/demo", ProcessConfig(), progress=lambda ev: print(ev), cancel=threading.Event())
    res.joints_ned, res.t_ns, res.keypoints_source, res.seconds, res.outputs

Steps (:data:`reconstruction.process.events.STEPS`):

* ``boxes`` (:mod:`.boxes`): per drone, the person's box in each recorded frame;
* ``keypoints`` (:mod:`.keypoints`): the keypoint models on the boxed frames, streamed from the MCAP recordings and
  cached in chunks; fused per joint into one detector per camera;
* ``fit``: the multi-view fit (:func:`reconstruction.multiview.fit.fit_capture`) or, with one drone, the monocular
  method (:func:`reconstruction.monocular.reconstruct.run`), in overlapping windows (:mod:`.windows`) stitched
  into one motion, each window cached;
* ``export`` (:mod:`.export`): ``motion.{bvh,npz,csv,rrd}``, ``capture.npz``, ``config.toml`` (this config) and
  ``summary.json`` in the method's folder of the flight, then the registered extra exporters.

Cache: ``<flight>/processing/<step>/`` (:meth:`flightdata.folder.FlightFolder.processing_step_dir`), entries named
by a hash of their inputs (recordings, earlier steps, settings) and written atomically; a crash or a cancel
(``cancel`` event, checked between batches, raises :class:`Cancelled`) resumes without redoing finished work. The
recordings are only read. A drone whose recording cannot be read is skipped with a warning while enough remain
(2 for multiview, 1 for monocular). ``keypoints.source = "sim"`` fits the simulator's recorded noisy true keypoints
instead (evaluation); a flight without any camera images falls back to its recorded keypoints, with a warning.
"""

from __future__ import annotations

import dataclasses
import logging
import struct
import tempfile
import threading
import time
from pathlib import Path

import numpy as np

from flightdata.folder import FlightFolder
from reconstruction.capture import CameraCapture, Capture, CaptureError
from reconstruction.flight import READER_VERSION, read_drone_log
from reconstruction.monocular.reconstruct import run as run_monocular
from reconstruction.multiview.fit import fit_capture
from reconstruction.multiview.flight import output_grid
from reconstruction.process.boxes import SOURCE_NAMES, compute_boxes, smoother_boxes
from reconstruction.process.cache import atomic_write_json, atomic_write_npz, file_identity, make_key, read_npz, remove_tree
from reconstruction.process.config import ProcessConfig
from reconstruction.process.events import Cancelled, ProcessError, ProgressSink, StepProgress
from reconstruction.process.export import EarlyExports, ExportContext, export_all
from reconstruction.process.frames import frame_table, has_images
from reconstruction.process.keypoints import compute_keypoints, fuse_keypoints, load_models
from reconstruction.process.windows import plan_windows, stitch
from reconstruction.result import ReconstructionResult
from skycap.errors import SkycapError

log = logging.getLogger(__name__)

__all__ = ["ProcessResult", "process", "sim_camera"]

CACHE_VERSION = 1


@dataclasses.dataclass
class ProcessResult(ReconstructionResult):
    """:class:`reconstruction.result.ReconstructionResult` plus ``keypoints_source`` (the model names joined by
    ``+``, ``"sim"`` or ``"recorded:<detectors>"``), ``seconds`` (wall time of this run), per step ``steps``
    (``seconds``, ``cached``), the drones used and those ``skipped`` (drone -> why), and ``stats`` (counters, e.g.
    ``frames_computed``: frames the keypoint models ran on in this run)."""

    keypoints_source: str = ""
    seconds: float = 0.0
    steps: dict = dataclasses.field(default_factory=dict)
    drones: list = dataclasses.field(default_factory=list)
    skipped: dict = dataclasses.field(default_factory=dict)
    stats: dict = dataclasses.field(default_factory=dict)


#: what makes a drone's recording "unreadable" (skipped with a warning) rather than a bug
_UNREADABLE = (SkycapError, OSError, ValueError, EOFError, KeyError, IndexError, struct.error)


def _unreadable(e: BaseException) -> bool:
    if isinstance(e, (Cancelled, ProcessError)):
        return False
    if isinstance(e, _UNREADABLE):
        return True
    try:
        from mcap.exceptions import McapError
    except ImportError:  # pragma: no cover
        return False
    return isinstance(e, McapError)


def _enough(drones: list[str], skipped: dict[str, str], method: str, flight: FlightFolder) -> None:
    need = 2 if method == "multiview" else 1
    if len(drones) < need:
        why = "; ".join(f"{d}: {r}" for d, r in skipped.items()) or "none recorded"
        raise ProcessError(f"{flight.path}: {len(drones)} usable drone(s), the {method or 'reconstruction'} needs "
                           f"{need} (skipped: {why}); fix or remove the broken recordings, or use --method monocular")


def _skip(d: str, e: BaseException, drones: list[str], skipped: dict[str, str], step: str) -> None:
    reason = f"{type(e).__name__}: {e}"
    log.warning("skipping %s (%s step): its recording cannot be used: %s", d, step, reason)
    skipped[d] = reason
    if d in drones:
        drones.remove(d)


def process(flight_dir, cfg: ProcessConfig | list[str] | None = None, *, progress: ProgressSink | None = None,
            cancel: threading.Event | None = None) -> ProcessResult:
    """Process a recorded flight (see the module doc). ``flight_dir``: a :class:`FlightFolder` or its path. ``cfg``: a
    :class:`ProcessConfig`, or a list of its ``--set`` overrides (``["keypoints.source=\"sim\""]``: what a caller
    that does not import the pipeline -- the ground station submitting a job -- sends)."""
    t_begin = time.perf_counter()
    flight = flight_dir if isinstance(flight_dir, FlightFolder) else FlightFolder(flight_dir)
    if isinstance(cfg, (list, tuple)):
        from skycap.config import load_config

        cfg = load_config(ProcessConfig, None, [str(o) for o in cfg])
    cfg = (cfg or ProcessConfig()).validate()
    sortie = cfg.sortie_or_none
    logs = flight.drone_logs(sortie=sortie)
    drones = list(logs)
    skipped: dict[str, str] = {}
    steps: dict[str, dict] = {}
    stats: dict = {}
    source = cfg.keypoints.source
    tmp = tempfile.TemporaryDirectory(prefix="skycap-process-") if not cfg.cache else None
    cache_root = Path(tmp.name) if tmp is not None else None

    def step_dir(step: str) -> Path:
        p = (cache_root / step) if cache_root is not None else flight.processing_step_dir(step)
        p.mkdir(parents=True, exist_ok=True)
        return p

    early: EarlyExports | None = None  # exporters started before the fit (the export step)
    try:
        if source == "models":
            with_images = {}
            for d in list(drones):
                try:
                    with_images[d] = has_images(logs[d])
                except Exception as e:
                    if not _unreadable(e):
                        raise
                    _skip(d, e, drones, skipped, "boxes")
            if with_images and not any(with_images.values()):
                log.warning("%s holds no camera images (topic camera/image): fitting the keypoints recorded in the "
                            "flight instead of running the keypoint models", flight.path)
                source = "recorded"
            else:
                for d, has in with_images.items():
                    if not has:
                        _skip(d, ProcessError("no camera images (camera/image) recorded"), drones, skipped, "boxes")
        _enough(drones, skipped, cfg.method, flight)
        ident = {}
        for d in list(drones):
            try:
                ident[d] = [file_identity(s.path) for s in logs[d]]
            except OSError as e:
                _skip(d, e, drones, skipped, "boxes")

        boxes: dict[str, dict] = {}
        kp_keys: dict[str, str] = {}
        kps: dict[str, np.ndarray] = {}
        if source == "models":
            boxes = _boxes_step(flight, logs, drones, skipped, ident, cfg, step_dir, progress, cancel, steps)
            _enough(drones, skipped, cfg.method, flight)
            kps, kp_keys = _keypoints_step(logs, drones, skipped, boxes, cfg, step_dir, progress, cancel, steps, stats)
            _enough(drones, skipped, cfg.method, flight)
            keypoints_source = "+".join(cfg.keypoints.models)
        else:
            for s in ("boxes", "keypoints"):
                steps[s] = {"seconds": 0.0, "cached": False, "skipped": f"keypoints source {source!r}"}
            keypoints_source = "sim" if source == "sim" else "recorded"

        # ------------------------------------------------------------------------------------------ fit
        t0 = time.perf_counter()
        sp = StepProgress("fit", progress, cancel)
        sp.check_cancel()
        cams = []
        for d in list(drones):
            try:
                cams.append(_camera(logs[d], d, source, boxes.get(d), kps.get(d), cfg))
            except Exception as e:
                if not _unreadable(e):
                    raise
                _skip(d, e, drones, skipped, "fit")
        method = cfg.method or ("multiview" if len(cams) >= 2 else "monocular")
        _enough(drones, skipped, method, flight)
        if source == "recorded":
            keypoints_source = "recorded:" + "+".join(sorted({n for c in cams for n in c.detectors}))
        capture = Capture(cams, meta={"source": "flight", "flight_dir": str(flight.path), "sortie": sortie,
                                      "recordings": flight.recording_names({d: logs[d] for d in drones}),
                                      "keypoints_source": keypoints_source})
        grid = _grid(capture, method, cfg)
        wcfg = cfg.windows
        windows = plan_windows(int(grid[0]), int(grid[-1]), wcfg.window_s, wcfg.overlap_s)
        inputs = kp_keys if source == "models" else {d: ident[d] for d in drones}
        fit_key = make_key("fit", CACHE_VERSION, READER_VERSION, method, inputs, source, cfg.keypoints.fuse, cfg.keypoints.agree_fraction,
                           cfg.keypoints.min_confidence, cfg.multiview if method == "multiview" else cfg.monocular,
                           wcfg, sortie)
        # the export's key is known now: exporters that need the motion only at their end start before the fit
        out = Path(cfg.out_dir) if cfg.out_dir else flight.reconstruction_dir(method)
        how = {"workers": 0, "pool": ""}  # how the exporters run does not change the files (nor does ``early``)
        exp_cfg = {k: how.get(k, v) for k, v in dataclasses.asdict(cfg.export).items() if k not in ("early", "early_pool")}
        exp_key = make_key("export", CACHE_VERSION, fit_key, exp_cfg, str(out.resolve()))
        marker = step_dir("export") / f"{exp_key}.json"
        prev = _read_marker(marker)
        if prev is None and cfg.export.early and cfg.export.workers > 0 and cfg.export.pool == "threads":
            early = EarlyExports(ExportContext(flight=flight, out_dir=out, t_ns=None, joints_ned=None, capture=capture,
                                               method=method, config=cfg, keypoints_source=keypoints_source,
                                               boxes=boxes), cfg.export.extra, cfg.export.workers,
                                 cfg.export.early_pool)
        results, cached_w, shapes, params = [], 0, [], None
        for k, (a, b) in enumerate(windows):
            path = step_dir("fit") / f"{fit_key}-w{k:03d}.npz"
            z = read_npz(path)
            if z is None:
                sel = (grid >= a) & (grid <= b)

                def cb(stage, done, total, k=k):
                    sp((k + (done / total if total else 1.0)) / len(windows), 1.0,
                       f"window {k + 1}/{len(windows)} ({method}): {stage} {done}/{total}")

                cb("start", 0, 1)
                z = _fit_window(capture, grid[sel], a, b, method, cfg, cb)
                atomic_write_npz(path, **z)
            else:
                cached_w += 1
            sp((k + 1) / len(windows), 1.0, f"window {k + 1}/{len(windows)}" + (" (cached)" if z is not None else ""))
            if int(z["ok"]):
                results.append((z["t_ns"], z["joints_ned"]))
                shapes.append(z["shape"])
                if len(windows) == 1 and "root_orient" in z:
                    params = {k2: z[k2] for k2 in ("root_orient", "pose", "transl", "shape")}
            else:
                log.warning("window %d/%d (%.1f-%.1f s) could not be fitted: %s", k + 1, len(windows),
                            (a - grid[0]) * 1e-9, (b - grid[0]) * 1e-9, str(z["error"]))
                results.append(None)
        if not any(r is not None for r in results):
            raise ProcessError(f"{flight.path}: no window could be fitted ({method}); see the warnings above")
        t_ns, joints = stitch(grid, windows, results, wcfg.overlap_s)
        shape = np.median(np.stack(shapes), axis=0) if shapes and shapes[0].size else None
        steps["fit"] = {"seconds": round(time.perf_counter() - t0, 3), "cached": cached_w == len(windows),
                        "windows": len(windows), "windows_cached": cached_w,
                        "windows_failed": sum(r is None for r in results)}

        # --------------------------------------------------------------------------------------- export
        t0 = time.perf_counter()
        sp = StepProgress("export", progress, cancel)
        sp(0, 1, "writing the outputs")
        ctx = ExportContext(flight=flight, out_dir=out, t_ns=t_ns, joints_ned=joints, capture=capture, method=method,
                            config=cfg, keypoints_source=keypoints_source, boxes=boxes, params=params, shape=shape)
        exporter_s: dict[str, float] = {}
        if prev is not None:
            paths = prev
        else:
            out.mkdir(parents=True, exist_ok=True)
            paths, exporter_s = export_all(ctx, cfg.export.rrd, cfg.export.extra, cfg.export.workers, sp.check_cancel,
                                           cfg.export.pool, early=early)
            capture.save(out / "capture.npz")
            from skycap.config import save_config

            save_config(cfg, out / "config.toml")
            atomic_write_json(marker, {k: str(v) for k, v in paths.items()})
        steps["export"] = {"seconds": round(time.perf_counter() - t0, 3), "cached": prev is not None,
                           "exporters": exporter_s}
        if early is not None and early.names:  # started before the fit: their seconds, and how many overlapped it
            steps["export"]["early"] = early.timing
        seconds = time.perf_counter() - t_begin
        span_s = float((t_ns[-1] - t_ns[0]) * 1e-9) if len(t_ns) > 1 else 0.0
        flight_s = _flight_seconds(capture)
        summary = {
            "method": method, "keypoints_source": keypoints_source, "seconds": round(seconds, 2),
            "frames": int(len(t_ns)), "cameras": capture.num_cameras, "drones": list(drones), "skipped": skipped,
            "windows": [[round((a - grid[0]) * 1e-9, 3), round((b - grid[0]) * 1e-9, 3)] for a, b in windows],
            "motion_span_s": round(span_s, 3), "flight_images_span_s": round(flight_s, 3),
            "steps": steps, "seconds_2d": round(sum(steps[s]["seconds"] for s in ("boxes", "keypoints")), 3),
            "seconds_per_flight_second": round(seconds / flight_s, 3) if flight_s > 0 else None,
            "fit_seconds": steps["fit"]["seconds"], "cache": str(flight.processing_dir) if cfg.cache else None,
            "box_sources": {d: {SOURCE_NAMES[k]: int(np.sum(b["source"] == k)) for k in range(len(SOURCE_NAMES))}
                            for d, b in boxes.items()},
            "stats": stats, "sortie": sortie, "recordings": capture.meta["recordings"],
            "outputs": {k: str(v) for k, v in paths.items()},
        }
        if out.is_dir():
            atomic_write_json(out / "summary.json", summary)
        sp(1, 1, f"wrote {out}")
        log.info("processed %s (%s, keypoints: %s) in %.1f s: %s", flight.path, method, keypoints_source, seconds,
                 ", ".join(f"{s} {v['seconds']:.1f} s{' (cached)' if v.get('cached') else ''}" for s, v in steps.items()))
        return ProcessResult(method=method, t_ns=t_ns, joints_ned=joints, summary=summary, out_dir=out,
                             outputs=dict(paths), keypoints_source=keypoints_source, seconds=seconds, steps=steps,
                             drones=list(drones), skipped=skipped, stats=stats)
    except BaseException as e:
        if early is not None:  # the fit failed or was cancelled: they stop, leave no file, and their threads end
            early.abort(e)
        raise
    finally:
        if tmp is not None:
            tmp.cleanup()


# ------------------------------------------------------------------------------------------------ steps
def _thread_map(fn, items, workers: int, name: str) -> list:
    """[fn(item) for item in items] in up to ``workers`` threads (here with 1): every call ends (a cancel stops them
    all) before the first error is raised."""
    from concurrent.futures import ThreadPoolExecutor

    items = list(items)
    workers = max(1, min(workers, len(items)))
    if workers == 1:
        return [fn(i) for i in items]
    with ThreadPoolExecutor(workers, thread_name_prefix=name) as pool:
        futures = [pool.submit(fn, i) for i in items]
        out, first_error = [], None
        for f in futures:
            try:
                out.append(f.result())
            except BaseException as e:
                first_error = first_error or e
        if first_error is not None:
            raise first_error
        return out


def _boxes_step(flight, logs, drones, skipped, ident, cfg, step_dir, progress, cancel, steps) -> dict[str, dict]:
    """Each drone's boxes (cached per drone): the offline smoother once over all drones, then each drone's box choice
    and detector re-runs in ``cfg.boxes.workers`` threads (each with its own detector; onnxruntime and the image
    decoding release the GIL)."""
    t0 = time.perf_counter()
    sp = StepProgress("boxes", progress, cancel)
    sp.check_cancel()
    everyone = {d: ident[d] for d in drones} if cfg.boxes.use_smoother else {}
    # the cache key leaves out how many threads compute the boxes (the same boxes)
    box_cfg = {k: v for k, v in dataclasses.asdict(cfg.boxes).items() if k != "workers"}
    local = threading.local()
    lock = threading.Lock()

    def detector():
        if getattr(local, "detector", None) is None:
            from onboard.detector.detector import DetectorConfig, PersonDetector

            local.detector = PersonDetector(DetectorConfig(threads=cfg.boxes.detector_threads))
        return local.detector

    n = len(drones)
    out: dict[str, dict] = {}
    paths, todo, cached = {}, [], 0
    for d in drones:
        key = make_key("boxes", CACHE_VERSION, ident[d], everyone, box_cfg, cfg.sortie)
        paths[d] = (step_dir("boxes") / f"{d}-{key}.npz", key)
        z = read_npz(paths[d][0])
        if z is None:
            todo.append(d)
        else:
            out[d] = z
            cached += 1
    frac = {d: 1.0 for d in out}
    if todo:
        sp(0, 1, "offline smoother over every drone's detections" if cfg.boxes.use_smoother else "boxes")
        track = smoother_boxes(flight, cfg.sortie_or_none) if cfg.boxes.use_smoother else {}

        def tick(d, done, total, msg):
            with lock:
                frac[d] = done / total if total else 1.0
                f = sum(frac.values()) / n
            sp(f, 1.0, msg)

        def one(d):
            try:
                frames = frame_table(logs[d])
                if not len(frames):
                    raise ProcessError("no camera frames")
                z = compute_boxes(logs[d], d, frames, cfg.boxes, track.get(d), detector,
                                  lambda done, total, msg, d=d: tick(d, done, total, msg))
            except Exception as e:
                if not _unreadable(e) and not isinstance(e, ProcessError):
                    raise
                return e
            atomic_write_npz(paths[d][0], key=paths[d][1], **z)
            z["key"] = np.array(paths[d][1])
            tick(d, 1, 1, f"{d}: boxes")
            return z

        results = _thread_map(one, todo, cfg.boxes.workers, "boxes")
        for d, z in zip(todo, results):
            if isinstance(z, BaseException):
                _skip(d, z, drones, skipped, "boxes")
            else:
                out[d] = z
    out = {d: out[d] for d in drones if d in out}  # the drones' order
    sp(1, 1, "boxes" + (" (cached)" if not todo else ""))
    steps["boxes"] = {"seconds": round(time.perf_counter() - t0, 3), "cached": cached == n and n > 0,
                      "workers": min(cfg.boxes.workers, len(todo))}
    return out


def _keypoints_step(logs, drones, skipped, boxes, cfg, step_dir, progress, cancel, steps, stats):
    """The keypoint models on each drone's boxed frames, in ``cfg.keypoints.workers`` threads (the onnxruntime runs
    and the image decoding release the GIL; each thread opens its own models) over parts of the drones' chunks."""
    t0 = time.perf_counter()
    sp = StepProgress("keypoints", progress, cancel)
    sp.check_cancel()
    kc = cfg.keypoints
    local = threading.local()
    lock = threading.Lock()

    def models():
        if getattr(local, "models", None) is None:
            local.models = load_models(kc)
        return local.models

    n = len(drones)

    def key_of(d):
        return make_key("keypoints", CACHE_VERSION, str(boxes[d]["key"]), kc.models, kc.crop_scale, kc.chunk_frames,
                        kc.track_rois)

    def part(d, chunks, task):
        """Compute (and write) one part of a drone's chunks (all of them with ``chunks`` None) -> keypoints."""
        st: dict = {}
        try:
            return compute_keypoints(logs[d], d, boxes[d], kc, step_dir("keypoints") / f"{d}-{key_of(d)}.chunks",
                                     models, lambda done, total, msg: report(task, done, total, msg), st, chunks)
        finally:
            with lock:
                for k, v in st.items():
                    stats[k] = stats.get(k, 0) + v

    results: dict[str, tuple] = {}  # drone -> (keypoints or the unreadable recording's error, cached)
    todo = []
    for d in drones:
        z = read_npz(step_dir("keypoints") / f"{d}-{key_of(d)}.npz")
        if z is not None and z["kp"].shape[:2] == (len(boxes[d]["t_ns"]), len(kc.models)):
            results[d] = (z["kp"], True)
        else:
            todo.append(d)
    # the work: each drone's chunks in ``workers`` contiguous parts (3 drones on 2 workers keep both busy to the end;
    # a part starts its BlazePose track with one detector run), then each drone's chunks (all cached) consolidated
    workers = max(1, min(kc.workers, sum(-(-len(boxes[d]["t_ns"]) // kc.chunk_frames) for d in todo) or 1))
    tasks = []
    for d in todo:
        n_chunks = max(1, -(-len(boxes[d]["t_ns"]) // kc.chunk_frames))
        k = min(workers, n_chunks)
        bounds = np.linspace(0, n_chunks, k + 1).round().astype(int)
        tasks += [(d, list(range(a, b))) for a, b in zip(bounds[:-1], bounds[1:])] if k > 1 else [(d, None)]
    frac = {t: 0.0 for t in range(len(tasks))}
    frac.update({("cached", d): 1.0 for d in results})

    def report(task, done, total, msg):
        with lock:
            frac[task] = done / max(total, 1)
            f = sum(frac.values()) / max(len(frac), 1)
        sp(f, 1.0, msg)

    def run(t):
        d, chunks = tasks[t]
        try:
            part(d, chunks, t)
        except Exception as e:
            if not _unreadable(e):
                raise
            return d, e
        return d, None

    errors: dict[str, BaseException] = {}
    outs = _thread_map(run, range(len(tasks)), workers, "keypoints")
    for d, e in outs:
        if e is not None:
            errors.setdefault(d, e)
    for d in todo:
        if d in errors:
            results[d] = (errors[d], None)
            continue
        kp = part(d, None, ("cached", d))  # every chunk written: read back, nothing computed
        atomic_write_npz(step_dir("keypoints") / f"{d}-{key_of(d)}.npz", kp=kp)
        remove_tree(step_dir("keypoints") / f"{d}-{key_of(d)}.chunks")
        results[d] = (kp, False)
    out, keys, cached = {}, {}, 0
    for d in list(drones):
        kp, hit = results[d]
        if hit is None:
            _skip(d, kp, drones, skipped, "keypoints")
            continue
        cached += int(hit)
        out[d], keys[d] = kp, key_of(d)
    steps["keypoints"] = {"seconds": round(time.perf_counter() - t0, 3), "cached": cached == n and n > 0,
                          "models": list(kc.models), "threads": kc.threads, "workers": workers,
                          "track_rois": kc.track_rois}
    return out, keys


def _camera(sorties, d: str, source: str, boxes: dict | None, kp: np.ndarray | None, cfg: ProcessConfig) -> CameraCapture:
    """One drone's camera for the fit: its poses from the recording and the fused model keypoints (or, for the sim /
    recorded sources, the keypoints recorded in the flight)."""
    gimbal = cfg.multiview.gimbal_stabilised
    offsets = None
    if cfg.multiview.use_refined_poses:
        from reconstruction.track.flight import load_refined_offsets

        offsets = load_refined_offsets(sorties[0].path.parent).get(d)
    paths = [s.path for s in sorties]
    if source != "models":
        if source == "sim":
            return sim_camera(paths, d, gimbal, offsets)
        return read_drone_log(paths, gimbal, offsets, name=d)
    t = np.asarray(boxes["t_ns"], dtype=np.int64)
    if cfg.keypoints.fuse:
        uv, conf = fuse_keypoints(kp, boxes["box_xywh"], cfg.keypoints.agree_fraction, cfg.keypoints.min_confidence)
        uv, conf, dets = uv[:, None], conf[:, None], ["fused:" + "+".join(cfg.keypoints.models)]
    else:
        uv = np.nan_to_num(kp[..., :2])
        conf = np.where(np.isfinite(kp[..., 0]), np.nan_to_num(kp[..., 2]), 0.0)
        dets = list(cfg.keypoints.models)
    order = np.argsort(t, kind="stable")
    t, uv, conf = t[order], uv[order], conf[order]
    keep = np.concatenate([[True], np.diff(t) > 0])  # one frame per capture time
    return read_drone_log(paths, gimbal, offsets, name=d, keypoints=(t[keep], dets, uv[keep], conf[keep]))


def sim_camera(paths, d, gimbal=True, offsets=None) -> CameraCapture:
    """The simulator's noisy true keypoints (``sim/keypoints2d``) even where a drone also recorded ``keypoints2d``."""
    from flightdata.flightlog import SortieLogs
    from shared_msgs.messages import Keypoints2D

    msgs = SortieLogs(paths).read_topic("sim/keypoints2d", Keypoints2D)
    if not msgs:
        raise CaptureError(f"{d}: no 'sim/keypoints2d' in its recordings: --keypoints sim needs a simulated flight")
    frames = sorted({m.header.t_measurement_ns for m in msgs})
    fidx = {t: i for i, t in enumerate(frames)}
    uv = np.zeros((len(frames), 1, 17, 2))
    conf = np.zeros((len(frames), 1, 17))
    for m in msgs:
        if m.persons:
            best = max(m.persons, key=lambda p: float(np.mean(p.confidence)))
            uv[fidx[m.header.t_measurement_ns], 0] = np.asarray(best.keypoints_px, dtype=float).reshape(17, 2)
            conf[fidx[m.header.t_measurement_ns], 0] = np.asarray(best.confidence, dtype=float)
    return read_drone_log(paths, gimbal, offsets, name=d, keypoints=(np.array(frames), [msgs[0].detector], uv, conf))


def _grid(capture: Capture, method: str, cfg: ProcessConfig) -> np.ndarray:
    if method == "multiview":
        grid = output_grid(capture, cfg.multiview.rate_hz)
    else:
        names = [c.name for c in capture.cameras]
        cam = capture.cameras[names.index(cfg.monocular.camera)] if cfg.monocular.camera in names else capture.cameras[0]
        seen = np.flatnonzero((cam.confidence.max(axis=1) >= 0.3).sum(axis=-1) >= 8)
        if len(seen) < 10:
            raise CaptureError(f"camera {cam.name!r} sees the person in {len(seen)} frames; the monocular method needs 10")
        grid = cam.t_frame_ns[seen[0] : seen[-1] + 1]
    if len(grid) < 2:
        raise CaptureError("fewer than two output times in which the person is seen; nothing to fit")
    return np.asarray(grid, dtype=np.int64)


def _sub_capture(capture: Capture, a: int, b: int, pose_margin_ns: int) -> Capture:
    """The cameras' frames in [a, b] and their poses within ``pose_margin_ns`` beyond (bounded memory per window)."""
    cams = []
    for c in capture.cameras:
        f = (c.t_frame_ns >= a) & (c.t_frame_ns <= b)
        if f.sum() < 2:
            continue
        p = (c.t_pose_ns >= a - pose_margin_ns) & (c.t_pose_ns <= b + pose_margin_ns)
        if p.sum() < 2:
            p = np.ones(len(c.t_pose_ns), bool)
        rates = {}
        for r, s in (("vel_world_mps", "vel_sigma_mps"), ("omega_cam_radps", "omega_sigma_radps")):
            if getattr(c, r) is not None:
                rates[r], rates[s] = getattr(c, r)[p], getattr(c, s)[p]
        cams.append(dataclasses.replace(
            c, t_pose_ns=c.t_pose_ns[p], T_world_cam=c.T_world_cam[p], pos_sigma_m=c.pos_sigma_m[p],
            rot_sigma_deg=c.rot_sigma_deg[p], t_frame_ns=c.t_frame_ns[f], keypoints_px=c.keypoints_px[f],
            confidence=c.confidence[f], image_paths=tuple(np.asarray(c.image_paths)[f]) if c.image_paths else (),
            **rates))
    if not cams:
        raise CaptureError("no camera has frames in this window")
    return Capture(cams, dict(capture.meta))


def _fit_window(capture, grid_w, a, b, method, cfg, cb) -> dict:
    margin = int(cfg.windows.margin_s * 1e9)
    try:
        sub = _sub_capture(capture, a - margin, b + margin, margin + int(2e9))
        if method == "multiview":
            if sub.num_cameras < 2:
                raise CaptureError(f"{sub.num_cameras} camera(s) with frames in this window; multiview needs 2")
            r = fit_capture(sub, grid_w, cfg.multiview.fit, progress=cb)
            return {"ok": 1, "t_ns": r.t_ns, "joints_ned": r.joints_ned, "shape": r.shape, "root_orient": r.root_orient,
                    "pose": r.pose, "transl": r.transl, "fit_seconds": r.fit_seconds}
        r = run_monocular(sub, cfg.monocular, progress=cb)
        shape = r.pipeline.model.shape if r.pipeline is not None and r.pipeline.model is not None else np.zeros(0)
        return {"ok": 1, "t_ns": r.t_ns, "joints_ned": r.joints_ned, "shape": np.asarray(shape)}
    except CaptureError as e:
        return {"ok": 0, "error": np.array(str(e))}


def _read_marker(path: Path) -> dict[str, Path] | None:
    import json

    if not path.is_file():
        return None
    try:
        paths = {k: Path(v) for k, v in json.loads(path.read_text()).items()}
    except (OSError, ValueError):
        return None
    return paths if all(p.is_file() for p in paths.values()) else None


def _flight_seconds(capture: Capture) -> float:
    """The span of the recorded frames (the flight time the processing covers)."""
    t0, t1 = capture.time_range_ns()
    return (t1 - t0) * 1e-9
