"""The ``export`` step: the stitched motion into the output folder (``motion.{bvh,npz,csv,rrd}`` through
:func:`reconstruction.export.export_motion`, as ``skycap reconstruct`` always wrote), then any extra exporters.

The hook for new formats (TRC, a Blender-ready file, a Foxglove MCAP, ...): register a function under a name and
list that name in ``ExportConfig.extra`` (``--set export.extra='["trc"]'``)::

    from reconstruction.process.export import ExportContext, register_exporter

    def write_trc(ctx: ExportContext) -> dict[str, Path]:
        path = ctx.out_dir / "motion.trc"
        ...  # ctx.t_ns (T,), ctx.joints_ned (T, 17, 3), ctx.capture, ctx.boxes, ctx.flight, ctx.config
        return {"trc": path}

    register_exporter("trc", write_trc)

An exporter returns the files it wrote ({name: path}); they are listed in ``summary.json`` ``outputs``.

An exporter that needs the motion only at its end (the Foxglove MCAP: the recordings first, the skeleton last)
registers with ``early=True``: the pipeline starts it before the fit (:class:`EarlyExports`: in a spawned process by
default, ``export.early_pool``), with a context whose motion is pending; it calls ``ctx.wait_motion()`` (or reads
:func:`late_motion`'s ``t_ns`` / ``joints_ned``) where it needs the motion, which blocks until the fit ends and raises
:class:`MotionUnavailable` when the fit failed or was cancelled (the exporter then removes what it began writing).
``ctx.check_motion()`` raises the same at once, for exporters that can stop early between their parts.
"""

from __future__ import annotations

import dataclasses
import logging
import pickle
import threading
import time
from collections.abc import Callable
from concurrent.futures.process import BrokenProcessPool
from pathlib import Path
from typing import Any

import numpy as np

from reconstruction.process.events import ProcessError

log = logging.getLogger(__name__)

__all__ = ["EARLY_EXPORTERS", "EXPORTERS", "EarlyExports", "ExportContext", "MotionUnavailable", "PendingMotion",
           "export_all", "late_motion", "register_exporter"]


class MotionUnavailable(ProcessError):
    """An early exporter waited for the motion, but the fit failed or was cancelled."""


class PendingMotion:
    """The fit's result as an early exporter sees it before the fit ends: :meth:`set` (the motion) or :meth:`fail`
    (the fit's error), once; :meth:`wait` blocks until either, :meth:`check` raises at once after a failure."""

    def __init__(self) -> None:
        self._done = threading.Event()
        #: seconds the exporters spent blocked in :meth:`ExportContext.wait_motion` (all of them together)
        self.waited_s = 0.0
        self._values: dict[str, Any] | None = None
        self._error: BaseException | None = None

    def set(self, **values: Any) -> None:
        self._values = values
        self._done.set()

    def fail(self, error: BaseException) -> None:
        if not self._done.is_set():
            self._error = error
            self._done.set()

    def _receive(self, block: bool) -> None:
        """Where :meth:`set` / :meth:`fail` come from: in this process, the caller's thread (nothing to do but
        wait)."""
        if block:
            self._done.wait()

    def check(self) -> None:
        """Raise :class:`MotionUnavailable` if the fit already failed (no wait)."""
        self._receive(block=False)
        if self._error is not None:
            raise MotionUnavailable(f"the fit ended without a motion ({type(self._error).__name__}: {self._error}); "
                                    "the early exporter stopped") from self._error

    def wait(self) -> dict[str, Any]:
        self._receive(block=True)
        self.check()
        assert self._values is not None
        return self._values


class _PipeMotion(PendingMotion):
    """:class:`PendingMotion` in an early exporter's spawned process: the parent's :meth:`set` / :meth:`fail` arrive
    on a pipe (:class:`_MotionSender`)."""

    def __init__(self, conn) -> None:
        super().__init__()
        self._conn = conn

    def _receive(self, block: bool) -> None:
        if not self._done.is_set() and (block or self._conn.poll()):
            try:
                kind, payload = self._conn.recv()
            except EOFError:  # the parent is gone
                kind, payload = "fail", "the processing that started this exporter ended"
            if kind == "ok":
                self.set(**payload)
            else:
                self.fail(ProcessError(payload))


class _MotionSender:
    """The parent's end of a :class:`_PipeMotion`: :meth:`set` / :meth:`fail` once; ``waited_s`` as the child
    reported it."""

    def __init__(self, conn) -> None:
        self._conn = conn
        self._sent = False
        self.waited_s = 0.0

    def set(self, **values: Any) -> None:
        self._send(("ok", values))

    def fail(self, error: BaseException) -> None:
        self._send(("fail", f"{type(error).__name__}: {error}"))

    def _send(self, msg) -> None:
        if not self._sent:
            self._sent = True
            try:
                self._conn.send(msg)
            except (BrokenPipeError, OSError):  # the child already ended (it failed: its report says why)
                pass


def _early_child(fn: Callable, ctx: "ExportContext", conn) -> None:
    """An early exporter in a spawned process: ``fn(ctx)`` with the motion from the pipe; its files, seconds and
    wait (or its error) go back on the pipe."""
    ctx.motion = _PipeMotion(conn)
    try:
        res, seconds = _timed(fn, ctx)
        conn.send(("done", {k: str(v) for k, v in res.items()}, seconds, ctx.motion.waited_s))
    except MotionUnavailable:
        conn.send(("stopped", None, 0.0, ctx.motion.waited_s))
    except BaseException as e:  # noqa: BLE001 - reported to the parent, which raises it
        conn.send(("error", f"{type(e).__name__}: {e}", 0.0, ctx.motion.waited_s))
    finally:
        conn.close()


@dataclasses.dataclass
class ExportContext:
    """What an exporter gets: the flight (:class:`flightdata.folder.FlightFolder`), the output folder, the motion
    (``t_ns`` (T,), ``joints_ned`` (T, 17, 3) world NED metres), the body-model ``params`` / ``shape`` when one
    window gave them, the capture fitted (:class:`reconstruction.capture.Capture`: cameras, poses, fused 2D
    keypoints), per drone the boxes step's arrays (``t_ns``, ``box_xywh``, ``source``), the method, the
    :class:`reconstruction.process.config.ProcessConfig` and the keypoints source."""

    flight: Any
    out_dir: Path
    t_ns: np.ndarray
    joints_ned: np.ndarray
    capture: Any
    method: str
    config: Any
    keypoints_source: str
    boxes: dict[str, dict[str, np.ndarray]] = dataclasses.field(default_factory=dict)
    params: dict | None = None
    shape: np.ndarray | None = None
    #: set for an early exporter's context (``t_ns`` ... ``shape`` are None until the fit ends): see :meth:`wait_motion`
    motion: Any = None

    def wait_motion(self) -> tuple[np.ndarray, np.ndarray]:
        """``(t_ns, joints_ned)``; in an early exporter, blocks until the fit ends (then ``params`` and ``shape`` are
        set too) and raises :class:`MotionUnavailable` if it failed or was cancelled."""
        if self.motion is not None and self.t_ns is None:
            t0 = time.perf_counter()
            try:
                v = self.motion.wait()
            finally:
                self.motion.waited_s += time.perf_counter() - t0
            self.t_ns, self.joints_ned, self.params, self.shape = v["t_ns"], v["joints_ned"], v["params"], v["shape"]
        return self.t_ns, self.joints_ned

    def check_motion(self) -> None:
        """In an early exporter: raise :class:`MotionUnavailable` now if the fit failed or was cancelled."""
        if self.motion is not None:
            self.motion.check()


class _LateMotion:
    """``t_ns`` / ``joints_ned`` read from an export context when first asked (see :func:`late_motion`)."""

    def __init__(self, ctx: ExportContext) -> None:
        self._ctx = ctx

    @property
    def t_ns(self) -> np.ndarray:
        return self._ctx.wait_motion()[0]

    @property
    def joints_ned(self) -> np.ndarray:
        return self._ctx.wait_motion()[1]


def late_motion(ctx: ExportContext) -> Any:
    """An object with ``t_ns`` and ``joints_ned`` attributes that wait for the fit (:meth:`ExportContext.wait_motion`)
    when read: what an early exporter hands a writer that takes a result (e.g.
    :func:`flightdata.foxglove.export_foxglove`, which reads them only for its last channel)."""
    return _LateMotion(ctx)


Exporter = Callable[[ExportContext], dict[str, Path]]

#: name -> exporter; ``ExportConfig.extra`` names which run after the standard files
EXPORTERS: dict[str, Exporter] = {}
#: the registered exporters that may start before the fit (they wait for the motion themselves)
EARLY_EXPORTERS: set[str] = set()


def register_exporter(name: str, fn: Exporter, early: bool = False) -> None:
    """Make ``fn`` available as ``export.extra`` entry ``name`` (a later registration replaces an earlier one).
    ``early``: ``fn`` reads the motion only through ``ctx.wait_motion()`` / :func:`late_motion`, so the pipeline may
    start it before the fit (:class:`EarlyExports`; in a spawned process it must be picklable, else it runs after the
    fit)."""
    EXPORTERS[name] = fn
    if early:
        EARLY_EXPORTERS.add(name)
    else:
        EARLY_EXPORTERS.discard(name)


def export_foxglove_mcap(ctx: ExportContext) -> dict[str, Path]:
    """``export.extra = ["foxglove"]`` (on by default): the processed flight as a Foxglove MCAP in Foxglove's schemas
    (:func:`flightdata.foxglove.export_foxglove`: camera images with the boxes and keypoints, drones and cameras as
    transforms, the person track, the reconstructed skeleton) beside the motion files, as ``flight.foxglove.mcap``."""
    from flightdata.folder import FOXGLOVE_FILE
    from flightdata.foxglove import export_foxglove

    res = export_foxglove(ctx.flight, late_motion(ctx), ctx.out_dir / FOXGLOVE_FILE, sortie=ctx.config.sortie_or_none,
                          overwrite=True, progress=lambda *_: ctx.check_motion())  # stops between drones on a failed fit
    return {"foxglove": Path(res.path)}


register_exporter("foxglove", export_foxglove_mcap, early=True)


def _cameras(ctx: ExportContext) -> list[dict]:
    """The drones' camera poses at their frames within the motion (what the rerun recording draws)."""
    cams = []
    for cam in ctx.capture.cameras:
        sel = (cam.t_frame_ns >= ctx.t_ns[0]) & (cam.t_frame_ns <= ctx.t_ns[-1])
        t = cam.t_frame_ns[sel]
        if len(t):
            cams.append({"name": cam.name, "t_ns": t, "T_world_cam": cam.pose_at(t), "K": cam.K[-1],
                         "width_px": cam.width_px, "height_px": cam.height_px})
    return cams


def _timed(fn: Callable, *args) -> tuple[Any, float]:
    t0 = time.perf_counter()
    return fn(*args), time.perf_counter() - t0


def _rrd(ctx: ExportContext) -> dict[str, Path]:
    from reconstruction.viz import write_rrd

    return {"rrd": write_rrd(ctx.out_dir / "motion.rrd", ctx.joints_ned, ctx.t_ns, cameras=_cameras(ctx),
                             capture=ctx.capture)}


def _motion_files(ctx: ExportContext) -> dict[str, Path]:
    from reconstruction.export import export_motion

    return export_motion(ctx.out_dir, ctx.joints_ned, ctx.t_ns, params=ctx.params, shape=ctx.shape, rrd=False)


def _picklable(fn: Callable) -> bool:
    try:
        pickle.dumps(fn)
        return True
    except Exception:  # a lambda or a closure: it runs in this process
        return False


def config_snapshot(cfg: Any) -> Any:
    """A dataclass config as nested read-only-by-convention namespaces with the same attributes (its properties
    evaluated), importing nothing: what a worker process gets as ``ExportContext.config`` (unpickling
    :class:`ProcessConfig` itself would import torch through the fit's config, seconds per worker)."""
    import types

    if not dataclasses.is_dataclass(cfg) or isinstance(cfg, type):
        return cfg
    ns = types.SimpleNamespace(**{f.name: config_snapshot(getattr(cfg, f.name)) for f in dataclasses.fields(cfg)})
    for name in dir(type(cfg)):
        if isinstance(getattr(type(cfg), name, None), property):
            setattr(ns, name, getattr(cfg, name))
    return ns


class EarlyExports:
    """The ``early`` exporters (:data:`EARLY_EXPORTERS`) named in ``names``, started now, before the fit, on ``ctx``
    (the flight, output folder, capture, method, config, boxes; no motion yet): in threads (``pool="threads"``) or
    each in its own spawned process (``pool="processes"``: its Python does not compete with the fit's for the GIL;
    ``ctx.config`` is then a :func:`config_snapshot` and the motion arrives on a pipe). Then exactly one of:
    :meth:`motion_ready` (the fit's motion; :func:`export_all` collects their files) or :meth:`abort` (the fit
    failed or was cancelled: they stop, remove what they began, and their threads / processes have ended when it
    returns). ``names`` empty (nothing early listed): nothing starts; :attr:`names` is empty."""

    def __init__(self, ctx: ExportContext, names: list[str], workers: int = 2, pool: str = "threads") -> None:
        if pool not in ("threads", "processes"):
            raise ProcessError(f"export.early_pool is {pool!r}; use 'threads' or 'processes'")
        self.names = [n for n in names if n in EARLY_EXPORTERS and n in EXPORTERS]
        if pool == "processes":
            self.names = [n for n in self.names if _picklable(EXPORTERS[n])]  # the others run after the fit
        self.pool = pool
        self._pending: dict[str, Any] = {}  # name -> PendingMotion (threads) or _MotionSender (processes)
        self.t_start = time.perf_counter()
        self.t_motion: float | None = None
        #: after :meth:`results`: per exporter {"seconds", "before_motion_s", "waited_s", "overlap_s"}
        self.timing: dict[str, dict] = {}
        self._executor = None
        self._futures: dict[str, Any] = {}
        self._procs: dict[str, tuple[Any, Any]] = {}  # name -> (process, parent's pipe end)
        self._out_dir_existed = Path(ctx.out_dir).exists()
        self._out_dir = Path(ctx.out_dir)
        if not self.names:
            return
        if pool == "threads":
            import concurrent.futures as cf

            self._executor = cf.ThreadPoolExecutor(max(1, min(workers, len(self.names))),
                                                   thread_name_prefix="export-early")
            for n in self.names:
                # each exporter its own context (wait_motion() fills it in its thread) and its own pending motion
                self._pending[n] = PendingMotion()
                early = dataclasses.replace(ctx, t_ns=None, joints_ned=None, params=None, shape=None,
                                            motion=self._pending[n])
                self._futures[n] = self._executor.submit(_timed, EXPORTERS[n], early)
        else:
            import multiprocessing

            mp = multiprocessing.get_context("spawn")
            light = dataclasses.replace(ctx, t_ns=None, joints_ned=None, params=None, shape=None, motion=None,
                                        config=config_snapshot(ctx.config))
            for n in self.names:
                parent, child = mp.Pipe()
                proc = mp.Process(target=_early_child, args=(EXPORTERS[n], light, child), name=f"export-early-{n}",
                                  daemon=True)
                proc.start()
                child.close()
                self._procs[n] = (proc, parent)
                self._pending[n] = _MotionSender(parent)
        log.info("export: started %s before the fit (%s)", ", ".join(self.names), pool)

    def motion_ready(self, t_ns: np.ndarray, joints_ned: np.ndarray, params: dict | None = None,
                     shape: np.ndarray | None = None) -> None:
        self.t_motion = time.perf_counter()
        for m in self._pending.values():
            m.set(t_ns=t_ns, joints_ned=joints_ned, params=params, shape=shape)

    def abort(self, error: BaseException, grace_s: float = 30.0) -> None:
        """Stop the early exporters (they raise :class:`MotionUnavailable` at their next wait or check) and wait
        for their threads / processes (a process still running after ``grace_s`` is terminated); their errors are
        dropped (``error`` is what the caller raises). Idempotent."""
        if not self.names:
            return
        for m in self._pending.values():
            m.fail(error)
        if self._executor is not None:
            self._executor.shutdown(wait=True, cancel_futures=True)
            self._executor = None
            for n, f in self._futures.items():
                if not f.cancelled() and f.exception() is not None and not isinstance(f.exception(), MotionUnavailable):
                    log.warning("export: early exporter %r failed while stopping: %s", n, f.exception())
        for n, (proc, conn) in self._procs.items():
            proc.join(grace_s)
            if proc.is_alive():
                log.warning("export: early exporter %r did not stop within %.0f s; terminated", n, grace_s)
                proc.terminate()
                proc.join()
            conn.close()
        self._procs = {}
        if not self._out_dir_existed:
            try:
                self._out_dir.rmdir()  # made for the early files only, and empty: the failed run leaves nothing
            except OSError:
                pass

    def _process_result(self, n: str) -> tuple[dict[str, str], float]:
        proc, conn = self._procs[n]
        try:
            kind, res, seconds, waited = conn.recv()
        except EOFError:
            proc.join()
            raise ProcessError(f"export: the process writing {n!r} died (exit code {proc.exitcode}); run the "
                               "processing again (the earlier steps are cached)") from None
        proc.join()
        conn.close()
        self._pending[n].waited_s = waited
        if kind != "done":
            raise ProcessError(f"export: the early exporter {n!r} failed: {res}")
        return res, seconds

    def results(self) -> tuple[dict[str, Path], dict[str, float], dict[str, dict]]:
        """After :meth:`motion_ready`: wait for them -> ({name: path}, {exporter: seconds}, {exporter: {"seconds",
        "before_motion_s", "waited_s", "overlap_s"}}): ``before_motion_s`` of its ``seconds`` passed before the fit
        ended, ``waited_s`` of those blocked on the motion, ``overlap_s`` (the difference) were its work done while
        the fit ran. An exporter's error is raised here."""
        out: dict[str, Path] = {}
        seconds: dict[str, float] = {}
        timing: dict[str, dict] = {}
        try:
            for n in self.names:
                res, seconds[n] = self._futures[n].result() if n in self._futures else self._process_result(n)
                out.update({k: Path(v) for k, v in res.items()})
                t_motion = self.t_motion if self.t_motion is not None else time.perf_counter()
                before = min(seconds[n], t_motion - self.t_start)
                waited = min(self._pending[n].waited_s, before)
                timing[n] = {"seconds": round(seconds[n], 3), "before_motion_s": round(before, 3),
                             "waited_s": round(waited, 3), "overlap_s": round(before - waited, 3)}
        finally:
            if self._executor is not None:
                self._executor.shutdown(wait=True, cancel_futures=True)
                self._executor = None
        self.timing = timing
        return out, seconds, timing


def export_all(ctx: ExportContext, rrd: bool, extra: list[str], workers: int = 2,
               check_cancel: Callable[[], None] | None = None, pool: str = "threads",
               early: EarlyExports | None = None) -> tuple[dict[str, Path], dict[str, float]]:
    """Every output of the export step -> ({name: path}, {exporter: seconds}).

    The exporters are independent: the rerun recording (``rrd``) and the ``extra`` exporters (the Foxglove MCAP)
    run in up to ``workers`` threads (``pool="threads"``) or spawned processes (``pool="processes"``; spawn: safe
    from a threaded caller, e.g. the ground station or a Ray worker) while the calling thread writes
    ``motion.{bvh,trc,npz,csv}``. ``workers=0`` runs them all in the calling thread, one after the other (the same
    files). With processes, an exporter that cannot be pickled (a lambda, a closure) runs here, and in a worker
    ``ctx.config`` is a :func:`config_snapshot` (the same attributes). ``check_cancel`` is called
    between exporters (it raises to cancel).

    ``early``: the :class:`EarlyExports` started before the fit for some of ``extra``; they are handed the motion
    (``ctx``'s) and their files collected here instead of running them again. Any error or cancel here stops them
    (:meth:`EarlyExports.abort`)."""
    names = list(extra)
    for n in names:
        if n not in EXPORTERS:
            raise ProcessError(f"export.extra names {n!r}, which no exporter registered; registered: "
                               f"{', '.join(sorted(EXPORTERS)) or 'none'} (reconstruction.process.export.register_exporter)")
    started = set(early.names) if early is not None else set()
    jobs: list[tuple[str, Exporter]] = ([("rrd", _rrd)] if rrd else []) + [(n, EXPORTERS[n]) for n in names
                                                                          if n not in started]
    if pool not in ("threads", "processes"):
        raise ProcessError(f"export.pool is {pool!r}; use 'threads' or 'processes'")
    remote = [(n, fn) for n, fn in jobs if workers > 0 and (pool == "threads" or _picklable(fn))]
    local = [(n, fn) for n, fn in jobs if (n, fn) not in remote]
    out: dict[str, Path] = {}
    seconds: dict[str, float] = {}
    executor = None
    futures = {}
    if early is not None:
        early.motion_ready(ctx.t_ns, ctx.joints_ned, ctx.params, ctx.shape)
    try:
        if remote:
            import concurrent.futures as cf
            import multiprocessing

            if pool == "threads":
                executor = cf.ThreadPoolExecutor(min(workers, len(remote)), thread_name_prefix="export")
                futures = {n: executor.submit(_timed, fn, ctx) for n, fn in remote}
            else:
                executor = cf.ProcessPoolExecutor(min(workers, len(remote)),
                                                  mp_context=multiprocessing.get_context("spawn"))
                light = dataclasses.replace(ctx, config=config_snapshot(ctx.config))
                futures = {n: executor.submit(_timed, fn, light) for n, fn in remote}
        for n, fn in [("motion", _motion_files)] + local:
            if check_cancel is not None:
                check_cancel()
            res, seconds[n] = _timed(fn, ctx)
            out.update({k: Path(v) for k, v in res.items()})
        for n, f in futures.items():
            try:
                res, seconds[n] = f.result()
            except BrokenProcessPool as e:  # a worker died (killed, or a caller's script without a __main__ guard)
                log.warning("export: the worker process for %r died (%s); writing it in this process instead", n, e)
                if check_cancel is not None:
                    check_cancel()
                res, seconds[n] = _timed(dict(remote)[n], ctx)
            out.update({k: Path(v) for k, v in res.items()})
        if early is not None:
            res, early_s, _ = early.results()
            out.update(res)
            seconds.update(early_s)
    except BaseException as e:
        if early is not None:
            early.abort(e)
        raise
    finally:
        if executor is not None:
            executor.shutdown(wait=True, cancel_futures=True)
    # the standard files first, then the extra ones in their order (as summary.json lists them)
    order = ["bvh", "trc", "npz", "csv", "rrd"] + names
    out = {k: out[k] for k in order if k in out} | {k: v for k, v in out.items() if k not in order}
    return out, {k: round(v, 3) for k, v in seconds.items()}
