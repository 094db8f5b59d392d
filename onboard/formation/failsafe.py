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
use them (they only change when the present set changes).
"""

from __future__ import annotations

import dataclasses
import enum

import numpy as np

from onboard.formation.slots import assign_slot_angles

__all__ = ["FailsafeAction", "FailsafeConfig", "FailsafeInputs", "FailsafeDecision", "decide", "FormationSupervisor"]


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
    over the current plan (inf if not applicable); positions_ned_m: known positions (for slot assignment).
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
    slots = assign_slot_angles(list(present), np.asarray(inp.person_ned_m, dtype=float), positions, inp.operator_angles_rad)
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
