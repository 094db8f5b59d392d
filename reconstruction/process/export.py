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
from collections.abc import Callable
from pathlib import Path
from typing import Any

import numpy as np

from reconstruction.process.events import ProcessError

log = logging.getLogger(__name__)

__all__ = ["EXPORTERS", "ExportContext", "register_exporter", "run_exporters"]


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


def run_exporters(ctx: ExportContext, names: list[str]) -> dict[str, Path]:
    out: dict[str, Path] = {}
    for n in names:
        fn = EXPORTERS.get(n)
        if fn is None:
            raise ProcessError(f"export.extra names {n!r}, which no exporter registered; registered: "
                               f"{', '.join(sorted(EXPORTERS)) or 'none'} (reconstruction.process.export.register_exporter)")
        out.update({k: Path(v) for k, v in fn(ctx).items()})
    return out


def standard_outputs(ctx: ExportContext, rrd: bool) -> dict[str, Path]:
    """``motion.{bvh,npz,csv}`` (+ ``.rrd``) with the drones' camera poses at their frames."""
    from reconstruction.export import export_motion

    cams = []
    for cam in ctx.capture.cameras:
        sel = (cam.t_frame_ns >= ctx.t_ns[0]) & (cam.t_frame_ns <= ctx.t_ns[-1])
        t = cam.t_frame_ns[sel]
        if len(t):
            cams.append({"name": cam.name, "t_ns": t, "T_world_cam": cam.pose_at(t), "K": cam.K[-1],
                         "width_px": cam.width_px, "height_px": cam.height_px})
    return export_motion(ctx.out_dir, ctx.joints_ned, ctx.t_ns, params=ctx.params, shape=ctx.shape, cameras=cams,
                         capture=ctx.capture, rrd=rrd)
