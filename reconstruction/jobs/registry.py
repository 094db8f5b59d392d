"""Processing callables by name or import path.

A processor is ``fn(flight_dir: Path, cfg, progress: Callable[[event], None], cancel: threading.Event) -> result``:
it reports progress events (``step``, ``fraction``, ``eta_s``, ``message``), checks ``cancel`` between units of
work and raises when it is set (leaving its cached steps consistent), and returns a picklable result.

Worker processes and Ray workers import it, so a job names it by a string: a registered name
(:func:`register_processor`) or an import path ``"package.module:function"``; a module-level function object is
accepted too and turned into its import path.
"""

from __future__ import annotations

import importlib
import threading
from collections.abc import Callable
from pathlib import Path
from typing import Any

from reconstruction.jobs.events import JobError

__all__ = ["Processor", "processor_spec", "register_processor", "registered_processors", "resolve_processor"]

Processor = Callable[[Path, Any, Callable[[Any], None], threading.Event], Any]

#: name -> import path; import paths (not functions) so that a worker process resolves the same name
_REGISTRY: dict[str, str] = {
    # reconstruction.api.reconstruct_flight (today's `skycap reconstruct`: the simulator's 2D keypoints) as a processor
    "reconstruct": "reconstruction.jobs.adapters:reconstruct_job",
    # the processing pipeline of issue 19 (boxes -> keypoint models -> fit -> exports), cached steps
    "process": "reconstruction.process:process",
    # the same, its result as plain data (method, summary, output paths) for a submitter that does not import torch
    "process_summary": "reconstruction.jobs.adapters:process_summary_job",
}


def register_processor(name: str, target: str | Callable) -> None:
    """Register ``target`` (an import path ``"module:function"`` or a module-level function) under ``name``.

    Registration lives in this process; a local worker or Ray worker resolves the import path it was given, so
    register import paths, not lambdas."""
    _REGISTRY[name] = processor_spec(target)


def registered_processors() -> dict[str, str]:
    return dict(_REGISTRY)


def processor_spec(target: str | Callable) -> str:
    """The import path a worker resolves for ``target`` (a registered name, an import path or a function)."""
    if isinstance(target, str):
        if target in _REGISTRY:
            return _REGISTRY[target]
        if ":" not in target:
            raise JobError(f"unknown processor {target!r}: use a registered name ({', '.join(sorted(_REGISTRY))}) or "
                           f"an import path 'package.module:function'")
        return target
    if not callable(target):
        raise JobError(f"a processor must be a function or its import path, not {type(target).__name__}")
    module, qualname = getattr(target, "__module__", None), getattr(target, "__qualname__", "")
    spec = f"{module}:{qualname}"
    if not module or module == "__main__" or "<" in qualname:
        raise JobError(f"processor {target!r} cannot be imported by a worker process ({spec}): define it at module "
                       f"level in an importable module and pass it or its import path 'package.module:function'")
    try:
        same = _import(spec) is target
    except JobError:
        same = False
    if not same:
        raise JobError(f"processor {target!r} is not what its import path {spec} gives; pass a module-level function")
    return spec


def resolve_processor(target: str | Callable) -> Processor:
    """The function for a registered name, import path or function (imported here)."""
    if callable(target) and not isinstance(target, str):
        return target
    return _import(processor_spec(target))


def _import(spec: str) -> Processor:
    module, _, attr = spec.partition(":")
    try:
        obj: Any = importlib.import_module(module)
    except ModuleNotFoundError as e:
        raise JobError(f"processor {spec}: module {module!r} cannot be imported here ({e}); install or update the "
                       f"package on this machine (and on every Ray node), or use another processor") from e
    for part in attr.split("."):
        try:
            obj = getattr(obj, part)
        except AttributeError as e:
            raise JobError(f"processor {spec}: {module} has no {attr!r}") from e
    if not callable(obj):
        raise JobError(f"processor {spec} is a {type(obj).__name__}, not a function")
    return obj
