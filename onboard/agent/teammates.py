"""What one drone knows of its teammates: their latest :class:`~shared_msgs.VehicleState` messages."""

from __future__ import annotations

from shared_msgs import VehicleState

__all__ = ["Teammates"]


class Teammates:
    """The other drones' latest states, kept for the separation check (``positions``, monotonic receive
    times), the formation MPC (``states``) and the formation failsafes (``seen_unix_s``, UNIX receive times)."""

    def __init__(self, self_id: str):
        self.self_id = self_id
        #: {drone_id: (position_ned_m, monotonic receive time s)} (:func:`onboard.mission.closest_neighbour`)
        self.positions: dict[str, tuple[tuple[float, float, float], float]] = {}
        #: {drone_id: latest VehicleState} (the formation MPC avoids them)
        self.states: dict[str, VehicleState] = {}
        #: {drone_id: UNIX s of the newest state's receipt} (a teammate falls silent after ``teammate_lost_after_s``)
        self.seen_unix_s: dict[str, float] = {}

    def note(self, drone_id: str, state: VehicleState, t_monotonic_s: float, t_unix_s: float) -> None:
        """A state received from ``drone_id`` (this drone's own is ignored)."""
        if drone_id == self.self_id:
            return
        self.positions[drone_id] = (state.position_ned_m, t_monotonic_s)
        self.states[drone_id] = state
        self.seen_unix_s[drone_id] = t_unix_s
