"""Simulated network faults on receive: a drop / delay layer that :class:`comms.transport.Transport` applies
to other drones' messages when :class:`FaultConfig` is active (simulation and fault tests only; off on real
drones), and :class:`MalformedDetectionsInjector`, a hostile publisher of malformed detections (the demo's
fault injection)."""

from __future__ import annotations

import heapq
import logging
import random
import threading
import time
from collections.abc import Callable
from dataclasses import dataclass, field
from typing import Any

from comms.errors import TransportError
from shared_msgs import encode, stamp_sent
from shared_msgs import keys as _keys
from shared_msgs.messages import BoundingBox, Detections

log = logging.getLogger(__name__)


@dataclass
class FaultConfig:
    """Simulated network faults on RECEIVE -- a chaos/simulation option for fault tests; leave it off (the
    defaults) on real drones.

    Applies to messages this node receives on **other drones'** keys (``skycap/v1/<fleet>/<drone>/<topic>``
    with ``<drone>`` not this node; ground-station, simulator and the node's own keys are never touched)
    whose topic is listed: each such message is dropped with probability ``drop_prob`` (topics
    ``drop_topics``) and delivered ``delay_s`` seconds late (topics ``delay_topics``; the
    :class:`Received` then carries the late delivery time). Counted per subscription in
    ``TopicStats.fault_dropped`` / ``fault_delayed``. ``seed`` makes the drop sequence reproducible.
    """

    drop_prob: float = 0.0
    drop_topics: list[str] = field(default_factory=lambda: [_keys.STATE, _keys.DETECTIONS, _keys.FORMATION_PLAN,
                                                            _keys.TARGET, _keys.HEALTH])
    delay_s: float = 0.0
    delay_topics: list[str] = field(default_factory=lambda: [_keys.DETECTIONS])
    seed: int = 0

    @property
    def active(self) -> bool:
        return self.drop_prob > 0.0 or self.delay_s > 0.0

    def validate(self) -> None:
        if not 0.0 <= self.drop_prob <= 1.0:
            raise TransportError(f"transport.fault.drop_prob={self.drop_prob} must be within 0..1 (0 = off)")
        if not 0.0 <= self.delay_s <= 60.0:
            raise TransportError(f"transport.fault.delay_s={self.delay_s} must be within 0..60 s (0 = off)")


class FaultInjector:
    """The receive-side fault layer of one transport (see :class:`FaultConfig`). Thread-safe.

    ``judge(key)`` -> None (drop), 0.0 (deliver now) or the delay in seconds; :meth:`later` runs a delivery
    on the injector's own timer thread (one thread, a heap of due times, started on first use).
    """

    def __init__(self, cfg: FaultConfig, node_id: str) -> None:
        self.cfg = cfg
        self.node_id = node_id
        self._rng = random.Random(cfg.seed)
        self._lock = threading.Lock()
        self._cond = threading.Condition(self._lock)
        self._heap: list[tuple[float, int, Callable[[], Any]]] = []
        self._n = 0
        self._thread: threading.Thread | None = None
        self._closed = False
        self._drop = frozenset(cfg.drop_topics)
        self._delay = frozenset(cfg.delay_topics)

    def applies(self, key: str) -> bool:
        """Whether ``key`` is another drone's key on a topic this layer drops or delays."""
        try:
            _, node, topic = _keys.parse_key(key)
        except ValueError:
            return False
        if node == self.node_id or node in (_keys.GCS, _keys.SIM):
            return False
        return (topic in self._drop and self.cfg.drop_prob > 0.0) or (topic in self._delay and self.cfg.delay_s > 0.0)

    def judge(self, key: str) -> float | None:
        """None: drop; 0.0: deliver now; > 0: deliver that many seconds late."""
        try:
            _, node, topic = _keys.parse_key(key)
        except ValueError:
            return 0.0
        if node == self.node_id or node in (_keys.GCS, _keys.SIM):
            return 0.0
        if topic in self._drop and self.cfg.drop_prob > 0.0:
            with self._lock:
                u = self._rng.random()
            if u < self.cfg.drop_prob:
                return None
        if topic in self._delay and self.cfg.delay_s > 0.0:
            return float(self.cfg.delay_s)
        return 0.0

    def later(self, delay_s: float, fn: Callable[[], Any]) -> None:
        with self._cond:
            if self._closed:
                return
            self._n += 1
            heapq.heappush(self._heap, (time.monotonic() + delay_s, self._n, fn))
            if self._thread is None:
                self._thread = threading.Thread(target=self._run, name=f"fault-delay-{self.node_id}", daemon=True)
                self._thread.start()
            self._cond.notify()

    def _run(self) -> None:
        while True:
            with self._cond:
                while not self._closed and (not self._heap or self._heap[0][0] > time.monotonic()):
                    self._cond.wait(None if not self._heap else max(0.0, self._heap[0][0] - time.monotonic()))
                if self._closed:
                    return
                _, _, fn = heapq.heappop(self._heap)
            try:
                fn()
            except Exception:  # the delivery logs its own errors; never let the timer thread die
                log.exception("%s: delayed delivery failed", self.node_id)

    def close(self) -> None:
        with self._cond:
            self._closed = True
            self._heap.clear()
            self._cond.notify_all()


class _CyclingInjector:
    """Publishes ``message(kind, t_ns)`` (subclasses: ``KINDS`` and ``message``) at ``rate_hz`` via
    ``bus.publish_raw``, cycling through the kinds and counting what went out."""

    KINDS: tuple[str, ...] = ()

    def __init__(self, bus, fleet: str, ids: list[str], rate_hz: float):
        self.bus, self.fleet, self.ids, self.period_s = bus, fleet, ids, 1.0 / rate_hz
        self.t_next = 0.0
        self.n = 0
        self.counts = {k: 0 for k in self.KINDS}

    def tick(self, now_s: float) -> None:
        if now_s < self.t_next:
            return
        self.t_next = now_s + self.period_s
        kind = self.KINDS[self.n % len(self.KINDS)]
        key, data = self.message(kind, int(now_s * 1e9))
        try:
            self.bus.publish_raw(key, data)
            self.counts[kind] += 1
        except Exception as e:
            log.warning("%s injection failed: %s", type(self).__name__, e)
        self.n += 1


class MalformedDetectionsInjector(_CyclingInjector):
    """Publishes malformed detections at ``rate_hz`` (fault injection), cycling through four kinds:

    0. a NaN box on the first drone's own detector key (``<d1>/sim/detections``): refused by the codec on receipt;
    1. an inverted box as the second drone's shared detections (``<d2>/detections``): decodes, the tracking
       stage of every other drone must ignore it;
    2. a non-rigid camera pose on ``<d1>/sim/detections``: decodes, the first drone's stage must ignore it;
    3. a NaN camera pose as ``<d2>/detections``: refused by the codec on receipt.

    With one drone, every kind goes to its own detector key.
    """

    KINDS = ("nan_box", "inverted_box", "non_rigid_pose", "nan_pose")

    def message(self, kind: str, t_ns: int):
        own, mate = self.ids[0], self.ids[1] if len(self.ids) > 1 else self.ids[0]
        key = _keys.drone_key(self.fleet, own, _keys.SIM_DETECTIONS) if kind in ("nan_box", "non_rigid_pose") or mate == own \
            else _keys.drone_key(self.fleet, mate, _keys.DETECTIONS)
        sender = own if "sim/detections" in key else mate
        T = [1.0, 0, 0, 0, 0, 1.0, 0, 0, 0, 0, 1.0, -6.0, 0, 0, 0, 1.0]
        box = dict(x_min_px=100.0, y_min_px=100.0, x_max_px=140.0, y_max_px=200.0, score=0.9)
        if kind == "nan_box":
            box["x_min_px"] = float("nan")
        elif kind == "inverted_box":
            box["x_max_px"], box["x_min_px"] = 100.0, 140.0
        elif kind == "non_rigid_pose":
            T = [2.0 * v if i in (0, 5, 10) else v for i, v in enumerate(T)]
        elif kind == "nan_pose":
            T[3] = float("nan")
        msg = Detections(header=Detections.make_header(sender, t_ns, 10_000_000 + self.n), camera_id="chaos",
                         frame_index=10_000_000 + self.n, detector="fault_injector", mode="simulated",
                         boxes=[BoundingBox(**box)], width_px=960, height_px=540, T_world_cam=tuple(T))
        return key, encode(stamp_sent(msg))  # raw bytes: the sender-side validation is bypassed on purpose



class MalformedFloodInjector(_CyclingInjector):
    """A flood of malformed messages on the keys every agent listens to, also in orbit mode (fault injection),
    at ``rate_hz``, cycling through:

    0. ``nan_state``: a VehicleState with a NaN position as the second drone's state (``<d2>/state``);
    1. ``garbage_state``: bytes that are no message at all, on ``<d2>/state``;
    2. ``nan_command``: a ground-station ``takeoff`` command with a NaN altitude (``gcs/cmd``);
    3. ``garbage_command``: garbage bytes on ``gcs/cmd``.

    Every one must be refused by the receiving transport's codec (counted in its ``TopicStats.malformed``) and
    never reach the agent. With one drone, the states go on its own key.
    """

    KINDS = ("nan_state", "garbage_state", "nan_command", "garbage_command")

    def __init__(self, bus, fleet: str, ids: list[str], rate_hz: float):
        super().__init__(bus, fleet, ids, rate_hz)
        self._rng = random.Random(1)

    def message(self, kind: str, t_ns: int) -> tuple[str, bytes]:
        from shared_msgs.messages import Command, VehicleState

        mate = self.ids[1] if len(self.ids) > 1 else self.ids[0]
        if kind in ("nan_state", "garbage_state"):
            key = _keys.drone_key(self.fleet, mate, _keys.STATE)
        else:
            key = _keys.gcs_key(self.fleet, _keys.CMD)
        if kind.startswith("garbage"):
            return key, bytes(self._rng.getrandbits(8) for _ in range(48))
        if kind == "nan_state":
            msg = VehicleState(header=VehicleState.make_header(mate, t_ns), position_ned_m=(float("nan"), 0.0, -6.0),
                               velocity_ned_m_s=(0.0, 0.0, 0.0), q_world_body=(1.0, 0.0, 0.0, 0.0))
        else:
            msg = Command(header=Command.make_header(_keys.GCS), command_id=f"chaos-{self.n}", target="*",
                          action="takeoff", params={"altitude_m": float("nan")})
        return key, encode(stamp_sent(msg))  # raw bytes: the sender-side validation is bypassed on purpose

