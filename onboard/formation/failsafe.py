"""Failsafe decisions of the formation (pure logic, no I/O): what the drone should do this step.

Priority, highest first (the first that applies wins; every condition found is listed in ``reasons``):

1. battery critical -> ``LAND``;
2. battery low -> ``RETURN``;
3. geofence or separation breach imminent (predicted margin below its threshold), or the MPC fell back
   several times in a row -> ``HOLD`` (brake and hover);
4. person lost (no accepted detection for ``person_lost_after_s``) -> ``HOLD_AND_SEARCH``;
5. the set of present teammates changed (one lost after ``teammate_lost_after_s``, or one appeared) ->
   ``RESPACE`` with new slot angles for the drones present;
6. otherwise ``CONTINUE``.

The decision carries the slot angles for the drones present whatever the action, so the caller can always
use them (they only change when the present set changes). The operator's angles are used while exactly the
drones they name are present; after a loss (or a join) the drones present are spaced equally, rotated to
where they are.

How the agent acts on a decision (:func:`respond`): ``RESPACE`` / ``CONTINUE`` -> fly the formation at the
decision's slot angle; ``HOLD`` -> brake and hold where the drone is; ``HOLD_AND_SEARCH`` -> hold and yaw to
look for the person; ``RETURN`` / ``LAND`` -> the mission's failsafe path (autopilot return / land).
:class:`FailsafeLog` keeps every change of decision (for the log, the counters and the flight statistics).
"""

from __future__ import annotations

import dataclasses
import enum

import numpy as np

from onboard.formation.slots import assign_slot_angles

__all__ = ["FailsafeAction", "FailsafeConfig", "FailsafeInputs", "FailsafeDecision", "decide", "FormationSupervisor",
           "FailsafeResponse", "respond", "FailsafeLog", "person_seen_s"]


class FailsafeAction(str, enum.Enum):
    CONTINUE = "continue"
    RESPACE = "respace"
    HOLD_AND_SEARCH = "hold_and_search"
    HOLD = "hold"
    RETURN = "return"
    LAND = "land"


@dataclasses.dataclass(frozen=True)
class FailsafeConfig:
    person_lost_after_s: float = 3.0
    teammate_lost_after_s: float = 2.0
    min_separation_margin_m: float = 0.5  #: predicted distance to a teammate below min_separation + this -> hold
    min_separation_m: float = 3.0
    min_geofence_margin_m: float = 0.5  #: predicted distance inside the fence below this -> hold
    max_consecutive_fallbacks: int = 5
    battery_return_frac: float = 0.25
    battery_land_frac: float = 0.12


@dataclasses.dataclass(frozen=True)
class FailsafeInputs:
    """What the drone knows this step.

    t_s: now; t_person_seen_s: newest accepted detection (None = never); teammates_last_seen_s: newest
    message time per teammate id (self excluded); predicted_min_separation_m / predicted_geofence_margin_m:
    over the current plan (inf if not applicable); positions_ned_m: known positions (for slot assignment);
    operator_angles_rad: the operator's slot angles of the planned formation (used while exactly those drones
    are present).
    """

    t_s: float
    self_id: str
    t_person_seen_s: float | None
    teammates_last_seen_s: dict[str, float]
    battery_frac: float
    predicted_min_separation_m: float = float("inf")
    predicted_geofence_margin_m: float = float("inf")
    consecutive_fallbacks: int = 0
    person_ned_m: tuple[float, float, float] = (0.0, 0.0, 0.0)
    positions_ned_m: dict[str, tuple[float, float, float]] = dataclasses.field(default_factory=dict)
    operator_angles_rad: dict[str, float] | None = None


@dataclasses.dataclass(frozen=True)
class FailsafeDecision:
    action: FailsafeAction
    reasons: tuple[str, ...]
    present_ids: tuple[str, ...]  #: self and the teammates heard from recently, sorted
    slot_angles_rad: dict[str, float]


def decide(inp: FailsafeInputs, previous_present: tuple[str, ...] | None, cfg: FailsafeConfig = FailsafeConfig()) -> FailsafeDecision:
    """The failsafe decision for this step (see the module doc). previous_present: the present set of the
    previous decision (None on the first call: no re-spacing is triggered)."""
    present = tuple(sorted({inp.self_id} | {i for i, t in inp.teammates_last_seen_s.items() if inp.t_s - t <= cfg.teammate_lost_after_s}))
    reasons: list[str] = []
    actions: list[FailsafeAction] = []
    b = inp.battery_frac
    if not np.isfinite(b):
        reasons.append("battery level unknown (NaN)")
        actions.append(FailsafeAction.RETURN)
    elif b <= cfg.battery_land_frac:
        reasons.append(f"battery critical ({b:.0%} <= {cfg.battery_land_frac:.0%})")
        actions.append(FailsafeAction.LAND)
    elif b <= cfg.battery_return_frac:
        reasons.append(f"battery low ({b:.0%} <= {cfg.battery_return_frac:.0%})")
        actions.append(FailsafeAction.RETURN)
    if inp.predicted_geofence_margin_m < cfg.min_geofence_margin_m:
        reasons.append(f"geofence breach imminent (margin {inp.predicted_geofence_margin_m:.2f} m)")
        actions.append(FailsafeAction.HOLD)
    if inp.predicted_min_separation_m < cfg.min_separation_m + cfg.min_separation_margin_m:
        reasons.append(f"separation breach imminent ({inp.predicted_min_separation_m:.2f} m)")
        actions.append(FailsafeAction.HOLD)
    if inp.consecutive_fallbacks >= cfg.max_consecutive_fallbacks:
        reasons.append(f"formation MPC fell back {inp.consecutive_fallbacks} times in a row")
        actions.append(FailsafeAction.HOLD)
    if inp.t_person_seen_s is None or inp.t_s - inp.t_person_seen_s > cfg.person_lost_after_s:
        since = "never seen" if inp.t_person_seen_s is None else f"not seen for {inp.t_s - inp.t_person_seen_s:.1f} s"
        reasons.append(f"person lost ({since})")
        actions.append(FailsafeAction.HOLD_AND_SEARCH)
    if previous_present is not None and tuple(previous_present) != present:
        lost = sorted(set(previous_present) - set(present))
        new = sorted(set(present) - set(previous_present))
        reasons.append("formation changed" + (f"; lost {lost}" if lost else "") + (f"; joined {new}" if new else ""))
        actions.append(FailsafeAction.RESPACE)
    order = [FailsafeAction.LAND, FailsafeAction.RETURN, FailsafeAction.HOLD, FailsafeAction.HOLD_AND_SEARCH, FailsafeAction.RESPACE]
    action = next((a for a in order if a in actions), FailsafeAction.CONTINUE)
    positions = {i: np.asarray(p, dtype=float) for i, p in inp.positions_ned_m.items() if i in present}
    op = inp.operator_angles_rad if inp.operator_angles_rad and set(inp.operator_angles_rad) == set(present) else None
    slots = assign_slot_angles(list(present), np.asarray(inp.person_ned_m, dtype=float), positions, op)
    return FailsafeDecision(action, tuple(reasons), present, slots)


class FormationSupervisor:
    """Stateful wrapper of :func:`decide`: remembers the present set and holds the slot angles steady
    between formation changes (so a drone's slot does not wander as positions move)."""

    def __init__(self, self_id: str, cfg: FailsafeConfig = FailsafeConfig()):
        self.self_id = self_id
        self.cfg = cfg
        self.present: tuple[str, ...] | None = None
        self.slot_angles_rad: dict[str, float] = {}

    def update(self, inp: FailsafeInputs) -> FailsafeDecision:
        d = decide(inp, self.present, self.cfg)
        if self.present is None or d.present_ids != self.present or not self.slot_angles_rad:
            self.slot_angles_rad = dict(d.slot_angles_rad)
        self.present = d.present_ids
        return dataclasses.replace(d, slot_angles_rad=dict(self.slot_angles_rad))


def person_seen_s(t_last_accepted_s: float | None, t_formation_start_s: float, acquire_grace_s: float,
                  person_lost_after_s: float) -> float:
    """The person's "last seen" time for :class:`FailsafeInputs`: the newest accepted detection; before the
    first one, the drones fly to the operator's approximate start position for ``acquire_grace_s`` before the
    person counts as lost (the clock starts so that "lost" fires ``acquire_grace_s`` after the formation's
    start)."""
    if t_last_accepted_s is not None:
        return float(t_last_accepted_s)
    return float(t_formation_start_s + acquire_grace_s - person_lost_after_s)


@dataclasses.dataclass(frozen=True)
class FailsafeResponse:
    """What the agent does with a decision: ``hold`` (brake and hold position), ``search`` (yaw to look for
    the person while holding), ``slot_angle_rad`` (this drone's slot, None if the decision lacks it) and
    ``mission_action`` ("return" / "land" through the mission's failsafe path, or None)."""

    hold: bool
    search: bool
    slot_angle_rad: float | None
    mission_action: str | None


def respond(decision: FailsafeDecision, self_id: str) -> FailsafeResponse:
    a = decision.action
    slot = decision.slot_angles_rad.get(self_id)
    mission = {FailsafeAction.RETURN: "return", FailsafeAction.LAND: "land"}.get(a)
    hold = a in (FailsafeAction.HOLD, FailsafeAction.HOLD_AND_SEARCH)
    return FailsafeResponse(hold=hold, search=a is FailsafeAction.HOLD_AND_SEARCH, slot_angle_rad=slot,
                            mission_action=mission)


class FailsafeLog:
    """Every change of the failsafe decision (its action or the set of drones present), with counters.

    ``events``: list of dicts (``t_s``, ``action``, ``reasons``, ``present``, ``slot_angle_rad``, ``source``);
    ``counts``: changes into each action (``"<source>:<action>"`` for other sources, e.g. ``"mission:land"`` for
    the agent's ground-station-loss failsafe); :meth:`note` returns the event when the decision changed (else
    None).
    """

    def __init__(self, self_id: str):
        self.self_id = self_id
        self.events: list[dict] = []
        self.counts: dict[str, int] = {}
        self._last: tuple[FailsafeAction, tuple[str, ...]] | None = None

    def note(self, t_s: float, d: FailsafeDecision) -> dict | None:
        key = (d.action, d.present_ids)
        if key == self._last:
            return None
        first = self._last is None
        self._last = key
        if first and d.action is FailsafeAction.CONTINUE:
            return None  # the normal start is not an event
        return self.add(t_s, d.action.value, d.reasons, d.present_ids, d.slot_angles_rad.get(self.self_id))

    def add(self, t_s: float, action: str, reasons, present=(), slot_angle_rad: float | None = None,
            source: str = "formation") -> dict:
        ev = {"t_s": round(float(t_s), 3), "action": str(action), "reasons": list(reasons), "present": list(present),
              "slot_angle_rad": None if slot_angle_rad is None else round(float(slot_angle_rad), 4), "source": source}
        self.events.append(ev)
        key = ev["action"] if source == "formation" else f"{source}:{ev['action']}"
        self.counts[key] = self.counts.get(key, 0) + 1
        return ev
