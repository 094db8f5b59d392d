"""Read flight recorder files (MCAP written by :mod:`flightdata.recorder`), finalised or cut short by a crash.

    from flightdata.flightlog import FlightLog

    log = FlightLog("flights/demo/drone_1.mcap")
    log.topic_counts()                               # {"state": 3012, "camera/image": 601, ...}
    for m in log.messages(["state"]):                # LogMessage: topic, msg, data, log_time_ns, ...
        ...
    states = log.read_topic("state", VehicleState)   # list of decoded messages

A file whose recorder was killed has no summary or footer: it is read sequentially up to the last complete
record (at most the recorder's flush interval is lost), with one warning saying so; ``log.truncated`` tells
afterwards. :func:`recover` rewrites such a file into a finalised one (what ``mcap recover`` does).
Errors are :class:`FlightLogError` naming the file and the fix.
"""

from __future__ import annotations

import logging
import os
import struct
from collections.abc import Iterable, Iterator
from dataclasses import dataclass
from pathlib import Path
from typing import Any, TypeVar

from mcap.exceptions import McapError
from mcap.reader import SeekingReader
from mcap.records import Channel, Footer, Metadata, Schema
from mcap.records import Message as McapMessage
from mcap.stream_reader import StreamReader

from shared_msgs.codec import MessageError, decode
from shared_msgs.messages import Message
from skycap.errors import SkycapError
from mcap.writer import Writer

__all__ = ["FlightLog", "FlightLogError", "LogMessage", "SortieLogs", "read_messages", "read_topic", "recover"]

log = logging.getLogger(__name__)

M = TypeVar("M", bound=Message)

MAGIC = b"\x89MCAP0\r\n"
PROFILE = "skycap"  #: the MCAP profile of skycap flight logs (written by the recorder and by recover)


class FlightLogError(SkycapError):
    """A flight log that cannot be read (missing, not MCAP, undecodable message)."""


@dataclass(slots=True)
class LogMessage:
    """One recorded message. ``msg`` is None when read with ``decode=False``.

    ``log_time_ns``: when the recorder received it; ``publish_time_ns``: the sender's ``header.t_sent_ns``;
    ``sequence``: ``header.seq``; ``type``: the message type tag (from the channel metadata).
    """

    topic: str
    msg: Message | None
    data: bytes
    log_time_ns: int
    publish_time_ns: int
    sequence: int
    type: str


class FlightLog:
    """A flight recorder file. Cheap to construct (checks the file exists and is MCAP)."""

    def __init__(self, path: str | Path) -> None:
        self.path = Path(path)
        if not self.path.is_file():
            raise FlightLogError(f"flight log {self.path} does not exist; pass a drone_<i>.mcap or truth.mcap file")
        size = self.path.stat().st_size
        with open(self.path, "rb") as f:
            head = f.read(len(MAGIC))
            if size >= 2 * len(MAGIC):
                f.seek(-len(MAGIC), os.SEEK_END)
                tail = f.read(len(MAGIC))
            else:
                tail = b""
        if head != MAGIC:
            raise FlightLogError(
                f"{self.path} is not an MCAP file (starts with {head[:8]!r}); flight logs are written by flightdata.recorder"
            )
        self.finalised = tail == MAGIC
        self.size_bytes = size
        self.truncated = False  #: set after reading a non-finalised file
        self.bytes_read = 0  #: where sequential reading of a non-finalised file stopped

    # ------------------------------------------------------------------------------------ reading
    def messages(
        self,
        topics: Iterable[str] | str | None = None,
        *,
        decode_messages: bool = True,
        skip_invalid: bool = False,
    ) -> Iterator[LogMessage]:
        """Messages of ``topics`` (all when None). Finalised files: in log-time order (indexed read);
        crash-truncated files: in file order up to the last complete chunk.

        Undecodable messages raise :class:`FlightLogError` (or are logged and skipped with ``skip_invalid``).
        """
        if isinstance(topics, str):
            topics = [topics]
        wanted = None if topics is None else set(topics)
        raw = self._iter_finalised(wanted) if self.finalised else self._iter_truncated(wanted)
        for schema, channel, rec in raw:
            tag = channel.metadata.get("type", "") if channel.metadata else ""
            msg = None
            if decode_messages:
                try:
                    msg = decode(rec.data, source=f"{self.path}:{channel.topic}")
                except MessageError as e:
                    if not skip_invalid:
                        raise FlightLogError(
                            f"{self.path}: message on {channel.topic!r} at log time {rec.log_time} cannot be decoded "
                            f"({e}); read it with the skycap version that recorded it, or pass skip_invalid=True"
                        ) from None
                    log.warning("%s: skipped an undecodable message on %r: %s", self.path, channel.topic, e)
                    continue
                tag = tag or msg.__struct_config__.tag
            yield LogMessage(channel.topic, msg, rec.data, rec.log_time, rec.publish_time, rec.sequence, tag)

    def read_topic(self, topic: str, expected: type[M] | None = None) -> list[M]:
        """All decoded messages of one topic in log-time order (also for crash-truncated files);
        ``expected`` checks their type (FlightLogError otherwise)."""
        return self.read_topics({topic: expected})[topic]

    def read_topics(self, types: dict[str, type | None]) -> dict[str, list]:
        """Several topics in one pass over the file -> {topic: decoded messages in log-time order}; ``types[topic]``
        (None: any) checks each message's type (FlightLogError otherwise). One pass instead of one per topic: a
        recording's chunks interleave the camera images with everything else, so every pass decompresses and walks
        them all."""
        rows: dict[str, list] = {t: [] for t in types}
        for m in self.messages(list(types)):
            expected = types[m.topic]
            if expected is not None and not isinstance(m.msg, expected):
                raise FlightLogError(
                    f"{self.path}: topic {m.topic!r} holds {type(m.msg).__name__}, expected {expected.__name__}"
                )
            rows[m.topic].append((m.log_time_ns, m.msg))
        out = {}
        for t, r in rows.items():
            r.sort(key=lambda x: x[0])  # stable: equal times keep file order
            out[t] = [msg for _, msg in r]
        return out

    def topic_counts(self) -> dict[str, int]:
        """Number of messages per topic (from the summary when finalised, else by reading)."""
        if self.finalised:
            summary = self._summary()
            if summary is not None and summary.statistics is not None:
                counts: dict[str, int] = {}
                for cid, n in summary.statistics.channel_message_counts.items():
                    t = summary.channels[cid].topic
                    counts[t] = counts.get(t, 0) + n
                return dict(sorted(counts.items()))
        counts = {}
        for m in self.messages(decode_messages=False):
            counts[m.topic] = counts.get(m.topic, 0) + 1
        return dict(sorted(counts.items()))

    def metadata(self) -> dict[str, dict[str, str]]:
        """The file's metadata records (name -> string pairs), e.g. ``{"skycap": {"node_id": "drone_1"}}``."""
        out: dict[str, dict[str, str]] = {}
        try:
            with open(self.path, "rb") as f:
                for rec in StreamReader(f).records:
                    if isinstance(rec, Metadata):
                        out[rec.name] = dict(rec.metadata)
                    elif isinstance(rec, (McapMessage, Footer)):
                        break  # the recorder writes its metadata first
        except (McapError, EOFError, struct.error, ValueError):
            pass
        return out

    # ---------------------------------------------------------------------------------- internals
    def _summary(self) -> Any:
        with open(self.path, "rb") as f:
            try:
                return SeekingReader(f).get_summary()
            except (McapError, EOFError, struct.error, ValueError) as e:
                raise FlightLogError(f"{self.path}: damaged MCAP summary ({e}); try flightdata.flightlog.recover") from None

    def _iter_finalised(self, wanted: set[str] | None) -> Iterator[tuple[Any, Channel, McapMessage]]:
        with open(self.path, "rb") as f:
            try:
                reader = SeekingReader(f)
                yield from reader.iter_messages(topics=None if wanted is None else sorted(wanted))
            except (McapError, EOFError, struct.error, ValueError) as e:
                raise FlightLogError(
                    f"{self.path}: damaged MCAP file ({type(e).__name__}: {e}); try flightdata.flightlog.recover"
                ) from None

    def _iter_truncated(self, wanted: set[str] | None) -> Iterator[tuple[Any, Channel, McapMessage]]:
        schemas: dict[int, Schema] = {}
        channels: dict[int, Channel] = {}
        n = 0
        with open(self.path, "rb") as f:
            reader = StreamReader(f, validate_crcs=True)
            it = reader.records
            while True:
                try:
                    rec = next(it)
                except StopIteration:
                    break
                except Exception as e:  # EndOfFile, struct.error, zstd/lz4 errors, CRC of a partial chunk
                    self.truncated = True
                    self.bytes_read = f.tell()
                    log.warning(
                        "%s was not finalised (recorder killed?): read %d messages, stopped at the incomplete record "
                        "near byte %d of %d (%s). flightdata.flightlog.recover() rewrites it as a finalised file.",
                        self.path, n, self.bytes_read, self.size_bytes, type(e).__name__,
                    )
                    return
                if isinstance(rec, Schema):
                    schemas[rec.id] = rec
                elif isinstance(rec, Channel):
                    channels[rec.id] = rec
                elif isinstance(rec, McapMessage):
                    ch = channels.get(rec.channel_id)
                    if ch is None:
                        raise FlightLogError(f"{self.path}: message on unknown channel {rec.channel_id}; the file is damaged")
                    n += 1
                    if wanted is None or ch.topic in wanted:
                        yield schemas.get(ch.schema_id), ch, rec
                elif isinstance(rec, Footer):
                    break
        self.truncated = True
        self.bytes_read = self.size_bytes


class SortieLogs:
    """Several recordings of one node (its sorties, :meth:`flightdata.folder.FlightFolder.drone_logs`) read as
    one log: file after file in the given (sortie) order, each file's messages as :class:`FlightLog` gives them.

        logs = SortieLogs([s.path for s in FlightFolder(d).sorties("drone_1")])
        states = logs.read_topic("state", VehicleState)

    Sorties follow each other in time (one recording per agent start), so chaining them keeps time order.
    """

    def __init__(self, paths: Iterable[str | Path]) -> None:
        self.logs = [FlightLog(p) for p in paths]
        if not self.logs:
            raise FlightLogError("no recordings to read: pass at least one <drone>.s<NNN>.mcap file")

    @property
    def paths(self) -> list[Path]:
        return [fl.path for fl in self.logs]

    def messages(self, topics: Iterable[str] | str | None = None, **kw: Any) -> Iterator[LogMessage]:
        """:meth:`FlightLog.messages` of every file, file after file."""
        if topics is not None and not isinstance(topics, str):
            topics = list(topics)
        for fl in self.logs:
            yield from fl.messages(topics, **kw)

    def read_topic(self, topic: str, expected: type[M] | None = None) -> list[M]:
        """:meth:`FlightLog.read_topic` of every file, concatenated in file order."""
        return [m for fl in self.logs for m in fl.read_topic(topic, expected)]

    def read_topics(self, types: dict[str, type | None]) -> dict[str, list]:
        """:meth:`FlightLog.read_topics` of every file, each topic concatenated in file order (each exactly as
        ``read_topic(topic, types[topic])`` gives it)."""
        out: dict[str, list] = {t: [] for t in types}
        for fl in self.logs:
            for t, msgs in fl.read_topics(types).items():
                out[t].extend(msgs)
        return out


def read_messages(path: str | Path, topics: Iterable[str] | str | None = None, **kw: Any) -> Iterator[LogMessage]:
    """Shorthand for ``FlightLog(path).messages(topics, **kw)``."""
    return FlightLog(path).messages(topics, **kw)


def read_topic(path: str | Path, topic: str, expected: type[M] | None = None) -> list[M]:
    """Shorthand for ``FlightLog(path).read_topic(topic, expected)``."""
    return FlightLog(path).read_topic(topic, expected)


def recover(src: str | Path, dst: str | Path, overwrite: bool = False) -> dict[str, int]:
    """Rewrite the readable part of ``src`` (finalised or not) into a finalised MCAP file ``dst``.

    Returns the message count per topic written. Uses the same layout as the recorder (schemas, channel
    metadata, log/publish times, sequence numbers). ``src`` is only read. An existing ``dst`` is refused
    unless ``overwrite`` (then it is replaced whole, only once the new file is complete); ``dst`` can never
    be ``src``.
    """

    src_log = FlightLog(src)
    dst = Path(dst)
    if dst.resolve() == src_log.path.resolve():
        raise FlightLogError(f"recover() would overwrite {src}; write to another file")
    if dst.exists() and not overwrite:
        raise FlightLogError(f"{dst} already exists; a recording is never overwritten: choose another output file "
                             "(or pass --force to replace it)")
    dst.parent.mkdir(parents=True, exist_ok=True)
    meta = src_log.metadata()
    counts: dict[str, int] = {}
    tmp = dst.with_name(f".{dst.name}.{os.getpid()}.partial")
    try:
        with open(tmp, "xb") as f:
            w = Writer(f)
            w.start(profile=PROFILE, library="skycap flightdata.flightlog.recover")
            for name, data in meta.items():
                w.add_metadata(name, data)
            schema_ids: dict[int, int] = {}
            channel_ids: dict[int, int] = {}
            raw = src_log._iter_finalised(None) if src_log.finalised else src_log._iter_truncated(None)
            for schema, channel, rec in raw:
                cid = channel_ids.get(channel.id)
                if cid is None:
                    sid = 0
                    if schema is not None:
                        sid = schema_ids.get(schema.id) or w.register_schema(schema.name, schema.encoding, schema.data)
                        schema_ids[schema.id] = sid
                    cid = w.register_channel(channel.topic, channel.message_encoding, sid, dict(channel.metadata))
                    channel_ids[channel.id] = cid
                w.add_message(cid, rec.log_time, rec.data, rec.publish_time, rec.sequence)
                counts[channel.topic] = counts.get(channel.topic, 0) + 1
            w.finish()
            f.flush()
            os.fsync(f.fileno())
    except BaseException:
        tmp.unlink(missing_ok=True)
        raise
    if overwrite:
        os.replace(tmp, dst)
    else:
        try:  # atomic and exclusive: a file that appeared at dst meanwhile is kept
            os.link(tmp, dst)
        except FileExistsError:
            raise FlightLogError(f"{dst} appeared while recovering; the recovered log is left in {tmp}") from None
        os.unlink(tmp)
    return dict(sorted(counts.items()))


# ------------------------------------------------------------------------------------------------ CLI
def register(sub: Any) -> Any:
    """Add ``skycap log info FILE...`` and ``skycap log recover IN OUT`` to the skycap CLI; returns the ``log``
    actions' subparsers (:mod:`flightdata.cli` adds ``skycap log foxglove`` to them)."""
    p = sub.add_parser(
        "log",
        help="inspect or recover flight recorder files (MCAP)",
        description="Inspect flight recorder files (drone_<i>.mcap, truth.mcap) or rewrite one cut short by a "
        "crash into a finalised file. Example: skycap log info flights/demo/*.mcap",
    )
    cmds = p.add_subparsers(dest="log_command", metavar="ACTION", required=True)
    pi = cmds.add_parser("info", help="topics, message counts, time span, finalised or not")
    pi.add_argument("files", nargs="+", type=Path)
    pi.set_defaults(func=_cmd_info)
    pr = cmds.add_parser("recover", help="rewrite a crash-truncated file as a finalised one")
    pr.add_argument("src", type=Path)
    pr.add_argument("dst", type=Path)
    pr.add_argument("--force", action="store_true", help="replace an existing DST (never SRC)")
    pr.set_defaults(func=_cmd_recover)
    return cmds


def describe(path: str | Path) -> dict[str, Any]:
    """Summary of one file: finalised, size, per-topic count, first/last log time (ns), metadata."""
    fl = FlightLog(path)
    counts: dict[str, int] = {}
    t_first = t_last = None
    for m in fl.messages(decode_messages=False):
        counts[m.topic] = counts.get(m.topic, 0) + 1
        t_first = m.log_time_ns if t_first is None else min(t_first, m.log_time_ns)
        t_last = m.log_time_ns if t_last is None else max(t_last, m.log_time_ns)
    return {
        "path": str(fl.path), "finalised": fl.finalised, "size_bytes": fl.size_bytes, "topics": dict(sorted(counts.items())),
        "t_first_ns": t_first, "t_last_ns": t_last, "metadata": fl.metadata(),
    }


def _cmd_info(args: Any) -> int:
    for f in args.files:
        d = describe(f)
        span = (d["t_last_ns"] - d["t_first_ns"]) / 1e9 if d["t_first_ns"] is not None else 0.0
        state = "finalised" if d["finalised"] else "NOT finalised (recorder killed?) -- skycap log recover can fix it"
        print(f"{d['path']}: {d['size_bytes'] / 1e6:.1f} MB, {span:.1f} s, {state}")
        for topic, n in d["topics"].items():
            print(f"  {topic:<28} {n:>8} msgs  {n / span if span > 0 else 0.0:8.1f} Hz")
    return 0


def _cmd_recover(args: Any) -> int:
    counts = recover(args.src, args.dst, overwrite=args.force)
    print(f"wrote {args.dst}: {sum(counts.values())} messages on {len(counts)} topics")
    return 0
