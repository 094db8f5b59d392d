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
"""

from __future__ import annotations

import dataclasses
import logging
import pickle
import time
from collections.abc import Callable
from concurrent.futures.process import BrokenProcessPool
from pathlib import Path
from typing import Any

import numpy as np

from reconstruction.process.events import ProcessError

log = logging.getLogger(__name__)

__all__ = ["EXPORTERS", "ExportContext", "export_all", "register_exporter"]


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


Exporter = Callable[[ExportContext], dict[str, Path]]

#: name -> exporter; ``ExportConfig.extra`` names which run after the standard files
EXPORTERS: dict[str, Exporter] = {}


def register_exporter(name: str, fn: Exporter) -> None:
    """Make ``fn`` available as ``export.extra`` entry ``name`` (a later registration replaces an earlier one)."""
    EXPORTERS[name] = fn


def export_foxglove_mcap(ctx: ExportContext) -> dict[str, Path]:
    """``export.extra = ["foxglove"]`` (on by default): the processed flight as a Foxglove MCAP in Foxglove's schemas
    (:func:`flightdata.foxglove.export_foxglove`: camera images with the boxes and keypoints, drones and cameras as
    transforms, the person track, the reconstructed skeleton) beside the motion files, as ``flight.foxglove.mcap``."""
    from flightdata.folder import FOXGLOVE_FILE
    from flightdata.foxglove import export_foxglove

    res = export_foxglove(ctx.flight, ctx, ctx.out_dir / FOXGLOVE_FILE, sortie=ctx.config.sortie_or_none, overwrite=True)
    return {"foxglove": Path(res.path)}


register_exporter("foxglove", export_foxglove_mcap)


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


def export_all(ctx: ExportContext, rrd: bool, extra: list[str], workers: int = 2,
               check_cancel: Callable[[], None] | None = None, pool: str = "threads") -> tuple[dict[str, Path], dict[str, float]]:
    """Every output of the export step -> ({name: path}, {exporter: seconds}).

    The exporters are independent: the rerun recording (``rrd``) and the ``extra`` exporters (the Foxglove MCAP)
    run in up to ``workers`` threads (``pool="threads"``) or spawned processes (``pool="processes"``; spawn: safe
    from a threaded caller, e.g. the ground station or a Ray worker) while the calling thread writes
    ``motion.{bvh,trc,npz,csv}``. ``workers=0`` runs them all in the calling thread, one after the other (the same
    files). With processes, an exporter that cannot be pickled (a lambda, a closure) runs here, and in a worker
    ``ctx.config`` is a :func:`config_snapshot` (the same attributes). ``check_cancel`` is called
    between exporters (it raises to cancel)."""
    names = list(extra)
    for n in names:
        if n not in EXPORTERS:
            raise ProcessError(f"export.extra names {n!r}, which no exporter registered; registered: "
                               f"{', '.join(sorted(EXPORTERS)) or 'none'} (reconstruction.process.export.register_exporter)")
    jobs: list[tuple[str, Exporter]] = ([("rrd", _rrd)] if rrd else []) + [(n, EXPORTERS[n]) for n in names]
    if pool not in ("threads", "processes"):
        raise ProcessError(f"export.pool is {pool!r}; use 'threads' or 'processes'")
    remote = [(n, fn) for n, fn in jobs if workers > 0 and (pool == "threads" or _picklable(fn))]
    local = [(n, fn) for n, fn in jobs if (n, fn) not in remote]
    out: dict[str, Path] = {}
    seconds: dict[str, float] = {}
    executor = None
    futures = {}
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
    finally:
        if executor is not None:
            executor.shutdown(wait=True, cancel_futures=True)
    # the standard files first, then the extra ones in their order (as summary.json lists them)
    order = ["bvh", "trc", "npz", "csv", "rrd"]
    out = {k: out[k] for k in order if k in out} | {k: v for k, v in out.items() if k not in order}
    return out, {k: round(v, 3) for k, v in seconds.items()}
