"""Reading session logs, including files cut off by a crash, and rewriting them as indexed MCAP.

A process killed while writing leaves an MCAP file without its summary section and footer, and
possibly with half a record at the end. mcap's seeking reader needs the footer; its
``NonSeekingReader``/``StreamReader`` read front to back but cannot say where a truncated record
begins. So :func:`read_log` walks the top-level records itself: it reads each record's opcode and
length, checks that the whole record is in the file, and only then hands the record's bytes to
mcap's ``StreamReader`` (``skip_magic=True``, ``validate_crcs=True``) to parse it, chunks
included (a chunk whose CRC does not match is a torn write).

A record that is cut off at the end of the file is the tail a crash leaves: reading stops there
and everything before it is returned, with the number of bytes that could not be read. A record
that is damaged *inside* the file (garbage written over it, a bad CRC, a length that runs past
the next record) is skipped: the reader looks for the next intact record after it (a record
header whose opcode is known, whose length fits in the file, which parses and validates, and
which is followed by another plausible record header or the end of the file) and reads on from
there. MCAP records carry no sync marker, so this is a search; the chunks our writer emits are
zstd-compressed with a CRC, which makes a false restart in garbage practically impossible. Every
skipped byte range is reported (:attr:`LogContents.damage`), and the messages after it are read
(the summary section of a closed file repeats the schemas and channels, so even a damaged first
chunk loses only its own messages).

Messages decode into the typed records of :mod:`bridge.log.records` (:attr:`LogMessage.record`,
:meth:`LogContents.records`); :attr:`LogMessage.data` is the plain JSON object.

:func:`recover` copies the intact part (schemas, channels, messages byte for byte, metadata,
attachments) into a new, normally indexed MCAP file that any MCAP reader and Foxglove open.
"""

from __future__ import annotations

import io
import json
import logging
import os
import re
import struct
import time
from collections import Counter
from collections.abc import Iterable, Mapping
from dataclasses import dataclass, field
from functools import cached_property
from pathlib import Path
from typing import Any

import msgspec
from mcap.exceptions import EndOfFile, McapError
from mcap.opcode import Opcode
from mcap.records import (
    Attachment,
    Channel,
    Header,
    McapRecord,
    Message,
    Metadata,
    Schema,
)
from mcap.stream_reader import StreamReader
from mcap.writer import Writer

from bridge.log.errors import LogError, LogFormatError, LogWriteError
from bridge.log.records import METADATA_NAME, RECORD_TYPES, Topic
from drivers.files import PRIVATE_FILE_MODE, create_private_file, read_regular_file

__all__ = [
    "MAX_LOG_BYTES",
    "ChannelInfo",
    "Damage",
    "LogContents",
    "LogMessage",
    "RecoverReport",
    "config_file_mode",
    "read_log",
    "recover",
]

logger = logging.getLogger(__name__)

_MAGIC = b"\x89MCAP0\r\n"
MAX_LOG_BYTES = 2 << 30
"""Largest session log read (2 GiB; it is read whole). An hour's session logs a few tens of MB."""
_RECORD_HEADER = struct.Struct("<BQ")
_KNOWN_OPCODES = frozenset(int(op) for op in Opcode)
# A record header candidate when resynchronising after damage: a known opcode and a length below
# 2**40 (its top 3 bytes zero); the full checks follow in _resync. A lookahead, so that
# candidates may overlap: a false one in the damaged bytes can start up to 8 bytes before the
# real next header, and a consuming pattern would then step over it.
_RESYNC = re.compile(rb"(?=[\x01-\x10].{5}\x00\x00\x00)", re.DOTALL)
_INDEX_OPCODES = frozenset({
    Opcode.MESSAGE_INDEX, Opcode.CHUNK_INDEX, Opcode.ATTACHMENT_INDEX, Opcode.METADATA_INDEX,
    Opcode.STATISTICS, Opcode.SUMMARY_OFFSET, Opcode.DATA_END,
})


@dataclass(frozen=True)
class LogMessage:
    """One message.

    Attributes:
        topic: Its channel's topic.
        log_time_ns: When it was written (writer's clock, ns).
        publish_time_ns: Breath-time base (ns) for breath-tied messages, else the log time.
        sequence: The writer's global counter (file order).
        raw: The message bytes (JSON).
        record: The typed record (:mod:`bridge.log.records`) of a known channel, or None (an
            unknown topic, or a message that does not fit its channel's record type).
    """

    topic: str
    log_time_ns: int
    publish_time_ns: int
    sequence: int
    raw: bytes = field(repr=False)
    record: Any = None

    @cached_property
    def data(self) -> dict[str, Any]:
        """The decoded JSON object (for tools that want plain dicts; readers use :attr:`record`)."""
        value = json.loads(self.raw)
        return value if isinstance(value, dict) else {}


@dataclass(frozen=True)
class Damage:
    """A byte range of the file that could not be read and was skipped.

    Attributes:
        start: Offset of the first damaged byte.
        end: Offset where reading resumed (exclusive).
        reason: What was wrong at ``start``.
    """

    start: int
    end: int
    reason: str

    @property
    def n_bytes(self) -> int:
        """Bytes skipped."""
        return self.end - self.start

    def describe(self) -> str:
        """``bytes 1,234–5,678 (4,444 bytes): reason``."""
        return f"bytes {self.start:,}–{self.end:,} ({self.n_bytes:,} bytes) skipped: {self.reason}"


@dataclass(frozen=True)
class ChannelInfo:
    """A channel of the file.

    Attributes:
        topic: Topic.
        schema_name: Schema name (empty without a schema).
        schema_encoding: ``jsonschema`` for ours.
        message_encoding: ``json`` for ours.
        schema: The parsed JSON schema, or None.
        message_count: Messages on this channel in the readable part of the file.
    """

    topic: str
    schema_name: str
    schema_encoding: str
    message_encoding: str
    schema: Mapping[str, Any] | None
    message_count: int


@dataclass(frozen=True)
class LogContents:
    """What could be read from a session log.

    Attributes:
        path: The file.
        size_bytes: Its size.
        readable_bytes: Bytes up to the end of the last intact record.
        complete: The file ends with a footer and the closing magic (the writer closed it).
        data_complete: The data section ended normally (DataEnd read): no message is missing
            even if the summary behind it was cut.
        stop_reason: Why reading stopped early ("" when complete).
        library: The writer's library string from the header.
        profile: The header's profile (``hilbo`` for ours).
        channels: Channels by topic.
        messages: Decoded messages in file (= write) order.
        metadata: Metadata records by name (a repeated name keeps the first).
        undecoded: Messages not decoded: not JSON, or not in the requested topics.
        undecodable: JSON messages that failed to parse (skipped, logged).
        invalid: Messages of a known channel that do not fit its record type (kept, with
            ``record`` None).
        damage: Byte ranges damaged inside the file and skipped (reading went on after each).
        format_version: The log format version from ``/config`` (None if unknown).
        time_range_ns: (first, last) log time over every readable message (decoded or not),
            or None without messages.
    """

    path: str
    size_bytes: int
    readable_bytes: int
    complete: bool
    data_complete: bool
    stop_reason: str
    library: str
    profile: str
    channels: Mapping[str, ChannelInfo]
    messages: tuple[LogMessage, ...]
    metadata: Mapping[str, Mapping[str, str]]
    undecoded: int = 0
    undecodable: int = 0
    time_range_ns: tuple[int, int] | None = None
    invalid: int = 0
    damage: tuple[Damage, ...] = ()

    @property
    def truncated(self) -> bool:
        """The file does not end as a closed MCAP file does (crash, kill -9, full disk)."""
        return not self.complete

    @property
    def unreadable_bytes(self) -> int:
        """Bytes after the last intact record (a torn chunk or record)."""
        return self.size_bytes - self.readable_bytes

    @property
    def damaged(self) -> bool:
        """Part of the file inside it could not be read (see :attr:`damage`)."""
        return bool(self.damage)

    @property
    def damaged_bytes(self) -> int:
        """Bytes skipped inside the file."""
        return sum(d.n_bytes for d in self.damage)

    def damage_text(self) -> str:
        """One line describing every damaged range ("" when undamaged)."""
        return "; ".join(d.describe() for d in self.damage)

    def records(self, name: str) -> list[Any]:
        """The typed records of one topic in file order (messages that did not decode left out)."""
        return [m.record for m in self.topic(name) if m.record is not None]

    @property
    def format_version(self) -> int | None:
        """The log format version stored in ``/config`` or the metadata."""
        value = self.session.get("format_version")
        try:
            return int(value) if value is not None else None
        except (TypeError, ValueError):
            return None

    @cached_property
    def by_topic(self) -> Mapping[str, tuple[LogMessage, ...]]:
        """Decoded messages grouped by topic, each in file order."""
        groups: dict[str, list[LogMessage]] = {}
        for m in self.messages:
            groups.setdefault(m.topic, []).append(m)
        return {k: tuple(v) for k, v in groups.items()}

    def topic(self, name: str) -> tuple[LogMessage, ...]:
        """Messages of one topic (empty if none)."""
        return self.by_topic.get(name, ())

    def data(self, name: str) -> list[dict[str, Any]]:
        """Decoded message bodies of one topic, in file order."""
        return [m.data for m in self.topic(name)]

    @property
    def is_hilbo(self) -> bool:
        """The file carries our session marker (``hilbo.session`` metadata or ``/config``)."""
        return METADATA_NAME in self.metadata or Topic.CONFIG in self.channels

    @cached_property
    def session(self) -> Mapping[str, Any]:
        """The first ``/config`` message, or the ``hilbo.session`` metadata, or {}."""
        cfg = self.topic(Topic.CONFIG)
        if cfg:
            rec = cfg[0].record
            return msgspec.structs.asdict(rec) if rec is not None else cfg[0].data
        meta = self.metadata.get(METADATA_NAME)
        return dict(meta) if meta else {}

    @property
    def session_id(self) -> str | None:
        """The session id."""
        value = self.session.get("session_id")
        return str(value) if value else None

    @property
    def previous_log(self) -> str | None:
        """The log this session resumed, if any."""
        value = self.session.get("previous_log")
        return str(value) if value else None

    @property
    def config(self) -> Mapping[str, Any] | None:
        """The session config stored in ``/config``."""
        value = self.session.get("config")
        return value if isinstance(value, Mapping) else None


@dataclass(frozen=True)
class RecoverReport:
    """What :func:`recover` did.

    Attributes:
        src: The damaged file.
        dst: The rewritten file.
        messages: Messages copied.
        per_topic: Messages copied per topic.
        source_complete: The source was already a closed file.
        unreadable_bytes: Bytes of the source that were lost (torn tail).
        stop_reason: Why reading the source stopped ("" when complete).
        damage: Byte ranges damaged inside the source and skipped.
    """

    src: str
    dst: str
    messages: int
    per_topic: Mapping[str, int]
    source_complete: bool
    unreadable_bytes: int
    stop_reason: str
    damage: tuple[Damage, ...] = ()


# ---------------------------------------------------------------------------------- scanning
@dataclass
class _Scan:
    """Top-level records of a file, and where and why reading stopped."""

    size: int
    readable: int = 0
    complete: bool = False
    data_complete: bool = False
    stop_reason: str = ""
    header: Header | None = None
    records: list[McapRecord] = field(default_factory=list)
    damage: list[Damage] = field(default_factory=list)


_PARSE_ERRORS = (McapError,)  # _parse turns whatever mcap's reader raises into McapError


def _parse(buf: bytes | memoryview, *, offset: int) -> list[McapRecord]:
    """Parse one whole top-level record (a chunk yields the records inside it)."""
    stream = io.BytesIO(buf)
    reader = StreamReader(stream, skip_magic=True, validate_crcs=True, record_size_limit=None)
    out: list[McapRecord] = []
    try:
        for rec in reader.records:
            out.append(rec)
    except EndOfFile:
        # The stream holds exactly one record: the reader's attempt at the next one ends here.
        if stream.tell() < len(buf):
            raise McapError(f"the record at byte {offset} ends before its declared length") from None
    except McapError:
        raise
    except Exception as err:
        # The one boundary around mcap's parser: damaged bytes make it raise what its code meets
        # (a ValueError from a CRC, OverflowError from a length of 2^63, struct.error, zstd's or
        # lz4's errors, MemoryError from a huge declared size). Each is a damaged record, which
        # the scan skips by resynchronising, never a traceback.
        raise McapError(f"{type(err).__name__}: {err}") from err
    return out


def _header_fits(buf: bytes, p: int, size: int) -> int | None:
    """End of the record whose header is at ``p`` if its opcode is known and it fits, else None."""
    if size - p < _RECORD_HEADER.size:
        return None
    opcode, length = _RECORD_HEADER.unpack_from(buf, p)
    end = p + _RECORD_HEADER.size + length
    return end if opcode in _KNOWN_OPCODES and end <= size else None


def _resync(buf: bytes, start: int, size: int) -> tuple[int, list[McapRecord]] | None:
    """The next intact record at or after ``start`` (its offset and parsed records), or None."""
    view = memoryview(buf)
    for m in _RESYNC.finditer(buf, start):
        p = m.start()
        end = _header_fits(buf, p, size)
        if end is None:
            continue
        opcode = buf[p]
        if opcode == Opcode.FOOTER:
            if buf[end:end + len(_MAGIC)] != _MAGIC:
                continue
        elif end != size and _header_fits(buf, end, size) is None:
            continue  # a real record is followed by another one (or the end of the file)
        if opcode in _INDEX_OPCODES or opcode == Opcode.HEADER:
            if opcode != Opcode.HEADER:
                return p, []
            continue
        try:
            return p, _parse(view[p:end], offset=p)
        except _PARSE_ERRORS:
            continue
    return None


def _scan(buf: bytes, path: str) -> _Scan:
    size = len(buf)
    scan = _Scan(size=size)
    if size == 0:
        raise LogFormatError(f"{path}: the file is empty (0 bytes); a session log starts with the MCAP "
                             "magic and a header")
    magic = buf[: len(_MAGIC)]
    if magic != _MAGIC[: len(magic)] or len(magic) < len(_MAGIC):
        if magic == _MAGIC[: len(magic)]:
            raise LogFormatError(f"{path}: only {size} bytes, cut inside the MCAP magic; nothing to read")
        raise LogFormatError(f"{path}: not an MCAP file (starts with {magic[:8]!r}, expected the MCAP "
                             f"magic {_MAGIC!r})")
    view = memoryview(buf)
    offset = len(_MAGIC)
    scan.readable = offset
    while True:
        if offset >= size:
            scan.stop_reason = f"the file ends at byte {offset} without a footer"
            return scan
        problem = ""
        parsed: list[McapRecord] = []
        opcode = buf[offset]
        if size - offset < _RECORD_HEADER.size:
            problem = f"a record header at byte {offset} is cut off"
        else:
            opcode, length = _RECORD_HEADER.unpack_from(buf, offset)
            end = offset + _RECORD_HEADER.size + length
            if opcode not in _KNOWN_OPCODES:
                problem = f"byte {offset} holds no MCAP record (opcode 0x{opcode:02x} is not one)"
            elif end > size:
                problem = (f"the record at byte {offset} (opcode 0x{opcode:02x}, {length} bytes) is "
                           f"cut off at byte {size}")
            elif opcode in _INDEX_OPCODES:
                # Indexes and summary records say nothing the data records don't: skip parsing them.
                offset = scan.readable = end
                scan.data_complete = scan.data_complete or opcode == Opcode.DATA_END
                continue
            else:
                try:
                    parsed = _parse(view[offset:end], offset=offset)
                except _PARSE_ERRORS as err:
                    # A torn or corrupted record: mcap's CRCValidationError (a ValueError), zstd's
                    # ZstdError, lz4's RuntimeError, or a field that runs past the record's end.
                    problem = f"the record at byte {offset} (opcode 0x{opcode:02x}) is damaged: {err}"
        if problem:
            if scan.header is None:
                raise LogFormatError(f"{path}: MCAP magic without a readable header record at byte 8 "
                                     f"({problem})")
            found = _resync(buf, offset + 1, size)
            if found is None:
                # Nothing intact after it: the tail a crash (or a full disk) leaves.
                scan.stop_reason = problem
                return scan
            nxt, _ = found
            scan.damage.append(Damage(offset, nxt, problem))
            logger.warning("%s: %s", path, scan.damage[-1].describe())
            offset = nxt
            continue
        if scan.header is None:
            if opcode != Opcode.HEADER or not parsed or not isinstance(parsed[0], Header):
                raise LogFormatError(f"{path}: MCAP magic without a header record (opcode 0x{opcode:02x} "
                                     "at byte 8)")
            scan.header = parsed[0]
        scan.records.extend(parsed)
        offset = scan.readable = end
        if opcode == Opcode.FOOTER:
            if buf[offset:offset + len(_MAGIC)] == _MAGIC:
                scan.readable = offset + len(_MAGIC)
                scan.complete = scan.readable == size
                if not scan.complete:
                    scan.stop_reason = f"{size - scan.readable} bytes after the closing magic"
            else:
                scan.stop_reason = "the closing magic after the footer is missing"
            return scan


def _open_scan(path: str | os.PathLike[str]) -> _Scan:
    p = Path(path)
    try:
        buf = read_regular_file(p, max_bytes=MAX_LOG_BYTES, what="a hilbo session log (.mcap)",
                                error=LogFormatError)
    except FileNotFoundError as err:
        raise LogFormatError(f"{str(p)!r}: no such file") from err
    except IsADirectoryError as err:
        raise LogFormatError(f"{str(p)!r} is a directory, not an MCAP log") from err
    except OSError as err:
        raise LogError(f"{str(p)!r}: cannot read: {err}") from err
    return _scan(buf, str(p))


# ---------------------------------------------------------------------------------- reading
def read_log(path: str | os.PathLike[str], *, topics: Iterable[str] | None = None,
             require_hilbo: bool = True) -> LogContents:
    """Read a session log, whole or cut off by a crash.

    Args:
        path: The ``.mcap`` file.
        topics: Decode only these topics (the others are counted, not decoded); None = all.
        require_hilbo: Refuse an MCAP file that is not a hilbo session log.

    Returns:
        The decoded messages in file order, channels, metadata, and how much was unreadable.

    Raises:
        LogFormatError: Not an MCAP file, empty, or (with ``require_hilbo``) another program's
            MCAP file.
        LogError: The file cannot be read.
    """
    try:
        return _read_log(path, topics, require_hilbo)
    except LogError:
        raise
    except Exception as err:
        # The reader's one error boundary: whatever a damaged file makes the code below raise is
        # the file's fault, reported with its name (the scan already isolates damaged records).
        raise LogFormatError(f"{path}: not readable as a session log ({type(err).__name__}: {err})") from err


def _read_log(path: str | os.PathLike[str], topics: Iterable[str] | None, require_hilbo: bool) -> LogContents:
    scan = _open_scan(path)
    wanted = None if topics is None else {str(t) for t in topics}
    schemas: dict[int, Schema] = {}
    channels: dict[int, Channel] = {}
    metadata: dict[str, dict[str, str]] = {}
    counts: Counter[str] = Counter()
    messages: list[LogMessage] = []
    undecoded = undecodable = invalid = 0
    t_first: int | None = None
    t_last: int | None = None
    # Schemas and channels first: after a damaged first chunk, the summary section's copies
    # still name the channels of the messages read after the damage.
    for rec in scan.records:
        if isinstance(rec, Schema):
            schemas.setdefault(rec.id, rec)
        elif isinstance(rec, Channel):
            channels.setdefault(rec.id, rec)
        elif isinstance(rec, Metadata):
            metadata.setdefault(rec.name, dict(rec.metadata))
    for rec in scan.records:
        if not isinstance(rec, Message):
            continue
        ch = channels.get(rec.channel_id)
        if ch is None:
            undecodable += 1
            continue
        counts[ch.topic] += 1
        t_first = rec.log_time if t_first is None else min(t_first, rec.log_time)
        t_last = rec.log_time if t_last is None else max(t_last, rec.log_time)
        if ch.message_encoding != "json" or (wanted is not None and ch.topic not in wanted):
            undecoded += 1
            continue
        record, ok = _decode(ch.topic, rec.data)
        if not ok:
            logger.warning("%s: message %d on %s is not valid JSON; skipped", path, rec.sequence, ch.topic)
            undecodable += 1
            continue
        if record is None and ch.topic in RECORD_TYPES:
            invalid += 1
        messages.append(LogMessage(ch.topic, rec.log_time, rec.publish_time, rec.sequence, rec.data, record))
    infos: dict[str, ChannelInfo] = {}
    for ch in channels.values():
        schema = schemas.get(ch.schema_id)
        parsed: Mapping[str, Any] | None = None
        if schema is not None and schema.encoding == "jsonschema":
            try:
                parsed = json.loads(schema.data)
            except (json.JSONDecodeError, UnicodeDecodeError):
                parsed = None
        infos.setdefault(ch.topic, ChannelInfo(
            ch.topic, schema.name if schema else "", schema.encoding if schema else "",
            ch.message_encoding, parsed, counts[ch.topic]))
    header = scan.header
    contents = LogContents(
        path=str(path), size_bytes=scan.size, readable_bytes=scan.readable, complete=scan.complete,
        data_complete=scan.data_complete or scan.complete, stop_reason=scan.stop_reason,
        library=header.library if header else "", profile=header.profile if header else "",
        channels=infos, messages=tuple(messages), metadata=metadata, undecoded=undecoded,
        undecodable=undecodable, invalid=invalid, damage=tuple(scan.damage),
        time_range_ns=None if t_first is None or t_last is None else (t_first, t_last),
    )
    if require_hilbo and not contents.is_hilbo:
        topics_found = sorted(infos) or "none"
        raise LogFormatError(
            f"{path}: an MCAP file, but not a hilbo session log (no {METADATA_NAME!r} metadata and no "
            f"{Topic.CONFIG} channel; its topics: {topics_found})"
        )
    if contents.truncated:
        logger.info("%s: truncated (%s); %d bytes unreadable", path, scan.stop_reason,
                    contents.unreadable_bytes)
    return contents


_DECODERS = {topic: msgspec.json.Decoder(t) for topic, t in RECORD_TYPES.items()}


def _decode(topic: str, raw: bytes) -> tuple[Any, bool]:
    """``(typed record or None, is JSON)`` of one message."""
    decoder = _DECODERS.get(topic)
    if decoder is None:
        try:
            return None, isinstance(json.loads(raw), dict)
        except (json.JSONDecodeError, UnicodeDecodeError, RecursionError):  # damaged: not JSON
            return None, False
    try:
        return decoder.decode(raw), True
    except msgspec.ValidationError:
        return None, True  # JSON, but not this channel's record (kept; record None)
    except msgspec.DecodeError:
        pass
    try:
        # Python's NaN/Infinity tokens (the optimizer snapshot keeps them): the stdlib reads them.
        obj = json.loads(raw)
    except (json.JSONDecodeError, UnicodeDecodeError, RecursionError):
        return None, False
    if not isinstance(obj, dict):
        return None, False
    try:
        return msgspec.convert(obj, RECORD_TYPES[topic]), True
    except msgspec.ValidationError:
        return None, True


# ---------------------------------------------------------------------------------- recovery
def config_file_mode(config: Mapping[str, Any] | None) -> int:
    """The ``[session] file_mode`` of a logged session config as permission bits.

    Files derived from a session's log (its review, a recovered copy) hold the same health data,
    so they get the mode the session gave its own log; 0o600 when the config does not say.
    """
    session = config.get("session") if isinstance(config, Mapping) else None
    text = session.get("file_mode") if isinstance(session, Mapping) else None
    if isinstance(text, str) and re.fullmatch(r"0?[0-7]{3}", text):
        return int(text, 8)
    return PRIVATE_FILE_MODE


def _scan_file_mode(scan: _Scan) -> int:
    """:func:`config_file_mode` of the first readable ``/config`` message of a scanned log."""
    ids = {r.id for r in scan.records if isinstance(r, Channel) and r.topic == Topic.CONFIG}
    for r in scan.records:
        if isinstance(r, Message) and r.channel_id in ids:
            try:
                obj = json.loads(r.data)
            except (ValueError, RecursionError):  # damaged: the default mode
                break
            return config_file_mode(obj.get("config") if isinstance(obj, dict) else None)
    return PRIVATE_FILE_MODE


def recover(src: str | os.PathLike[str], dst: str | os.PathLike[str], *,
            overwrite: bool = False, file_mode: int | None = None) -> RecoverReport:
    """Rewrite the intact part of a (crashed) log as a normal, indexed MCAP file.

    Schemas, channels, messages (bytes, times and sequence numbers unchanged), metadata and
    attachments are copied; a ``hilbo.recovered`` metadata record names the source and the
    bytes lost. Works on any MCAP file, hilbo's or not.

    Args:
        src: The damaged (or intact) file.
        dst: The file to write; must differ from ``src``.
        overwrite: Replace an existing ``dst``.
        file_mode: Permission bits of ``dst``; None: the source session's ``[session]
            file_mode`` (:func:`config_file_mode`), 0o600 when it has none (health data).

    Raises:
        LogFormatError: ``src`` is not an MCAP file, or ``dst`` is ``src``.
        LogWriteError: ``dst`` exists (without ``overwrite``) or cannot be written.
    """
    src_p, dst_p = Path(src), Path(dst)
    if dst_p.exists() and src_p.exists() and os.path.samefile(src_p, dst_p):
        raise LogFormatError(f"recover: the output {str(dst_p)!r} is the input; give another file name")
    scan = _open_scan(src_p)
    tmp = dst_p.with_name(dst_p.name + ".part")
    if dst_p.exists() and not overwrite:
        raise LogWriteError(f"recover: {str(dst_p)!r} exists; remove it or choose another output file")
    per_topic: Counter[str] = Counter()
    mode = _scan_file_mode(scan) if file_mode is None else file_mode
    try:
        with create_private_file(tmp, mode) as f:
            writer = Writer(f)
            header = scan.header
            writer.start(profile=header.profile if header else "", library=header.library if header else "")
            schema_ids: dict[int, int] = {}
            channel_ids: dict[int, int] = {}
            schemas: dict[int, Schema] = {}
            channels: dict[int, Channel] = {}
            seen_meta: set[tuple[str, tuple[tuple[str, str], ...]]] = set()
            for rec in scan.records:
                if isinstance(rec, Schema):
                    schemas.setdefault(rec.id, rec)
                elif isinstance(rec, Channel):
                    channels.setdefault(rec.id, rec)
            for rec in scan.records:
                if isinstance(rec, Metadata):
                    key = (rec.name, tuple(sorted(rec.metadata.items())))
                    if key not in seen_meta:  # the summary section repeats nothing, but be safe
                        seen_meta.add(key)
                        writer.add_metadata(rec.name, dict(rec.metadata))
                elif isinstance(rec, Attachment):
                    writer.add_attachment(rec.create_time, rec.log_time, rec.name, rec.media_type, rec.data)
                elif isinstance(rec, Message):
                    ch = channels.get(rec.channel_id)
                    if ch is None:
                        continue
                    if ch.id not in channel_ids:
                        sid = 0
                        if ch.schema_id != 0 and ch.schema_id in schemas:
                            if ch.schema_id not in schema_ids:
                                s = schemas[ch.schema_id]
                                schema_ids[ch.schema_id] = writer.register_schema(s.name, s.encoding, s.data)
                            sid = schema_ids[ch.schema_id]
                        channel_ids[ch.id] = writer.register_channel(ch.topic, ch.message_encoding, sid,
                                                                     dict(ch.metadata))
                    writer.add_message(channel_ids[ch.id], log_time=rec.log_time, data=rec.data,
                                       publish_time=rec.publish_time, sequence=rec.sequence)
                    per_topic[ch.topic] += 1
            writer.add_metadata("hilbo.recovered", {
                "source": str(src_p), "source_bytes": str(scan.size),
                "unreadable_bytes": str(scan.size - scan.readable),
                "source_complete": str(scan.complete).lower(), "stop_reason": scan.stop_reason,
                "damaged_ranges": "; ".join(d.describe() for d in scan.damage),
                "recovered_unix_ns": str(time.time_ns()),
            })
            writer.finish()
            f.flush()
            os.fsync(f.fileno())
        os.replace(tmp, dst_p)
    except OSError as err:
        tmp.unlink(missing_ok=True)
        raise LogWriteError(f"recover: cannot write {str(dst_p)!r}: {err}") from err
    return RecoverReport(src=str(src_p), dst=str(dst_p), messages=sum(per_topic.values()),
                         per_topic=dict(per_topic), source_complete=scan.complete,
                         unreadable_bytes=scan.size - scan.readable, stop_reason=scan.stop_reason,
                         damage=tuple(scan.damage))
