"""Which runner processes flights: the typed config, the command-line options and the factory.

    cfg = load_config(JobsConfig, path, overrides)          # or part of a bigger config: cfg.jobs
    runner = runner_from_config(cfg)                        # LocalRunner / RayRunner

    add_job_args(parser)                                    # --ray ADDRESS, --workers N
    cfg = jobs_config_from_args(args, cfg)                  # the flags over the config
"""

from __future__ import annotations

import argparse
import dataclasses
from dataclasses import dataclass
from typing import Any

from reconstruction.jobs.events import JobError

__all__ = ["JobsConfig", "add_job_args", "jobs_config_from_args", "runner_from_config"]

RUNNERS = ("local", "ray")


@dataclass
class JobsConfig:
    """Where flights are processed (``[jobs]`` in a TOML config, ``--set jobs.workers=2``)."""

    #: "local" (worker processes on this machine) or "ray" (a Ray cluster)
    runner: str = "local"
    #: local: flights processed at once, each in its own worker process
    workers: int = 1
    #: local: BLAS / OpenMP / torch threads per worker (0: the machine's CPUs shared among the workers)
    threads_per_worker: int = 0
    #: local: processes a job's parallel units (per drone, per window) may use; 1: in the job's own process
    unit_workers: int = 1
    #: ray: the cluster's address: "HOST:PORT" of its head, "auto" (the cluster this machine belongs to), "local"
    #: (start a one-machine cluster in this process)
    ray_address: str = "auto"
    #: ray: CPUs reserved per flight and per parallel unit
    ray_cpus_per_job: float = 1.0
    ray_unit_cpus: float = 1.0
    #: the processing callable: a registered name ("reconstruct", "process") or an import path "module:function"
    processor: str = "process"
    #: local: seconds a cancelled worker has to stop by itself before it is terminated
    cancel_grace_s: float = 30.0

    def __post_init__(self) -> None:
        if self.runner not in RUNNERS:
            raise JobError(f"jobs.runner must be one of {', '.join(RUNNERS)}, not {self.runner!r}")
        if self.workers < 1 or self.unit_workers < 1:
            raise JobError(f"jobs.workers and jobs.unit_workers must be >= 1 (got {self.workers}, {self.unit_workers})")


def add_job_args(parser: argparse.ArgumentParser) -> None:
    """Add ``--ray ADDRESS`` and ``--workers N`` to a command that processes flights."""
    g = parser.add_argument_group("where to process")
    g.add_argument("--ray", metavar="ADDRESS", default=None,
                   help="process on a Ray cluster: its head's HOST:PORT, 'auto' (the cluster this machine is part of) "
                        "or 'local' (start one here); default: worker processes on this machine")
    g.add_argument("--workers", type=int, default=None, metavar="N",
                   help="local worker processes: flights processed at once (default: the config's jobs.workers)")


def jobs_config_from_args(args: argparse.Namespace, base: JobsConfig | None = None) -> JobsConfig:
    """``base`` (default: the defaults) with ``--ray`` / ``--workers`` applied."""
    cfg = base or JobsConfig()
    changes: dict[str, Any] = {}
    if getattr(args, "ray", None):
        changes.update(runner="ray", ray_address=args.ray)
    if getattr(args, "workers", None) is not None:
        changes["workers"] = args.workers
    return dataclasses.replace(cfg, **changes) if changes else cfg


def runner_from_config(cfg: JobsConfig):
    """The runner ``cfg`` names (a Ray runner connects to its cluster here)."""
    if cfg.runner == "ray":
        from reconstruction.jobs.ray_runner import RayRunner

        return RayRunner(cfg.ray_address or "auto", num_cpus_per_job=cfg.ray_cpus_per_job, unit_cpus=cfg.ray_unit_cpus)
    from reconstruction.jobs.local import LocalRunner

    return LocalRunner(cfg.workers, threads_per_worker=cfg.threads_per_worker or None, unit_workers=cfg.unit_workers, cancel_grace_s=cfg.cancel_grace_s)
