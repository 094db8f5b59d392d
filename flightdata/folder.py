"""The flight folder: the one owner of a flight's files, their names and their layout.

    from flightdata.folder import FlightFolder

    flight = FlightFolder("flights/demo")
    flight.drone_ids()                 # ['drone_1', 'drone_2', ..., 'drone_10'] -- natural order
    flight.drone_logs()                # {'drone_1': [Sortie(1, .../drone_1.s001.mcap)], ...} -- every sortie
    flight.drone_logs(sortie=2)        # only sortie 2 of each drone that flew it
    flight.plan()                      # the OrbitPlan (plan.json)
    path = flight.new_recording("drone_1")   # the next sortie's file; never an existing one

Layout (version :data:`LAYOUT_VERSION`; every name below is spelled here and nowhere else)::

    <flight>/
      <drone_id>.s<NNN>.mcap          one recording per agent start (sortie NNN = 001, 002, ...), MCAP
      <drone_id>.s<NNN>.config.toml   the agent's resolved configuration of that sortie
      <drone_id>.s<NNN>.track.json    the agent's tracking / failsafe counters of that sortie (track mode)
      <drone_id>.s<NNN>.transport.json  the agent's transport counters of that sortie (received, refused and why)
      truth.mcap                      the simulator's ground truth (simulated flights only)
      plan.json                       the orbit plan the ground station sent (OrbitPlan, JSON)
      config.toml                     the resolved configuration of the job that made the folder
      summary.json                    the flight's figures (orbit, rates, tracking, reconstruction accuracy)
      logs/                           the processes' stderr logs (demo)
      reconstruction/                 multi-view reconstruction outputs (BVH, NPZ, CSV, .rrd, summary.json)
      reconstruction_monocular/       monocular reconstruction outputs (same files)
      reconstruction_refined/         multi-view reconstruction with the refined drone positions (``skycap refine --reconstruct``)
      refined_track.npz / .json       the offline smoother's outputs (``skycap refine``)
      processing/                     ``skycap process``'s step cache (boxes, keypoints in chunks, fit windows),
                                      each entry keyed by a hash of its inputs and settings; safe to delete
      flight.foxglove.mcap            the flight in Foxglove's schemas (``skycap log foxglove``; two dots: never
                                      read as a recording)

Layout 1 (before sorties) named a drone's only recording ``<drone_id>.mcap``; it reads as sortie 1.

Recordings are never overwritten or truncated: :meth:`FlightFolder.new_recording` returns a path that does
not exist yet (the next sortie number), and the recorder creates it exclusively (``open(path, "xb")``), so
a restarted agent, a second flight into the same folder or two agents racing for a number can never open
an existing recording for writing. Readers take the whole flight (every sortie of every drone, in sortie
order) or one chosen sortie, and log which files they used (:meth:`FlightFolder.describe_logs`).
"""

from __future__ import annotations

import logging
import re
from collections.abc import Iterable
from dataclasses import dataclass
from pathlib import Path

import msgspec
import numpy as np

from flightdata.flightlog import FlightLog
from shared_msgs import OrbitPlan, SimTruth
from skycap.errors import SkycapError
from skycap.frames import yaw_from_quat_wxyz

log = logging.getLogger(__name__)

__all__ = ["LAYOUT_VERSION", "FlightFolder", "FlightFolderError", "Sortie", "natural_key", "read_sim_truth"]

LAYOUT_VERSION = 2
"""2: one recording per sortie (``<drone>.s<NNN>.mcap``); 1: one ``<drone>.mcap`` per drone."""

TRUTH_NAME = "truth"
PLAN_FILE = "plan.json"
TRUTH_FILE = f"{TRUTH_NAME}.mcap"
CONFIG_FILE = "config.toml"
SUMMARY_FILE = "summary.json"
LOGS_DIR = "logs"
RECONSTRUCTION_DIRS = {"multiview": "reconstruction", "monocular": "reconstruction_monocular"}
RECONSTRUCTION_REFINED_DIR = "reconstruction_refined"
REFINED_NPZ = "refined_track.npz"
REFINED_JSON = "refined_track.json"
PROCESSING_DIR = "processing"
FOXGLOVE_FILE = "flight.foxglove.mcap"

_SORTIE_RE = re.compile(r"^(?P<node>[^.]+)\.s(?P<n>\d{3,})\.mcap$")
_LEGACY_RE = re.compile(r"^(?P<node>[^.]+)\.mcap$")


class FlightFolderError(SkycapError):
    """A flight folder that lacks what was asked of it (no recordings, no plan, an unknown sortie)."""


def natural_key(name: str) -> tuple:
    """Sort key that orders embedded numbers by value: ``drone_2`` before ``drone_10``."""
    return tuple(int(t) if t.isdigit() else t for t in re.split(r"(\d+)", name))


@dataclass(frozen=True, order=True)
class Sortie:
    """One recording of one node: ``number`` (1, 2, ...) and its ``path``."""

    number: int
    path: Path

    @classmethod
    def of(cls, path: str | Path) -> Sortie:
        """The sortie a recording's path names (``drone_1.s002.mcap`` -> 2; layout 1 ``drone_1.mcap`` -> 1)."""
        path = Path(path)
        m = _SORTIE_RE.match(path.name)
        if m:
            return cls(int(m["n"]), path)
        if _LEGACY_RE.match(path.name):
            return cls(1, path)
        raise FlightFolderError(f"{path} is not named as a recording (<node>.s<NNN>.mcap)")

    @property
    def track_stats_path(self) -> Path:
        """The agent's counters of this sortie (``<drone>.s<NNN>.track.json``)."""
        return self.path.with_suffix(".track.json")

    @property
    def transport_stats_path(self) -> Path:
        """The agent's transport counters of this sortie, per subscription (received, malformed and why, ...;
        ``<drone>.s<NNN>.transport.json``)."""
        return self.path.with_suffix(".transport.json")

    @property
    def config_path(self) -> Path:
        """The agent's resolved configuration of this sortie (``<drone>.s<NNN>.config.toml``)."""
        return self.path.with_suffix(".config.toml")


class FlightFolder:
    """One flight's folder (see the module docstring for its layout). Creating the object touches nothing."""

    def __init__(self, path: str | Path) -> None:
        self.path = Path(path)

    def __repr__(self) -> str:
        return f"FlightFolder({str(self.path)!r})"

    # ------------------------------------------------------------------------------------ fixed names
    @property
    def plan_path(self) -> Path:
        return self.path / PLAN_FILE

    @property
    def truth_path(self) -> Path:
        return self.path / TRUTH_FILE

    @property
    def config_path(self) -> Path:
        return self.path / CONFIG_FILE

    @property
    def summary_path(self) -> Path:
        return self.path / SUMMARY_FILE

    @property
    def logs_dir(self) -> Path:
        return self.path / LOGS_DIR

    @property
    def refined_npz_path(self) -> Path:
        return self.path / REFINED_NPZ

    @property
    def refined_json_path(self) -> Path:
        return self.path / REFINED_JSON

    @property
    def foxglove_path(self) -> Path:
        """The flight as a Foxglove MCAP (:func:`flightdata.foxglove.export_foxglove`)."""
        return self.path / FOXGLOVE_FILE

    @property
    def refined_reconstruction_dir(self) -> Path:
        """The multi-view reconstruction with the refined drone positions (``skycap refine --reconstruct``)."""
        return self.path / RECONSTRUCTION_REFINED_DIR

    @property
    def processing_dir(self) -> Path:
        """``skycap process``'s step cache (``processing/``): derived data only, never a recording."""
        return self.path / PROCESSING_DIR

    def processing_step_dir(self, step: str) -> Path:
        """The cache folder of one ``skycap process`` step (``processing/<step>``, e.g. ``keypoints``)."""
        if not step or "/" in step or step.startswith("."):
            raise FlightFolderError(f"processing step {step!r} cannot name a folder: use letters, digits and '_'")
        return self.processing_dir / step

    def reconstruction_dir(self, method: str) -> Path:
        """The output folder of a reconstruction method (``multiview`` or ``monocular``)."""
        try:
            return self.path / RECONSTRUCTION_DIRS[method]
        except KeyError:
            raise FlightFolderError(f"unknown reconstruction method {method!r}; "
                                    f"one of {sorted(RECONSTRUCTION_DIRS)}") from None

    # ------------------------------------------------------------------------------------- recordings
    def _recordings(self) -> dict[str, list[Sortie]]:
        out: dict[str, list[Sortie]] = {}
        if not self.path.is_dir():
            return out
        for p in self.path.iterdir():
            m = _SORTIE_RE.match(p.name)
            if m:
                out.setdefault(m["node"], []).append(Sortie(int(m["n"]), p))
                continue
            m = _LEGACY_RE.match(p.name)
            if m:
                out.setdefault(m["node"], []).append(Sortie(1, p))
        for node, sorties in out.items():
            sorties.sort()
            numbers = [s.number for s in sorties]
            if len(set(numbers)) != len(numbers):
                raise FlightFolderError(
                    f"{self.path}: {node} has two recordings numbered as one sortie "
                    f"({[s.path.name for s in sorties]}); a layout-1 file <drone>.mcap reads as sortie 1, so rename "
                    f"one of them to {node}.s<NNN>.mcap with an unused number")
        return out

    def drone_ids(self) -> list[str]:
        """The drones with at least one recording, in natural order (``drone_2`` before ``drone_10``)."""
        return sorted((n for n in self._recordings() if n != TRUTH_NAME), key=natural_key)

    def has_recordings(self) -> bool:
        """Whether the folder holds any recording (a drone's or the simulator truth)."""
        return bool(self._recordings()) or self.truth_path.exists()

    def sorties(self, drone_id: str) -> list[Sortie]:
        """The recordings of ``drone_id`` in sortie order (empty when it has none)."""
        return self._recordings().get(drone_id, [])

    def drone_logs(self, sortie: int | None = None, drone_ids: Iterable[str] | None = None) -> dict[str, list[Sortie]]:
        """Per drone (natural order), its recordings: every sortie (``sortie=None``, the whole flight) or
        only sortie ``sortie`` (drones that did not fly it are left out). Raises :class:`FlightFolderError`
        when nothing matches."""
        rec = self._recordings()
        ids = list(drone_ids) if drone_ids is not None else self.drone_ids()
        out: dict[str, list[Sortie]] = {}
        for d in ids:
            chosen = [s for s in rec.get(d, []) if sortie is None or s.number == sortie]
            if chosen:
                out[d] = chosen
        if not out:
            have = {d: [s.number for s in rec.get(d, [])] for d in ids}
            what = "no drone recordings" if sortie is None else f"no recording of sortie {sortie}"
            raise FlightFolderError(f"{self.path} holds {what} (drones and their sorties: {have or 'none'}); "
                                    "pass the folder an agent recorded into (--record-dir) or another --sortie")
        return out

    def describe_logs(self, logs: dict[str, list[Sortie]]) -> str:
        """One line that says which recordings a reader used, for its log and its summary."""
        return "; ".join(f"{d}: " + ", ".join(s.path.name for s in ss) for d, ss in logs.items())

    @staticmethod
    def recording_names(logs: dict[str, list[Sortie]]) -> dict[str, list[str]]:
        """Per drone, the file names of the recordings a reader used (JSON-ready, for its summary)."""
        return {d: [s.path.name for s in ss] for d, ss in logs.items()}

    def new_recording(self, node_id: str) -> Path:
        """The path of ``node_id``'s next sortie (one above the highest present). It does not exist yet;
        the recorder creates it exclusively, so even a race for the same number cannot overwrite a file."""
        if not node_id or "." in node_id or "/" in node_id:
            raise FlightFolderError(f"node id {node_id!r} cannot name a recording: use letters, digits, '_' or '-'")
        n = max((s.number for s in self._recordings().get(node_id, [])), default=0) + 1
        return self.path / f"{node_id}.s{n:03d}.mcap"

    # ---------------------------------------------------------------------------------- plan, truth
    def save_plan(self, plan: OrbitPlan) -> Path:
        """Write ``plan.json`` (the orbit plan as sent)."""
        self.path.mkdir(parents=True, exist_ok=True)
        self.plan_path.write_bytes(msgspec.json.format(msgspec.json.encode(plan), indent=2))
        return self.plan_path

    def plan(self) -> OrbitPlan:
        """The orbit plan (``plan.json``); :class:`FlightFolderError` when it is missing or unreadable."""
        return load_plan(self.plan_path)

    def sim_truth(self, drone_ids: list[str]) -> tuple[np.ndarray, np.ndarray, np.ndarray, np.ndarray]:
        """:func:`read_sim_truth` of this flight's ``truth.mcap``."""
        return read_sim_truth(self.truth_path, drone_ids)


def load_plan(path: str | Path) -> OrbitPlan:
    """An orbit plan from its JSON file."""
    try:
        return msgspec.json.decode(Path(path).read_bytes(), type=OrbitPlan)
    except (OSError, msgspec.DecodeError, msgspec.ValidationError) as e:
        raise FlightFolderError(f"cannot read the orbit plan {path}: {e}") from None


def read_sim_truth(path: str | Path, drone_ids: list[str]) -> tuple[np.ndarray, np.ndarray, np.ndarray, np.ndarray]:
    """The simulator truth (``truth.mcap``, SimTruth) of the samples that hold every drone of ``drone_ids``,
    in time order: (t_ns (T,) int64, person root (T, 3), drone positions (T, D, 3), drone yaw_rad (T, D)),
    world NED; T = 0 when there is none (the caller says what it needed)."""
    ts, person, pos, yaw = [], [], [], []
    for m in FlightLog(path).messages():
        msg = m.msg
        if not isinstance(msg, SimTruth):
            continue
        by_id = {v.drone_id: v for v in msg.vehicles}
        if not all(d in by_id for d in drone_ids):
            continue
        ts.append(msg.header.t_measurement_ns)
        person.append(msg.person_root_ned_m)
        pos.append([by_id[d].position_ned_m for d in drone_ids])
        yaw.append([yaw_from_quat_wxyz(by_id[d].q_world_body) for d in drone_ids])
    o = np.argsort(ts)
    D = len(drone_ids)
    return (np.asarray(ts, dtype=np.int64)[o], np.asarray(person, dtype=float).reshape(-1, 3)[o],
            np.asarray(pos, dtype=float).reshape(-1, D, 3)[o], np.asarray(yaw, dtype=float).reshape(-1, D)[o])

