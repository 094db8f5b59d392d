"""The flight recorder: one MCAP file per drone (and one for simulator ground truth), crash-tolerant.

    from flightdata.recorder import Recorder, channel_name

    with Recorder.new_sortie(flight_dir, "drone_1") as rec:    # drone_1.s<next>.mcap, never an existing file
        rec.record_received("cmd", rx)                       # a transport.Received: bytes as received
        data = bus.publish(key, state); rec.record("state", data)   # what we sent, bytes as sent
        rec.record_message("health", health_msg)             # encode here

File layout (readable by the standard MCAP tools and :mod:`flightdata.flightlog`):

* profile ``"skycap"``; one **channel per topic** (``state``, ``camera/image``, ``camera_info``, ``cmd``,
  ``ack``, ``plan``, ``sim/keypoints2d``, ``detections``, ``keypoints2d``, ``health``, ``target``, ``truth``
  ...; :func:`channel_name` turns a Zenoh key into one: the node's own topics by their short name, other
  nodes' as ``<node>/<topic>``, e.g. ``gcs/cmd``, ``drone_2/detections``);
* message encoding ``"msgpack"`` (the bytes of :func:`shared_msgs.codec.encode`, unchanged);
* one schema per message type: name ``skycap.<type>.v<version>``, encoding ``"jsonschema"``, data the
  JSON Schema of the message (:func:`msgspec.json.schema`; it describes the fields -- ``bytes`` fields are
  MessagePack bin, not base64 strings, in the file);
* ``log_time`` = receive (or recording) time, ``publish_time`` = ``header.t_sent_ns``, ``sequence`` =
  ``header.seq``; all ns since the UNIX epoch.

Crash tolerance: callers only put bytes on a queue (never blocked by disk); a writer thread adds them to the
current MCAP chunk and, every ``flush_interval_s`` (default 0.5 s), closes the chunk, flushes and
``os.fsync``\\ s the file. A ``kill -9`` or power loss therefore loses at most the last
``flush_interval_s`` plus the fsync time; the file then lacks its summary and footer:
:func:`flightdata.flightlog.read_messages` reads such a file as it is, and :func:`flightdata.flightlog.recover`
(or the Go CLI's ``mcap recover in.mcap -o out.mcap``) rewrites it into a finalised one.
On :meth:`Recorder.close` the queue is drained and the summary (statistics, chunk and message indexes)
and footer are written; recorders still open when the interpreter exits normally are closed then.

If the queue holds more than ``max_queue_bytes`` (the disk cannot keep up), new messages are dropped and
counted (``stats()["dropped"]``), never blocking the flight code. If the writer thread fails (disk full,
I/O error), :meth:`Recorder.record` raises :class:`RecorderError` naming the file and the cause; what was
flushed before stays readable (the file then lacks its summary, as after a crash).

Fault injection (simulation and fault tests only): :func:`simulate_disk_full` makes a folder's disk "full":
from then on every recorder writing there fails its next write with ``OSError(ENOSPC)`` *before* writing
anything of it (a real full disk may leave a torn last record, which the reader also skips), and no new
recording can be created there. :meth:`Recorder.inject_writer_failure` kills a recorder's writer thread with
an injected error, as a crash of it would (what it had not flushed is lost).
"""

from __future__ import annotations

import errno
import json
import logging
import os
import queue
import threading
import time
import weakref
from dataclasses import dataclass
from pathlib import Path
from typing import Any

import msgspec
from mcap.writer import CompressionType, Writer

from shared_msgs import keys as _keys
from shared_msgs.codec import TYPE_BY_TAG, encode
from shared_msgs.messages import Header, Message, now_ns
from flightdata.flightlog import PROFILE
from flightdata.folder import FlightFolder
from skycap.errors import SkycapError

__all__ = [
    "Recorder",
    "simulate_disk_full",
    "RecorderError",
    "MESSAGE_ENCODING",
    "PROFILE",
    "channel_name",
    "schema_name",
]

log = logging.getLogger(__name__)

MESSAGE_ENCODING = "msgpack"
SCHEMA_ENCODING = "jsonschema"


class RecorderError(SkycapError):
    """The flight recorder cannot write its file (bad path, disk full, closed recorder)."""


def channel_name(key: str, own_node: str) -> str:
    """Recorder channel for a Zenoh key: ``topic`` for ``own_node``'s keys, ``<node>/<topic>`` for others'.

    ``channel_name("skycap/v1/f/drone_1/state", "drone_1") == "state"``;
    ``channel_name("skycap/v1/f/gcs/cmd", "drone_1") == "gcs/cmd"``.
    """
    _, node, topic = _keys.parse_key(key)
    return topic if node == own_node else f"{node}/{topic}"


def schema_name(tag: str) -> str:
    """MCAP schema name of a message type tag, e.g. ``skycap.vehicle_state.v1``."""
    cls = TYPE_BY_TAG[tag]
    return f"skycap.{tag}.v{cls.SCHEMA_VERSION}"


class _Probe(msgspec.Struct):
    type: str
    header: Header


_probe = msgspec.msgpack.Decoder(_Probe)


@dataclass(slots=True)
class _Item:
    topic: str
    data: bytes
    log_time_ns: int


_STOP = object()
_CRASH = object()

#: folders whose disk is simulated full (:func:`simulate_disk_full`)
_FULL_DISKS: set[Path] = set()


def simulate_disk_full(folder: str | Path, full: bool = True) -> None:
    """Fault injection: the disk of ``folder`` is full (``full=False``: has room again) for every recorder of
    this process writing there (see the module doc)."""
    p = Path(folder).resolve()
    if full:
        _FULL_DISKS.add(p)
        log.warning("SIMULATED DISK FULL: %s", p)
    else:
        _FULL_DISKS.discard(p)


def _disk_full(path: Path) -> bool:
    return bool(_FULL_DISKS) and path.parent.resolve() in _FULL_DISKS


_OPEN_RECORDERS: weakref.WeakSet = weakref.WeakSet()


def _close_open_recorders() -> None:
    """Finalise recorders still open when the interpreter exits normally (their writer thread is a daemon)."""
    for r in list(_OPEN_RECORDERS):
        try:
            r.close()
        except Exception as e:
            log.error("closing %s at exit failed: %s", r.path, e)


try:
    threading._register_atexit(_close_open_recorders)  # type: ignore[attr-defined]  # before thread joins
except (AttributeError, RuntimeError):
    import atexit

    atexit.register(_close_open_recorders)


class Recorder:
    """Writes skycap messages to one MCAP file from a background thread; see the module docstring.

    ``path``: the ``.mcap`` file (its folder is created). ``node_id``: written in the file's metadata.
    ``flush_interval_s``: longest time between fsyncs (the most a crash loses). ``chunk_size``: a chunk is
    also closed when it grows past this many bytes. ``compression``: ``"zstd"``, ``"lz4"`` or ``"none"``.
    ``metadata``: string pairs stored as the MCAP metadata record ``skycap`` (flight id, config hash...).
    """

    def __init__(
        self,
        path: str | Path,
        *,
        node_id: str = "",
        flush_interval_s: float = 0.5,
        chunk_size: int = 4 * 1024 * 1024,
        compression: str = "zstd",
        max_queue_bytes: int = 64 * 1024 * 1024,
        metadata: dict[str, str] | None = None,
    ) -> None:
        self.path = Path(path)
        self.node_id = node_id
        if not (0.01 <= flush_interval_s <= 10.0):
            raise RecorderError(f"flush_interval_s={flush_interval_s} must be within 0.01..10 s")
        comp = {"zstd": CompressionType.ZSTD, "lz4": CompressionType.LZ4, "none": CompressionType.NONE}.get(compression)
        if comp is None:
            raise RecorderError(f"compression {compression!r} must be 'zstd', 'lz4' or 'none'")
        self.flush_interval_s = float(flush_interval_s)
        self.max_queue_bytes = int(max_queue_bytes)
        try:
            self.path.parent.mkdir(parents=True, exist_ok=True)
            if _disk_full(self.path):
                raise OSError(errno.ENOSPC, "No space left on device (simulated disk full)")
            self._file = open(self.path, "xb")  # exclusive: a recording is never overwritten or truncated
        except FileExistsError:
            raise RecorderError(f"{self.path} already exists; a recording is never overwritten: record a new sortie "
                                "(Recorder.new_sortie) or choose another file") from None
        except OSError as e:
            raise RecorderError(f"cannot create the flight log {self.path}: {e}; choose a writable folder") from None
        self._writer = Writer(self._file, chunk_size=chunk_size, compression=comp)
        self._writer.start(profile=PROFILE, library="skycap flightdata.recorder")
        meta = {"node_id": node_id, "created_ns": str(now_ns())}
        meta.update({str(k): str(v) for k, v in (metadata or {}).items()})
        self._writer.add_metadata("skycap", meta)
        self._writer.flush()
        os.fsync(self._file.fileno())

        self._queue: queue.SimpleQueue = queue.SimpleQueue()
        self._lock = threading.Lock()
        self._queued_bytes = 0
        self._schemas: dict[str, int] = {}
        self._channels: dict[str, int] = {}
        self._counts = {"written": 0, "bytes": 0, "dropped": 0, "invalid": 0, "flushes": 0}
        self._last_flush_ns = now_ns()
        self._error: BaseException | None = None
        self._closed = False
        self._thread = threading.Thread(target=self._run, name=f"recorder:{self.path.name}", daemon=True)
        self._thread.start()
        _OPEN_RECORDERS.add(self)
        log.info("recording %s (flush every %.2f s, %s)", self.path, self.flush_interval_s, compression)

    @classmethod
    def new_sortie(cls, flight_dir: str | Path, node_id: str, **kw: Any) -> Recorder:
        """A recorder on ``node_id``'s next sortie in ``flight_dir`` (:meth:`FlightFolder.new_recording`).
        Another process that took the same number first makes this one take the next."""
        folder = FlightFolder(flight_dir)
        for _ in range(100):
            path = folder.new_recording(node_id)
            try:
                return cls(path, node_id=node_id, **kw)
            except RecorderError:
                if not path.exists():
                    raise
        raise RecorderError(f"{flight_dir}: no free sortie number for {node_id} after 100 tries")

    # ------------------------------------------------------------------------------------- callers
    def record(self, topic: str, data: bytes, log_time_ns: int | None = None) -> bool:
        """Queue the encoded message ``data`` on channel ``topic``; ``log_time_ns`` defaults to now.

        Returns False (and counts it) when the queue is over ``max_queue_bytes``. Never blocks on disk.
        Raises :class:`RecorderError` if the recorder is closed or its writer failed.
        """
        if self._error is not None:
            raise RecorderError(f"flight log {self.path} failed: {self._error}") from None
        if self._closed:
            raise RecorderError(f"flight log {self.path} is closed; open a new Recorder")
        n = len(data)
        with self._lock:
            if self._queued_bytes + n > self.max_queue_bytes:
                self._counts["dropped"] += 1
                if self._counts["dropped"] in (1, 10) or self._counts["dropped"] % 1000 == 0:
                    log.warning("%s: disk too slow, dropped %d messages so far", self.path, self._counts["dropped"])
                return False
            self._queued_bytes += n
        self._queue.put(_Item(topic, bytes(data), now_ns() if log_time_ns is None else int(log_time_ns)))
        return True

    def record_message(self, topic: str, msg: Message, log_time_ns: int | None = None) -> bool:
        """Encode ``msg`` (header as it is) and :meth:`record` it."""
        return self.record(topic, encode(msg), log_time_ns)

    def record_received(self, topic: str, rx: Any) -> bool:
        """Record an :class:`comms.transport.Received` (its bytes, log time = its receive time)."""
        return self.record(topic, rx.data, rx.t_received_ns)

    def inject_writer_failure(self, reason: str = "injected writer failure") -> None:
        """Fault injection: the writer thread dies of ``RuntimeError(reason)`` when it reaches this point of the
        queue (what it had not flushed is lost, as in a crash of it); :meth:`record` then raises."""
        self._queue.put((_CRASH, reason))

    def stats(self) -> dict[str, int]:
        """Counters: written, bytes, dropped (queue full), invalid (not a skycap message), flushes, queued_bytes."""
        with self._lock:
            return {**self._counts, "queued_bytes": self._queued_bytes}

    @property
    def error(self) -> str:
        """The writer's failure ("" while it works): set on the writer thread, raised by the next :meth:`record`."""
        e = self._error
        return "" if e is None else str(e) or type(e).__name__

    def close(self) -> None:
        """Write what is queued, then the summary and footer; fsync and close the file (idempotent)."""
        if self._closed:
            return
        self._closed = True
        self._queue.put(_STOP)
        self._thread.join()
        if self._error is not None:
            _quiet_close(self._file)
            raise RecorderError(f"flight log {self.path} failed: {self._error}") from None
        try:
            self._check_disk()
            self._writer.finish()
            self._file.flush()
            os.fsync(self._file.fileno())
        except OSError as e:
            raise RecorderError(f"cannot finish the flight log {self.path}: {e}") from None
        finally:
            _quiet_close(self._file)
        log.info("closed %s: %s", self.path, self.stats())

    def __enter__(self) -> Recorder:
        return self

    def __exit__(self, *exc: Any) -> None:
        self.close()

    # ------------------------------------------------------------------------------ writer thread
    def _channel_id(self, topic: str, tag: str) -> int:
        key = f"{topic}\0{tag}"
        cid = self._channels.get(key)
        if cid is None:
            sid = self._schemas.get(tag)
            if sid is None:
                cls = TYPE_BY_TAG[tag]
                sid = self._writer.register_schema(
                    name=schema_name(tag),
                    encoding=SCHEMA_ENCODING,
                    data=json.dumps(msgspec.json.schema(cls)).encode(),
                )
                self._schemas[tag] = sid
            cid = self._writer.register_channel(
                topic=topic, message_encoding=MESSAGE_ENCODING, schema_id=sid, metadata={"type": tag}
            )
            self._channels[key] = cid
        return cid

    def _write(self, item: _Item) -> None:
        try:
            probe = _probe.decode(item.data)
            if probe.type not in TYPE_BY_TAG:
                raise ValueError(f"unknown type {probe.type!r}")
        except (msgspec.DecodeError, msgspec.ValidationError, ValueError) as e:
            self._counts["invalid"] += 1
            if self._counts["invalid"] <= 5:
                log.warning("%s: not recording an invalid message on %r: %s", self.path, item.topic, e)
            return
        cid = self._channel_id(item.topic, probe.type)
        self._writer.add_message(
            channel_id=cid,
            log_time=item.log_time_ns,
            data=item.data,
            publish_time=probe.header.t_sent_ns,
            sequence=probe.header.seq & 0xFFFFFFFF,
        )
        self._counts["written"] += 1
        self._counts["bytes"] += len(item.data)

    def _check_disk(self) -> None:
        if _disk_full(self.path):
            raise OSError(errno.ENOSPC, f"No space left on device (simulated disk full): {self.path}")

    def _flush(self) -> None:
        self._check_disk()
        self._writer.flush()  # closes the chunk in progress and writes it with its message indexes
        os.fsync(self._file.fileno())
        self._counts["flushes"] += 1

    def _run(self) -> None:
        interval_s = self.flush_interval_s
        next_flush = time.monotonic() + interval_s
        dirty = False
        try:
            while True:
                timeout = max(0.0, next_flush - time.monotonic())
                try:
                    item = self._queue.get(timeout=timeout)
                except queue.Empty:
                    item = None
                if item is _STOP:
                    while True:  # drain what arrived before close()
                        try:
                            rest = self._queue.get_nowait()
                        except queue.Empty:
                            break
                        if isinstance(rest, tuple) and rest[0] is _CRASH:
                            raise RuntimeError(rest[1])
                        if rest is not _STOP:
                            self._dequeue(rest)
                    return
                if isinstance(item, tuple) and item[0] is _CRASH:
                    raise RuntimeError(item[1])
                if item is not None:
                    self._dequeue(item)
                    dirty = True
                if time.monotonic() >= next_flush:
                    if dirty:
                        self._flush()
                        dirty = False
                    next_flush = time.monotonic() + interval_s
        except BaseException as e:  # disk full, I/O error: surface it to the callers
            self._error = e
            log.exception("flight log %s: writer failed", self.path)

    def _dequeue(self, item: _Item) -> None:
        with self._lock:
            self._queued_bytes -= len(item.data)
        self._check_disk()  # a full chunk is written to the file by add_message
        self._write(item)


def _quiet_close(f: Any) -> None:
    try:
        f.close()
    except Exception:
        pass
