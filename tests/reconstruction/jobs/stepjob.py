"""A real small processor for the job tests: numpy work in steps over a flight folder, each step cached in the
folder (written atomically), resumable, cancellable between units, its units spread with ``parallel_map``.

Importable by worker processes and Ray workers as ``tests.reconstruction.jobs.stepjob:step_job``.
"""

from __future__ import annotations

import dataclasses
import os
import threading
from pathlib import Path

import numpy as np

from reconstruction.jobs.units import parallel_map

CACHE = "stepjob"


@dataclasses.dataclass(frozen=True)
class StepEvent:
    """The processing function's own event class (what the real ``process`` reports): the runner takes any object
    with these fields."""

    step: str
    fraction: float
    eta_s: float | None
    message: str


@dataclasses.dataclass
class StepConfig:
    steps: int = 3
    units: int = 2
    #: matrix size and products per unit (the work)
    size: int = 96
    iters: int = 40
    #: raise StepFailure in this step (None: never)
    fail_at_step: int | None = None
    #: raise an exception that cannot be pickled in this step
    unpicklable_at_step: int | None = None
    #: os._exit the worker in this step (a crash)
    crash_at_step: int | None = None


class StepCancelled(Exception):
    """What the processor raises when cancelled."""


class StepFailure(Exception):
    """A processor error with a message to pass through."""


class _Unpicklable(Exception):
    def __init__(self, lock):
        super().__init__("holds a lock")
        self.lock = lock


@dataclasses.dataclass
class StepResult:
    state: np.ndarray
    computed: list[int]
    cached: list[int]
    pid: int


def make_flight(folder: Path, seed: int) -> Path:
    folder.mkdir(parents=True, exist_ok=True)
    rng = np.random.default_rng(seed)
    np.save(folder / "input.npy", rng.standard_normal((96, 96)) / 10)
    return folder


def unit(args) -> np.ndarray:
    state, step, u, size, iters = args
    rng = np.random.default_rng(1000 * step + u)
    w = rng.standard_normal((size, size)) / np.sqrt(size)
    x = state[:size, :size].copy()
    for _ in range(iters):
        x = np.tanh(x @ w)
    return x


def step_path(flight_dir: Path, k: int) -> Path:
    return flight_dir / CACHE / f"step_{k:03d}.npz"


def step_job(flight_dir: Path, cfg: StepConfig | None, progress, cancel: threading.Event) -> StepResult:
    cfg = cfg or StepConfig()
    (flight_dir / CACHE).mkdir(exist_ok=True)
    state = np.load(flight_dir / "input.npy")
    computed, cached = [], []
    for k in range(cfg.steps):
        name = f"step{k}"
        path = step_path(flight_dir, k)
        if path.exists():
            state = np.load(path)["state"]
            cached.append(k)
            progress(StepEvent(name, 1.0, 0.0, "cached"))
            continue
        if cancel.is_set():
            raise StepCancelled(f"cancelled before step {k}")
        progress(StepEvent(name, 0.0, None, "start"))
        if cfg.fail_at_step == k:
            raise StepFailure(f"step {k} cannot read {flight_dir.name}/input.npy: bad values")
        if cfg.unpicklable_at_step == k:
            raise _Unpicklable(threading.Lock())
        if cfg.crash_at_step == k:
            os._exit(3)
        n_done = [0]

        def done(i, _r, name=name, n=cfg.units):
            n_done[0] += 1
            progress(StepEvent(name, n_done[0] / n, None, f"unit {i}"))

        parts = parallel_map(unit, [(state, k, u, cfg.size, cfg.iters) for u in range(cfg.units)], on_done=done)
        state = np.mean(parts, axis=0) + state[: cfg.size, : cfg.size]
        tmp = path.with_name(path.name + ".tmp")
        with open(tmp, "wb") as f:
            np.savez(f, state=state)
        os.replace(tmp, path)
        computed.append(k)
    return StepResult(state, computed, cached, os.getpid())
