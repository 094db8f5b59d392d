"""Thin adapter over Zenoh (eclipse-zenoh 1.x) that speaks skycap messages.

    from comms.transport import Transport, TransportConfig
    from shared_msgs import keys, VehicleState

    with Transport.open(TransportConfig(), node_id="drone_1") as bus:      # peer, connects to the rendezvous
        bus.declare_alive(keys.alive_key("f1", "drone_1"))                  # presence for the others
        bus.subscribe(keys.gcs_key("f1", keys.CMD), on_cmd, expected_type=Command)
        bus.watch_presence(keys.all_drones_key("f1", "alive"), on_join=print, on_leave=print)
        data = bus.publish(keys.drone_key("f1", "drone_1", keys.STATE), state)  # stamps t_sent_ns + seq

Default topology for N processes on one machine (the built-in simulation and the demo launcher)
---------------------------------------------------------------------------------------------------
Router-less, no ``zenohd``: every process is a Zenoh **peer** with multicast scouting **off**.

* One process -- the simulator / demo launcher -- opens the *rendezvous* peer, listening on
  ``tcp/127.0.0.1:7447`` (:meth:`TransportConfig.rendezvous`).
* Every other process (agents, ground station, tools) opens a peer that listens on an ephemeral
  loopback port (``tcp/127.0.0.1:0``) and connects to the rendezvous (:class:`TransportConfig` defaults).
  Zenoh's gossip scouting then tells the peers about each other and they build a full mesh, so traffic
  goes peer to peer and keeps flowing if the rendezvous process exits.
* A peer started before the rendezvous opens anyway and keeps retrying the connection in the background
  (Zenoh's default for peers), so start order does not matter.

On real drones, set ``listen``/``connect`` to the radio network's addresses (or ``mode = "client"`` with
``connect`` = a router) from the config file; the code does not change. Tests always use explicit
``tcp/127.0.0.1:<free port>`` endpoints with multicast scouting off (``tests/helpers/ports.py``).

Threading
---------
Zenoh delivers samples on its own threads. Subscriber callbacks run there: keep them short (append to a
queue, set a value). Malformed, wrong-version or wrong-type payloads are logged (rate-limited) and counted
in :meth:`Transport.stats`, never raised into Zenoh's thread; an exception raised by a user callback is
logged with its traceback and counted too. For asyncio code use :meth:`Transport.subscribe_async` (an
async iterator fed with ``loop.call_soon_threadsafe``) or wrap a callback with :func:`deliver_to_loop`.
:meth:`Transport.publish` may be called from any thread.
"""

from __future__ import annotations

import asyncio
import atexit
import dataclasses
import json
import logging
import socket
import threading
import weakref
from collections.abc import Callable
from dataclasses import dataclass, field
from typing import Any, Generic, Literal, TypeVar

import zenoh

from shared_msgs import keys as _keys
from shared_msgs.codec import MessageError, decode, encode, stamp_sent, validate
from shared_msgs.messages import Message, now_ns
from comms.errors import TransportError
from comms.faults import FaultConfig, FaultInjector
from comms.security import FleetKeys, SecurityConfig, acl_config, tls_config

__all__ = [
    "DEFAULT_RENDEZVOUS",
    "TransportConfig",
    "SecurityConfig",
    "FaultConfig",
    "TransportError",
    "Transport",
    "Received",
    "Subscription",
    "AsyncSubscription",
    "TopicStats",
    "deliver_to_loop",
]

log = logging.getLogger(__name__)

DEFAULT_RENDEZVOUS = "tcp/127.0.0.1:7447"
"""The well-known endpoint of the local rendezvous peer (opened by the simulator / demo launcher)."""

M = TypeVar("M", bound=Message)

# Topics whose messages must not be dropped under congestion (Zenoh blocks the publisher instead).
_BLOCKING_TOPICS = frozenset({_keys.CMD, _keys.ACK, _keys.PLAN})
# Topics sent with low priority so they never delay control traffic.
_LOW_PRIORITY_TOPICS = frozenset({_keys.CAMERA_IMAGE})

_MSGPACK_ENCODING = "application/msgpack;skycap"


@dataclass
class TransportConfig:
    """How to join the Zenoh network (loads from TOML as part of any job's config).

    ``mode``: ``"peer"`` (default, router-less) or ``"client"`` (talk only through the router(s) in
    ``connect``). ``listen``/``connect``: Zenoh endpoints such as ``tcp/127.0.0.1:7447``; port 0 picks a
    free port. ``multicast_scouting``: UDP multicast discovery on the LAN (off by default: explicit
    endpoints only). ``gossip_scouting``: peers tell each other about peers they know (needed for the
    full mesh behind one rendezvous). ``zenoh_json5``: extra raw Zenoh settings, key -> JSON5 value
    (e.g. ``{"transport/unicast/max_links" = "2"}``), applied last. ``fault``: simulated receive-side
    drops and delays for fault tests (:class:`FaultConfig`; off by default). ``security``: mutual TLS and
    access control from a fleet folder (:class:`comms.security.SecurityConfig`); with it every endpoint must
    be ``tls/...`` (``quic/...`` also works); without it the session is plaintext and open to anyone on the
    network, which is logged as a warning.
    """

    mode: Literal["peer", "client"] = "peer"
    listen: list[str] = field(default_factory=lambda: ["tcp/127.0.0.1:0"])
    connect: list[str] = field(default_factory=lambda: [DEFAULT_RENDEZVOUS])
    multicast_scouting: bool = False
    gossip_scouting: bool = True
    zenoh_json5: dict[str, str] = field(default_factory=dict)
    fault: FaultConfig = field(default_factory=FaultConfig)
    security: SecurityConfig = field(default_factory=SecurityConfig)

    @classmethod
    def rendezvous(cls, endpoint: str = DEFAULT_RENDEZVOUS, keys_dir: str = "") -> TransportConfig:
        """The peer the others connect to: listens on ``endpoint``, connects to nobody."""
        return cls(listen=[endpoint], connect=[], security=SecurityConfig(keys_dir=str(keys_dir or "")))

    @classmethod
    def local_peer(cls, rendezvous: str = DEFAULT_RENDEZVOUS, keys_dir: str = "") -> TransportConfig:
        """A peer on an ephemeral loopback port (same protocol as ``rendezvous``, e.g. ``tls``) that joins it;
        ``keys_dir``: the fleet folder for mutual TLS and access control (empty: insecure)."""
        proto = str(rendezvous).partition("/")[0] or "tcp"
        return cls(listen=[f"{proto}/127.0.0.1:0"], connect=[rendezvous],
                   security=SecurityConfig(keys_dir=str(keys_dir or "")))

    def validate(self) -> None:
        """Raise :class:`TransportError` naming the bad field."""
        self.fault.validate()
        if self.security.enabled:
            for name in ("listen", "connect"):
                for ep in getattr(self, name):
                    if str(ep).partition("/")[0] not in ("tls", "quic"):
                        raise TransportError(
                            f"transport.{name} endpoint {ep!r} is plaintext while transport.security.keys_dir is set; "
                            f"write it as tls/{str(ep).partition('/')[2]} (every link is mutual TLS)")
        if self.mode not in ("peer", "client"):
            raise TransportError(f"transport.mode {self.mode!r} must be 'peer' or 'client'")
        for name in ("listen", "connect"):
            for ep in getattr(self, name):
                proto, sep, addr = str(ep).partition("/")
                if not sep or not proto or not addr:
                    raise TransportError(
                        f"transport.{name} endpoint {ep!r} is not a Zenoh endpoint; write it like tcp/127.0.0.1:7447"
                    )
        if self.mode == "client" and not self.connect:
            raise TransportError("transport.mode 'client' needs at least one transport.connect endpoint (a router)")
        if not self.listen and not self.connect and not self.multicast_scouting:
            raise TransportError(
                "transport has no listen endpoint, no connect endpoint and no multicast scouting: it could never "
                "meet anyone; set transport.connect (e.g. ['tcp/127.0.0.1:7447']) or transport.listen"
            )

    def to_zenoh(self, identity: str = "") -> zenoh.Config:
        """The equivalent :class:`zenoh.Config`; with security, TLS and ACL for ``security.identity`` (default:
        ``identity``). Raises :class:`comms.security.SecurityError` for an unusable certificate."""
        self.validate()
        cfg = zenoh.Config()
        if self.security.enabled:
            fleet_keys = FleetKeys.load(self.security.keys_dir)
            identity = self.security.identity or identity
            fleet_keys.check(identity)
            cfg.insert_json5("transport/link/tls", json.dumps(tls_config(fleet_keys, identity,
                                                                         self.security.verify_name)))
            cfg.insert_json5("access_control", json.dumps(acl_config(fleet_keys)))
        cfg.insert_json5("mode", json.dumps(self.mode))
        cfg.insert_json5("listen/endpoints", json.dumps(list(self.listen)))
        cfg.insert_json5("connect/endpoints", json.dumps(list(self.connect)))
        cfg.insert_json5("scouting/multicast/enabled", json.dumps(bool(self.multicast_scouting)))
        cfg.insert_json5("scouting/gossip/enabled", json.dumps(bool(self.gossip_scouting)))
        for k, v in self.zenoh_json5.items():
            try:
                cfg.insert_json5(k, v)
            except Exception as e:  # zenoh.ZError
                raise TransportError(f"transport.zenoh_json5[{k!r}] = {v!r} is refused by Zenoh: {e}") from None
        return cfg


def local_peer_overrides(connect: str | None, keys_dir: str | None) -> dict[str, Any]:
    """Config overrides (``transport.*``) of a command's ``--zenoh-connect`` / ``--zenoh-keys``: join that
    rendezvous as a local peer (listen on an ephemeral loopback port in its protocol), with that fleet folder.
    Unset options leave the config file's values alone."""
    out: dict[str, Any] = {}
    if connect:
        out["transport.connect"] = [connect]
        out["transport.listen"] = [f"{connect.partition('/')[0]}/127.0.0.1:0"]
    if keys_dir:
        out["transport.security.keys_dir"] = str(keys_dir)
    return out


@dataclass(slots=True)
class Received(Generic[M]):
    """One decoded message as delivered to a subscriber callback.

    ``key``: the concrete key expression it was published on; ``msg``: the decoded message; ``data``: the
    exact bytes received (hand them to the recorder as they are); ``t_received_ns``: wall-clock receive
    time (ns since the UNIX epoch, same base as ``header.t_sent_ns``).
    """

    key: str
    msg: M
    data: bytes
    t_received_ns: int

    @property
    def latency_ns(self) -> int:
        """Receive time minus the sender's ``t_sent_ns`` (includes clock offset between machines)."""
        return self.t_received_ns - self.msg.header.t_sent_ns


@dataclass
class TopicStats:
    """Counters of one subscription (a key expression)."""

    received: int = 0  #: decoded and handed to the callback
    malformed: int = 0  #: refused by the codec (malformed, unknown type, wrong version, wrong type, NaN)
    forged: int = 0  #: refused: ``header.sender_id`` is not the node whose key the message came on
    callback_errors: int = 0  #: the user callback raised
    dropped: int = 0  #: async queue full: oldest message dropped
    fault_judged: int = 0  #: other drones' messages the simulated fault layer applied to (:class:`FaultConfig`)
    fault_dropped: int = 0  #: dropped by the simulated fault layer
    fault_delayed: int = 0  #: delivered late by the simulated fault layer
    last_error: str = ""


class Subscription:
    """Handle of a subscriber (data or liveliness); :meth:`close` stops delivery. Counters in ``stats``."""

    def __init__(self, transport: Transport, key_expr: str, stats: TopicStats) -> None:
        self.key_expr = key_expr
        self.stats = stats
        self._transport = transport
        self._zenoh_sub: Any = None
        self._closed = False
        self._on_close: list[Callable[[], Any]] = []

    def close(self) -> None:
        if self._closed:
            return
        self._closed = True
        self._transport._forget(self)
        if self._zenoh_sub is not None:
            _quiet(self._zenoh_sub.undeclare)  # may fail when the session is already closed
        self._closed_hooks()

    def _closed_hooks(self) -> None:
        for fn in self._on_close:
            _quiet(fn)

    @property
    def closed(self) -> bool:
        return self._closed


class AsyncSubscription(Generic[M]):
    """Async iterator of :class:`Received` fed from Zenoh's thread via ``loop.call_soon_threadsafe``.

        async for rx in bus.subscribe_async(key, VehicleState):
            ...

    A bounded queue (``maxsize``): when the consumer falls behind, the oldest message is dropped and
    counted in ``stats.dropped`` (fresh data matters more than complete data for telemetry).
    """

    _END = object()

    def __init__(self, sub: Subscription, queue: asyncio.Queue, loop: asyncio.AbstractEventLoop) -> None:
        self.subscription = sub
        self.stats = sub.stats
        self._queue = queue
        self._loop = loop
        self._ended = False
        sub._on_close.append(self._end)

    def _end(self) -> None:  # any thread: wake a waiting consumer with the end marker
        deliver_to_loop(self._loop, self._put_end)()

    def _put_end(self) -> None:
        if self._queue.full():
            try:
                self._queue.get_nowait()
            except asyncio.QueueEmpty:
                pass
        self._queue.put_nowait(self._END)

    def __aiter__(self) -> AsyncSubscription[M]:
        return self

    async def __anext__(self) -> Received[M]:
        """Next message; the iteration ends after :meth:`close` or :meth:`Transport.close`."""
        if self._ended:
            raise StopAsyncIteration
        item = await self._queue.get()
        if item is self._END:
            self._ended = True
            raise StopAsyncIteration
        return item

    async def get(self, timeout_s: float | None = None) -> Received[M]:
        """Next message; ``asyncio.TimeoutError`` after ``timeout_s``; :class:`TransportError` once closed."""
        if self._ended:
            raise TransportError(f"subscription to {self.subscription.key_expr!r} is closed")
        item = await asyncio.wait_for(self._queue.get(), timeout_s)
        if item is self._END:
            self._ended = True
            raise TransportError(f"subscription to {self.subscription.key_expr!r} is closed")
        return item

    def get_nowait(self) -> Received[M] | None:
        """A waiting message, or None."""
        try:
            item = self._queue.get_nowait()
        except asyncio.QueueEmpty:
            return None
        if item is self._END:
            self._ended = True
            return None
        return item

    def close(self) -> None:
        self.subscription.close()


def deliver_to_loop(loop: asyncio.AbstractEventLoop, callback: Callable[..., Any]) -> Callable[..., None]:
    """Wrap ``callback`` so that calling the wrapper from any thread runs ``callback`` on ``loop``.

    Calls after the loop was closed are dropped silently (shutdown).
    """

    def wrapper(*args: Any) -> None:
        try:
            loop.call_soon_threadsafe(callback, *args)
        except RuntimeError:  # loop closed
            pass

    return wrapper


class _RateLimitedLog:
    """Log the first ``first`` events per key, then every ``every``-th."""

    def __init__(self, first: int = 5, every: int = 100) -> None:
        self.first, self.every = first, every

    def should_log(self, count: int) -> bool:
        return count <= self.first or count % self.every == 0


_OPEN_TRANSPORTS: weakref.WeakSet = weakref.WeakSet()


def _close_open_transports() -> None:
    """Close transports left open at interpreter exit. zenoh-python 1.x runs each callback subscriber in a
    non-daemon Python thread ("pyo3-closure") that only ends when the subscriber is undeclared, so an
    unclosed transport would make the interpreter wait forever at exit. ``threading._register_atexit``
    hooks run before the interpreter joins non-daemon threads (plain ``atexit`` runs after: too late)."""
    for t in list(_OPEN_TRANSPORTS):
        _quiet(t.close)


try:
    threading._register_atexit(_close_open_transports)  # type: ignore[attr-defined]
except (AttributeError, RuntimeError):  # other Pythons: best effort
    atexit.register(_close_open_transports)


class Transport:
    """A Zenoh session that publishes and subscribes skycap messages. Open with :meth:`open`.

    Use as a context manager or call :meth:`close` (transports still open at interpreter exit are closed by
    an ``atexit`` hook). All methods are thread-safe.
    """

    def __init__(self, session: zenoh.Session, config: TransportConfig, node_id: str, identity: str = "") -> None:
        self._session = session
        self.config = config
        self.node_id = node_id
        self._identity = (config.security.identity or identity or node_id) if config.security.enabled else ""
        self._lock = threading.Lock()
        self._publishers: dict[str, Any] = {}
        self._seq: dict[str, int] = {}
        self._subs: list[Subscription] = []
        self._tokens: list[Any] = []
        self._latched: dict[str, bytes] = {}
        self._queryables: dict[str, Any] = {}
        self._stats: dict[str, TopicStats] = {}
        self._closed = False
        self._logrl = _RateLimitedLog()
        self._fault: FaultInjector | None = None
        if config.fault.active:
            self._fault = FaultInjector(config.fault, node_id)
            log.warning("%s: SIMULATED NETWORK FAULTS on receive: drop %.0f%% of %s from other drones, delay %s by "
                        "%.0f ms", node_id, 100 * config.fault.drop_prob, config.fault.drop_topics,
                        config.fault.delay_topics, 1e3 * config.fault.delay_s)

    # ----------------------------------------------------------------------------------------- life
    @classmethod
    def open(cls, config: TransportConfig | None = None, node_id: str = "node", identity: str = "") -> Transport:
        """Open a Zenoh session from ``config`` (defaults: local peer joining the rendezvous).

        ``node_id`` is used in logs and errors (messages carry their own ``header.sender_id``). ``identity``:
        the certificate a secure session presents when ``config.security.identity`` is empty (default:
        ``node_id``; e.g. a drone's camera service presents its drone's). Raises :class:`TransportError` (e.g. a
        listen port already in use) or :class:`comms.security.SecurityError` (an unusable certificate).
        """
        config = config or TransportConfig()
        zcfg = config.to_zenoh(config.security.identity or identity or node_id)
        try:
            session = zenoh.open(zcfg)
        except Exception as e:  # zenoh.ZError
            raise TransportError(
                f"{node_id}: cannot open the Zenoh session (mode={config.mode}, listen={config.listen}, "
                f"connect={config.connect}): {e}. If a listen port is in use, another process already listens "
                f"there (a second rendezvous?): pick another port or join it via transport.connect"
            ) from None
        t = cls(session, config, node_id, identity)
        _OPEN_TRANSPORTS.add(t)
        log.info("%s: zenoh %s session %s open (listen=%s, connect=%s, multicast=%s)", node_id, config.mode,
                 session.zid(), config.listen, config.connect, config.multicast_scouting)
        if config.security.enabled:
            log.info("%s: secure transport: mutual TLS as %r (fleet CA %s), Zenoh access control on", node_id,
                     t.identity, config.security.keys_dir)
        else:
            log.warning("%s: INSECURE transport: plaintext, no authentication, no access control -- anyone on the "
                        "network can read everything and command the fleet (set transport.security.keys_dir; "
                        "see `skycap keys`)", node_id)
        return t

    @property
    def secure(self) -> bool:
        """Whether this session runs mutual TLS with the fleet's access control."""
        return self.config.security.enabled

    @property
    def identity(self) -> str:
        """The certificate identity this session presents (its node id unless configured), '' when insecure."""
        return self._identity

    def close(self) -> None:
        """Undeclare everything and close the session (idempotent). Liveliness tokens vanish: others see a leave."""
        with self._lock:
            if self._closed:
                return
            self._closed = True
            subs, self._subs = list(self._subs), []
            tokens, self._tokens = list(self._tokens), []
            pubs, self._publishers = list(self._publishers.values()), {}
            qs, self._queryables = list(self._queryables.values()), {}
        if self._fault is not None:
            self._fault.close()
        for s in subs:
            s._closed = True
            if s._zenoh_sub is not None:
                _quiet(s._zenoh_sub.undeclare)
            s._closed_hooks()
        for obj in [*tokens, *pubs, *qs]:
            _quiet(obj.undeclare)
        _quiet(self._session.close)
        log.info("%s: zenoh session closed", self.node_id)

    @property
    def closed(self) -> bool:
        return self._closed

    def __enter__(self) -> Transport:
        return self

    def __exit__(self, *exc: Any) -> None:
        self.close()

    def zid(self) -> str:
        """This session's Zenoh id."""
        return str(self._session.zid())

    def peers(self) -> list[str]:
        """Zenoh ids of the peers this session is connected to right now."""
        return [str(z) for z in self._session.info.peers_zid()]

    def _check_open(self) -> None:
        if self._closed:
            raise TransportError(f"{self.node_id}: transport is closed; open a new one with Transport.open()")

    def _forget(self, sub: Subscription) -> None:
        with self._lock:
            if sub in self._subs:
                self._subs.remove(sub)

    # -------------------------------------------------------------------------------------- publish
    def _publisher(self, key: str) -> Any:
        pub = self._publishers.get(key)
        if pub is None:
            try:
                topic = _keys.parse_key(key)[2]
            except ValueError:
                topic = ""
            cc = zenoh.CongestionControl.BLOCK if topic in _BLOCKING_TOPICS else zenoh.CongestionControl.DROP
            prio = zenoh.Priority.DATA_LOW if topic in _LOW_PRIORITY_TOPICS else zenoh.Priority.DATA
            try:
                pub = self._session.declare_publisher(
                    key, encoding=zenoh.Encoding(_MSGPACK_ENCODING), congestion_control=cc, priority=prio
                )
            except Exception as e:
                raise TransportError(f"{self.node_id}: cannot publish on {key!r}: {e}") from None
            self._publishers[key] = pub
        return pub

    def publish(self, key: str, msg: Message, *, latch: bool = False) -> bytes:
        """Stamp, encode and publish ``msg`` on ``key``; returns the bytes sent (record them as they are).

        Sets ``msg.header.t_sent_ns`` (now) and ``msg.header.seq`` (per-key counter from 1) **in place**.
        ``latch=True`` also keeps these bytes as the key's latest value, served to :meth:`query_latest`
        (use it for plans and camera info). Raises :class:`shared_msgs.MessageError` for a message that
        receivers would refuse (NaN, wrong array length, wrong schema version). Commands, acks and plans are never dropped under congestion
        (Zenoh blocks instead); camera images go with low priority.
        """
        if not isinstance(msg, Message):
            raise TypeError(f"publish() takes a skycap message, got {type(msg).__name__}")
        with self._lock:
            self._check_open()
            seq = self._seq.get(key, 0) + 1
            self._seq[key] = seq
            pub = self._publisher(key)
        msg.header.seq = seq
        stamp_sent(msg)
        validate(msg)  # a message receivers would refuse fails here, in the sender, with the reason
        data = encode(msg)
        self._put(pub, key, data)
        if latch:
            self._latch(key, data)
        return data

    def publish_raw(self, key: str, data: bytes) -> None:
        """Publish bytes as they are (forwarding recorded data; tests of malformed input)."""
        with self._lock:
            self._check_open()
            pub = self._publisher(key)
        self._put(pub, key, bytes(data))

    def _put(self, pub: Any, key: str, data: bytes) -> None:
        try:
            pub.put(data)
        except Exception as e:
            if self._closed:
                raise TransportError(f"{self.node_id}: transport closed while publishing on {key!r}") from None
            raise TransportError(f"{self.node_id}: publishing on {key!r} failed: {e}") from None

    # ------------------------------------------------------------------------------------ subscribe
    def subscribe(
        self,
        key_expr: str,
        callback: Callable[[Received], Any],
        expected_type: type[M] | None = None,
    ) -> Subscription:
        """Call ``callback(Received)`` for every valid message on ``key_expr`` (wildcards allowed).

        Runs on a Zenoh thread. Input that fails :func:`shared_msgs.codec.decode` (malformed, unknown
        type, wrong schema version, not ``expected_type``, NaN) is logged and counted in
        ``Subscription.stats.malformed``; exceptions from ``callback`` are logged and counted in
        ``stats.callback_errors``. Neither ever reaches Zenoh or stops the subscription.
        """
        with self._lock:
            self._check_open()
            stats = TopicStats()
            self._stats[f"{key_expr}#{len(self._stats)}"] = stats
            sub = Subscription(self, key_expr, stats)
            self._subs.append(sub)
        where = f"{key_expr} (node {self.node_id})"

        def on_sample(sample: zenoh.Sample) -> None:
            if sub._closed:
                return
            t_rx = now_ns()
            key = str(sample.key_expr)
            try:
                data = sample.payload.to_bytes()
                msg = decode(data, expected_type, source=key)
            except MessageError as e:
                stats.malformed += 1
                stats.last_error = str(e)
                if self._logrl.should_log(stats.malformed):
                    log.warning("%s: dropped input #%d: %s", where, stats.malformed, e)
                return
            except Exception as e:  # never raise into zenoh's thread
                stats.malformed += 1
                stats.last_error = f"{type(e).__name__}: {e}"
                if self._logrl.should_log(stats.malformed):
                    log.warning("%s: dropped input #%d: %s", where, stats.malformed, stats.last_error)
                return
            node = _key_node(key)
            if node is not None and msg.header.sender_id != node:
                stats.forged += 1
                stats.last_error = (f"sender_id {msg.header.sender_id!r} on {key} (a key of node {node!r}): "
                                    f"a claimed sender must be the node whose keys it publishes under")
                if self._logrl.should_log(stats.forged):
                    log.warning("%s: refused forged message #%d: %s", where, stats.forged, stats.last_error)
                return
            fault = self._fault
            if fault is not None and fault.applies(key):
                stats.fault_judged += 1
                delay_s = fault.judge(key)
                if delay_s is None:
                    stats.fault_dropped += 1
                    return
                if delay_s > 0.0:
                    stats.fault_delayed += 1
                    fault.later(delay_s, lambda: deliver(Received(key, msg, data, now_ns())))
                    return
            deliver(Received(key, msg, data, t_rx))

        def deliver(rx: Received) -> None:
            if sub._closed:
                return
            stats.received += 1
            try:
                callback(rx)
            except Exception as e:
                stats.callback_errors += 1
                stats.last_error = f"callback raised {type(e).__name__}: {e}"
                if self._logrl.should_log(stats.callback_errors):
                    log.exception("%s: subscriber callback raised (#%d)", where, stats.callback_errors)

        try:
            sub._zenoh_sub = self._session.declare_subscriber(key_expr, on_sample)
        except Exception as e:
            self._forget(sub)
            raise TransportError(f"{self.node_id}: cannot subscribe to {key_expr!r}: {e}") from None
        return sub

    def subscribe_async(
        self,
        key_expr: str,
        expected_type: type[M] | None = None,
        *,
        maxsize: int = 256,
        loop: asyncio.AbstractEventLoop | None = None,
    ) -> AsyncSubscription[M]:
        """Like :meth:`subscribe` but returns an async iterator of :class:`Received` on ``loop``.

        Call from inside the running loop (or pass ``loop``). When more than ``maxsize`` messages wait,
        the oldest is dropped (counted in ``stats.dropped``).
        """
        loop = loop or asyncio.get_running_loop()
        queue: asyncio.Queue = asyncio.Queue(maxsize=maxsize)
        holder: dict[str, Subscription] = {}

        def put(rx: Received) -> None:  # runs on the loop
            sub_ = holder.get("sub")  # None only for a message racing the declaration
            if sub_ is not None and sub_.closed:
                return
            if queue.full():
                try:
                    queue.get_nowait()
                except asyncio.QueueEmpty:
                    pass
                if sub_ is not None:
                    sub_.stats.dropped += 1
            queue.put_nowait(rx)

        sub = self.subscribe(key_expr, deliver_to_loop(loop, put), expected_type)
        holder["sub"] = sub
        return AsyncSubscription(sub, queue, loop)

    # ------------------------------------------------------------------------------------- presence
    def declare_alive(self, key: str) -> Any:
        """Declare a liveliness token on ``key`` (use ``keys.alive_key(fleet, node)``); it lives until
        :meth:`close` (or ``token.undeclare()``) or until this process dies -- others then see a leave."""
        with self._lock:
            self._check_open()
            try:
                tok = self._session.liveliness().declare_token(key)
            except Exception as e:
                raise TransportError(f"{self.node_id}: cannot declare liveliness token {key!r}: {e}") from None
            self._tokens.append(tok)
            return tok

    def watch_presence(
        self,
        key_expr: str,
        on_join: Callable[[str], Any] | None = None,
        on_leave: Callable[[str], Any] | None = None,
        *,
        history: bool = True,
    ) -> Subscription:
        """Call ``on_join(key)`` / ``on_leave(key)`` when a liveliness token matching ``key_expr`` appears /
        disappears (``keys.all_drones_key(fleet, "alive")`` watches every node). With ``history`` the
        tokens already present are reported as joins at once. Runs on a Zenoh thread; exceptions are
        logged and counted like :meth:`subscribe`'s."""
        with self._lock:
            self._check_open()
            stats = TopicStats()
            self._stats[f"{key_expr}#alive#{len(self._stats)}"] = stats
            sub = Subscription(self, key_expr, stats)
            self._subs.append(sub)

        def on_sample(sample: zenoh.Sample) -> None:
            if sub._closed:
                return
            key = str(sample.key_expr)
            cb = on_join if sample.kind == zenoh.SampleKind.PUT else on_leave
            stats.received += 1
            if cb is None:
                return
            try:
                cb(key)
            except Exception as e:
                stats.callback_errors += 1
                stats.last_error = f"presence callback raised {type(e).__name__}: {e}"
                log.exception("%s: presence callback raised", key_expr)

        try:
            sub._zenoh_sub = self._session.liveliness().declare_subscriber(key_expr, on_sample, history=history)
        except Exception as e:
            self._forget(sub)
            raise TransportError(f"{self.node_id}: cannot watch liveliness on {key_expr!r}: {e}") from None
        return sub

    def alive(self, key_expr: str, timeout_s: float = 1.0) -> list[str]:
        """Keys of the liveliness tokens matching ``key_expr`` present now (sorted)."""
        self._check_open()
        out = set()
        for reply in self._session.liveliness().get(key_expr, timeout=timeout_s):
            if reply.ok is not None:
                out.add(str(reply.ok.key_expr))
        return sorted(out)

    # ------------------------------------------------------------------------ latest value (queries)
    def _latch(self, key: str, data: bytes) -> None:
        with self._lock:
            self._latched[key] = data
            if key in self._queryables or self._closed:
                return

            def on_query(query: zenoh.Query) -> None:
                with self._lock:
                    payload = self._latched.get(key)
                if payload is not None:
                    try:
                        query.reply(key, payload, encoding=zenoh.Encoding(_MSGPACK_ENCODING))
                    except Exception as e:
                        log.warning("%s: replying to a query on %s failed: %s", self.node_id, key, e)

            try:
                self._queryables[key] = self._session.declare_queryable(key, on_query)
            except Exception as e:
                raise TransportError(f"{self.node_id}: cannot serve latest value of {key!r}: {e}") from None

    def query_latest(
        self, key_expr: str, expected_type: type[M] | None = None, timeout_s: float = 1.0
    ) -> list[Received[M]]:
        """Ask the network for the latest latched value(s) on ``key_expr`` (see ``publish(latch=True)``).

        Returns one :class:`Received` per answering publisher (empty when nobody answers within
        ``timeout_s``). Invalid replies are logged and skipped.
        """
        self._check_open()
        out: list[Received[M]] = []
        try:
            replies = self._session.get(key_expr, timeout=timeout_s)
        except Exception as e:
            raise TransportError(f"{self.node_id}: query on {key_expr!r} failed: {e}") from None
        for reply in replies:
            sample = reply.ok
            if sample is None:
                continue
            key = str(sample.key_expr)
            data = sample.payload.to_bytes()
            try:
                msg = decode(data, expected_type, source=key)
            except MessageError as e:
                log.warning("%s: ignored reply to query %s: %s", self.node_id, key_expr, e)
                continue
            out.append(Received(key, msg, data, now_ns()))
        return out

    # ---------------------------------------------------------------------------------------- stats
    def stats(self) -> dict[str, dict[str, Any]]:
        """Counters per subscription (``"<key_expr>#<n>"`` -> TopicStats as dict) and published seq per key."""
        with self._lock:
            out = {k: dataclasses.asdict(v) for k, v in self._stats.items()}
            out["published"] = dict(self._seq)
        return out


def _key_node(key: str) -> str | None:
    """The node segment of a skycap key (whose certificate alone may publish there), None for other keys."""
    try:
        return _keys.parse_key(key)[1]
    except ValueError:
        return None


def _quiet(fn: Callable[[], Any]) -> None:
    try:
        fn()
    except Exception:
        pass
