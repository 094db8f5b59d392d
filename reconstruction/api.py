"""Reconstruction as library functions: one function per method over a capture, one over a flight folder.

    from flightdata.folder import FlightFolder
    from reconstruction.api import reconstruct_flight
    from reconstruction.multiview.run import MultiviewConfig

    res = reconstruct_flight(FlightFolder("flights/demo"), "multiview", MultiviewConfig(), sortie=None,
                             progress=lambda stage, done, total: print(stage, done, total))
    res.joints_ned, res.t_ns        # (T, 17, 3) world NED, (T,) ns
    res.summary["recordings"]       # {"drone_1": ["drone_1.s001.mcap", ...], ...}: what was read
    res.outputs                     # {"bvh": Path, "npz": Path, ...} (written into res.out_dir)

Per method (``reconstruction.<method>.run``): a typed config dataclass and ``run(capture, config, *, out_dir=None,
progress=None) -> result`` over a :class:`reconstruction.capture.Capture` (from any source: a flight folder,
:func:`reconstruction.synth.synthesize_capture`, ``Capture.load``):

* multiview: :class:`reconstruction.multiview.run.MultiviewConfig`, :func:`reconstruction.multiview.run.run`;
* monocular: :class:`reconstruction.monocular.reconstruct.MonocularRunConfig`,
  :func:`reconstruction.monocular.reconstruct.run`;
* the offline smoother (``skycap refine``): :class:`reconstruction.track.flight.RefineConfig`,
  :func:`reconstruction.track.flight.refine_flight`.

The flight-level :func:`reconstruct_flight` reads the flight (:func:`reconstruction.flight.read_flight`: natural
drone order, the whole flight -- every sortie of each drone, chained in sortie order -- or one ``sortie``), runs
the method and writes its outputs into the method's folder of the flight (or ``out_dir``); the summary
(``summary.json``) names the recordings it used.

Library functions do not print (they log), take no argparse namespace and return no exit codes; errors a user can
act on are :class:`skycap.errors.SkycapError` subclasses (:class:`ReconstructionError`, ``CaptureError``,
``FlightFolderError``) whose message names the problem and the fix. ``progress(stage, done, total)`` is called
as the work advances (``stage``: e.g. ``"read"``, ``"fit"``, ``"export"``; ``done`` of ``total`` steps).
The command line (``skycap refine``) is a thin layer over these functions.

From the recorded images: :func:`reconstruction.process.process` (``skycap process``, alias ``skycap reconstruct``)
runs the keypoint models on the flight's camera frames and then these methods' fits, in cached, resumable,
cancellable steps with progress events; :func:`reconstruct_flight` fits the keypoints recorded in the flight
(``keypoints2d`` / ``sim/keypoints2d``).
"""

from __future__ import annotations

import dataclasses
import logging
from collections.abc import Callable
from pathlib import Path
from typing import Any

import numpy as np

from flightdata.folder import FlightFolder
from reconstruction.monocular.reconstruct import MonocularRunConfig
from reconstruction.monocular.reconstruct import read_capture as read_monocular_capture
from reconstruction.monocular.reconstruct import run as run_monocular
from reconstruction.multiview.run import MultiviewConfig
from reconstruction.multiview.run import read_capture as read_multiview_capture
from reconstruction.multiview.run import run as run_multiview
from reconstruction.result import Progress, ReconstructionError, ReconstructionResult, report

log = logging.getLogger(__name__)

__all__ = ["METHODS", "Progress", "ReconstructionError", "ReconstructionResult", "choose_method", "default_config",
           "reconstruct_flight", "report"]

METHODS = ("multiview", "monocular")

def default_config(method: str) -> Any:
    """The default config of ``method`` (:data:`METHODS`)."""
    if method == "multiview":
        return MultiviewConfig()
    if method == "monocular":
        return MonocularRunConfig()
    raise ReconstructionError(f"unknown reconstruction method {method!r}; use one of {', '.join(METHODS)}")


def choose_method(flight, sortie: int | None = None) -> str:
    """The default method for a flight: multiview with more than one drone (in ``sortie``, when given), else monocular."""
    flight = flight if isinstance(flight, FlightFolder) else FlightFolder(flight)
    return "multiview" if len(flight.drone_logs(sortie=sortie)) > 1 else "monocular"


def reconstruct_flight(flight, method: str | None = None, config: Any = None, *, sortie: int | None = None,
                       out_dir: str | Path | None = None, progress: Progress | None = None) -> ReconstructionResult:
    """Reconstruct a recorded flight with ``method`` (None: :func:`choose_method`) and ``config`` (None: the method's
    default), from the whole flight (``sortie=None``: every sortie of each drone in order) or one sortie.

    ``flight``: a :class:`flightdata.folder.FlightFolder` or its path. Writes into ``out_dir`` (default: the
    method's folder, :meth:`FlightFolder.reconstruction_dir`) the motion (BVH/NPZ/CSV/RRD), ``config.toml`` and
    ``summary.json`` (with ``recordings``: per drone the files read, and ``sortie``). Returns the method's result.
    """
    flight = flight if isinstance(flight, FlightFolder) else FlightFolder(flight)
    method = method or choose_method(flight, sortie)
    config = default_config(method) if config is None else config
    out = Path(out_dir) if out_dir is not None else flight.reconstruction_dir(method)
    if method == "multiview":
        _check_config(config, MultiviewConfig, method)
        cap = read_multiview_capture(flight, config, sortie=sortie, progress=progress)
        run = run_multiview
    elif method == "monocular":
        _check_config(config, MonocularRunConfig, method)
        cap = read_monocular_capture(flight, config, sortie=sortie, progress=progress)
        run = run_monocular
    else:
        raise ReconstructionError(f"unknown reconstruction method {method!r}; use one of {', '.join(METHODS)}")
    log.info("%s reconstruction of %s (%s)", method, flight.path, "whole flight" if sortie is None else f"sortie {sortie}")
    return run(cap, config, out_dir=out, progress=progress)


def _check_config(config: Any, cls: type, method: str) -> None:
    if not isinstance(config, cls):
        raise ReconstructionError(f"the {method} method takes a {cls.__name__}, not a {type(config).__name__}; "
                                  f"build one with {cls.__module__}.{cls.__name__}(...) or pass config=None for the defaults")
