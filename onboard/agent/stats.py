"""The agent's flight statistics (``<drone>.s<NNN>.track.json``): tracking, formation, failsafes, network."""

from __future__ import annotations

from typing import TYPE_CHECKING, Sequence

from comms.transport import Subscription
from onboard.config import AgentConfig
from shared_msgs import keys

if TYPE_CHECKING:  # annotations only: the track-mode parts are imported when track mode is configured
    from onboard.agent.failsafes import FormationFailsafes
    from onboard.agent.formation import FormationFlight
    from onboard.agent.tracking import TrackingCapture

__all__ = ["tracking_stats", "malformed_detections", "transport_counts"]


def tracking_stats(cfg: AgentConfig, subs: Sequence[Subscription], tracking: TrackingCapture | None,
                   formation: FormationFlight | None, failsafes: FormationFailsafes | None) -> dict:
    """What the flight summary needs from an agent's tracking (written next to its recording); the track-mode
    parts are None in orbit mode (their figures are then empty)."""
    tr = tracking.stats() if tracking is not None else {
        "detections_source": cfg.track.detections, "detector": None, "offset_log": [], "counts": {},
        "filter_stats": {}}
    fm = formation.stats() if formation is not None else {
        "mpc_solve_ms": [], "mpc_fallbacks": 0, "teammate_plans_received": 0}
    return {
        "drone_id": cfg.drone_id,
        "mode": cfg.mode,
        "detections_source": tr["detections_source"],
        "detector": tr["detector"],
        **fm,
        "offset_log": tr["offset_log"],
        "counts": tr["counts"],
        "filter_stats": tr["filter_stats"],
        "failsafe_events": [] if failsafes is None else list(failsafes.log.events),
        "failsafe_counts": {} if failsafes is None else dict(failsafes.log.counts),
        "malformed_detections": malformed_detections(subs, tracking),
        "transport": transport_counts(subs),
    }


def malformed_detections(subs: Sequence[Subscription], tracking: TrackingCapture | None) -> dict:
    """Detections ignored as malformed: refused by the codec on receipt (NaN/inf, wrong array lengths,
    undecodable), refused by the tracking stage (inconsistent boxes, non-rigid pose ...), and
    non-finite measurements the filter refused; ``total`` = their sum."""
    det_topics = (keys.DETECTIONS, keys.SIM_DETECTIONS)
    det_subs = [s for s in subs if any(s.key_expr.endswith("/" + t) for t in det_topics)]
    codec = sum(int(s.stats.malformed) for s in det_subs)
    content, nonfinite = tracking.malformed_counts() if tracking is not None else (0, 0)
    return {"refused_by_codec": codec, "invalid_content": content, "nonfinite_measurements": nonfinite,
            "total": codec + content + nonfinite}


def transport_counts(subs: Sequence[Subscription]) -> dict:
    """Receive counters over all subscriptions (with the simulated fault layer's drops and delays)."""
    out = {"received": 0, "malformed": 0, "fault_judged": 0, "fault_dropped": 0, "fault_delayed": 0}
    for s in subs:
        st = s.stats
        out["received"] += int(st.received)
        out["malformed"] += int(st.malformed)
        out["fault_judged"] += int(st.fault_judged)
        out["fault_dropped"] += int(st.fault_dropped)
        out["fault_delayed"] += int(st.fault_delayed)
    return out
