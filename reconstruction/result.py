"""What every reconstruction method shares: the progress callback, the error type and the result.

The methods (:mod:`reconstruction.multiview.run`, :mod:`reconstruction.monocular.reconstruct`) import these;
:mod:`reconstruction.api` runs the methods over a flight folder.
"""

from __future__ import annotations

import dataclasses
from collections.abc import Callable
from pathlib import Path
from typing import Any

import numpy as np

from skycap.errors import SkycapError

__all__ = ["Progress", "ReconstructionError", "ReconstructionResult", "report"]


Progress = Callable[[str, int, int], None]
"""``progress(stage, done, total)``: ``done`` of ``total`` steps of ``stage`` are finished."""


class ReconstructionError(SkycapError):
    """A reconstruction that cannot run as asked (unknown method, a config that does not fit the method)."""


def report(progress: Progress | None, stage: str, done: int, total: int) -> None:
    """Call ``progress`` when there is one."""
    if progress is not None:
        progress(stage, int(done), int(total))


@dataclasses.dataclass
class ReconstructionResult:
    """What a reconstruction method returns.

    joints_ned (T, 17, 3) world NED at t_ns (T,); summary: the figures (what ``summary.json`` holds); out_dir and
    outputs ({"bvh", "npz", "csv", "rrd"} -> path): where the files were written (None / {} when not written).
    """

    method: str
    t_ns: np.ndarray
    joints_ned: np.ndarray
    summary: dict[str, Any]
    out_dir: Path | None = None
    outputs: dict[str, Path] = dataclasses.field(default_factory=dict)
