"""``mapd record info FILE``: what a recording holds, also when it was cut short by a crash."""

from __future__ import annotations

import struct
from collections.abc import Iterator
from dataclasses import dataclass, field
from io import BytesIO
from pathlib import Path
from typing import Any

from mapd.errors import MapFileError
from mapd.files.reading import open_for_reading
from mapd.grid import DEFAULT_MAX_CELLS


@dataclass
class TopicSummary:
    schema: str
    encoding: str
    messages: int = 0
    first_ns: int | None = None
    last_ns: int | None = None


@dataclass
class RecordingSummary:
    path: str
    complete: bool
    messages: int = 0
    topics: dict[str, TopicSummary] = field(default_factory=dict)
    error: str | None = None

    def to_json(self) -> dict[str, Any]:
        return {
            "path": self.path,
            "complete": self.complete,
            "messages": self.messages,
            "error": self.error,
            "topics": {t: vars(s) for t, s in sorted(self.topics.items())},
        }


#: Room in a chunk beside its one map: the messages of the recorder's ``chunk_bytes`` before it
#: (256 KiB), the map's header, and the schemas and channels.
CHUNK_SLACK = 1 << 20
#: Largest record read from the file (a chunk, compressed): a map of ``DEFAULT_MAX_CELLS`` compresses
#: well under it; a hostile length is refused before it is read. (Larger for ``max_cells`` above the
#: default: :func:`limits_for`.)
MAX_RECORD_BYTES = 64 << 20
#: Largest chunk decompressed. A chunk holds the messages of ``chunk_bytes`` plus at most one more,
#: which is at most a map of ``max_cells`` cells (one byte each) and its header. A chunk
#: declaring more is refused before anything is decompressed, and none decompresses past what it
#: declares: a few KiB of zstd can otherwise stand for gigabytes.
MAX_CHUNK_BYTES = DEFAULT_MAX_CELLS + CHUNK_SLACK

#: Records parsed out of chunks, at most, per byte of the chunks read so far (plus
#: :data:`RECORDS_GRACE`). A recorded record is a map, a transform or link counters, 100 bytes or
#: more that compress a few times: 50,000 nearly equal transforms make 0.035 records a byte. A zstd
#: chunk of a few KiB can hold millions of 9-byte records, each a step of the parsing loop, and
#: bytes outside chunks (padding in records mapd skips) earn nothing: 1 MB of them bought 16 M
#: records, 27 s of parsing.
RECORDS_PER_CHUNK_BYTE = 1
RECORDS_GRACE = 1 << 16
#: Names (topics, schemas, encodings) are kept this long: a chunk can inflate one to 64 MiB.
MAX_NAME = 200
#: Topics told apart, at most: a recording of mapd has a few; each chunk of a hostile file can
#: bring a new one (or redefine a channel's), and every one is kept for the summary.
MAX_TOPICS = 1024

_RECORD_HEAD = struct.Struct("<BQ")  # opcode, length
_MESSAGE_HEAD = struct.Struct("<H4xQ")  # channel id, (sequence), log time
_MESSAGE_HEAD_BYTES = 22  # channel id, sequence, log time, publish time


def limits_for(max_cells: int) -> tuple[int, int]:
    """The largest record read and the largest chunk decompressed, for a recording of maps up to
    ``max_cells`` cells (the daemon's ``[limits] max_cells``): what :func:`summarize` holds at most."""
    chunk = max_cells + CHUNK_SLACK
    # a chunk of maps that hardly compress is a little over its size (zstd's frame, the record)
    return max(MAX_RECORD_BYTES, chunk + CHUNK_SLACK), chunk


def _decompress(chunk: Any, max_chunk: int = MAX_CHUNK_BYTES, max_cells: int = DEFAULT_MAX_CELLS) -> bytes:
    """A chunk's records, decompressed to at most the size it declares (and ``max_chunk``)."""
    size = chunk.uncompressed_size
    if size > max_chunk:
        raise MapFileError(
            f"a chunk declares {size} bytes, over the {max_chunk} a recording's chunk holds with maps of up "
            f"to {max_cells} cells (mapd record info --max-cells, as the daemon's [limits] max_cells)"
        )
    if chunk.compression == "":
        data = bytes(chunk.data)
    elif chunk.compression == "zstd":
        import zstandard

        with zstandard.ZstdDecompressor().stream_reader(chunk.data) as reader:
            parts: list[bytes] = []
            got = 0
            while got <= size:  # one byte past the declared size tells a lie from the truth
                part = reader.read(size + 1 - got)
                if not part:
                    break
                parts.append(part)
                got += len(part)
            data = b"".join(parts)
    elif chunk.compression == "lz4":
        import lz4.frame

        data = lz4.frame.LZ4FrameDecompressor().decompress(chunk.data, max_length=size + 1)
    else:
        raise MapFileError(f"a chunk is compressed with {chunk.compression[:20]!r}, which mapd does not read")
    if len(data) != size:
        raise MapFileError(f"a chunk decompresses to {'more than ' if len(data) > size else ''}"
                           f"{min(len(data), size)} bytes, not the {size} it declares")  # fmt: skip
    return data


@dataclass
class _RecordCount:
    """Records parsed out of chunks so far, against what the bytes read so far allow."""

    parsed: int = 0
    allowed: int = RECORDS_GRACE


def _chunk_records(data: bytes, count: _RecordCount) -> Iterator[Any]:
    """The schemas and channels of a decompressed chunk, and ``(channel id, log time)`` of each message.

    Messages are not built as objects: a chunk can hold millions of tiny ones. Other records are
    skipped, as the MCAP spec asks of readers. Every record is counted in ``count``; past
    ``count.allowed`` the file is refused (:data:`RECORDS_PER_CHUNK_BYTE`).
    """
    from mcap.data_stream import ReadDataStream
    from mcap.opcode import Opcode
    from mcap.records import Channel, Schema

    message, schema, channel = int(Opcode.MESSAGE), int(Opcode.SCHEMA), int(Opcode.CHANNEL)
    head_size, unpack_head = _RECORD_HEAD.size, _RECORD_HEAD.unpack_from
    pos, end = 0, len(data)
    while pos < end:
        count.parsed += 1
        if count.parsed > count.allowed:
            raise MapFileError(
                f"chunks hold more records than {RECORDS_PER_CHUNK_BYTE} a byte of their compressed data "
                "(a compression bomb, not a recording)"
            )
        if end - pos < head_size:
            raise MapFileError("a chunk ends inside a record header")
        opcode, length = unpack_head(data, pos)
        pos += head_size
        if length > end - pos:
            raise MapFileError("a record runs past the end of its chunk")
        if opcode == message:
            if length < _MESSAGE_HEAD_BYTES:
                raise MapFileError("a message record is shorter than its header")
            yield _MESSAGE_HEAD.unpack_from(data, pos)
        elif opcode in (schema, channel):
            stream = ReadDataStream(BytesIO(data[pos : pos + length]))
            yield Schema.read(stream) if opcode == schema else Channel.read(stream)
        pos += length


def summarize(path: Path, *, max_cells: int = DEFAULT_MAX_CELLS) -> RecordingSummary:
    """Read every message of ``path`` in order (so a file without its footer reads up to its last chunk).

    Memory stays bounded whatever the file says: records and chunks over what a recording of maps
    up to ``max_cells`` cells holds (:func:`limits_for`; by default :data:`MAX_RECORD_BYTES` and
    :data:`MAX_CHUNK_BYTES`) are refused, and messages are counted, not kept.
    """
    max_record, max_chunk = limits_for(max_cells)
    try:
        from mcap.records import Channel, Chunk, Footer, Message, Schema
        from mcap.stream_reader import StreamReader
    except ModuleNotFoundError:
        raise MapFileError("record info needs mcap (pip install 'mapd[record]')") from None
    summary = RecordingSummary(str(path), complete=False)
    # Only the names are kept, cut to MAX_NAME: a schema's data or a channel's metadata can be
    # 64 MiB each, and 40 chunks of them held 2.8 GB.
    schemas: dict[int, str] = {}
    channels: dict[int, tuple[str, str, int]] = {}  # id -> topic, message encoding, schema id

    def message(channel_id: int, log_time: int) -> None:
        ch = channels.get(channel_id)
        if ch is None:
            return
        topic, encoding, schema_id = ch
        t = summary.topics.get(topic)
        if t is None:
            if len(summary.topics) >= MAX_TOPICS:
                raise MapFileError(f"more than {MAX_TOPICS} topics (not a recording of mapd)")
            t = summary.topics[topic] = TopicSummary(schemas.get(schema_id, ""), encoding)
        t.messages += 1
        t.first_ns = log_time if t.first_ns is None else min(t.first_ns, log_time)
        t.last_ns = log_time if t.last_ns is None else max(t.last_ns, log_time)
        summary.messages += 1

    def take(record: Any) -> None:
        if isinstance(record, Schema):
            schemas[record.id] = record.name[:MAX_NAME]
        elif isinstance(record, Channel):
            channels[record.id] = (
                record.topic[:MAX_NAME],
                record.message_encoding[:MAX_NAME],
                record.schema_id,
            )
        elif isinstance(record, tuple):
            message(*record)

    try:
        # open_for_reading: a FIFO named by mistake reads as empty instead of blocking for ever
        with open_for_reading(path) as fh:
            # emit_chunks: chunks are decompressed here, within max_chunk; the mcap reader
            # would decompress whatever size a chunk claims and build every message it holds.
            reader = StreamReader(fh, skip_magic=False, emit_chunks=True, record_size_limit=max_record)
            count = _RecordCount()
            chunk_bytes = 0  # (counted here, not by fh.tell(): a pipe cannot tell)
            for record in reader.records:
                if isinstance(record, Chunk):
                    chunk_bytes += len(record.data)
                    count.allowed = RECORDS_GRACE + RECORDS_PER_CHUNK_BYTE * chunk_bytes
                    for item in _chunk_records(_decompress(record, max_chunk, max_cells), count):
                        take(item)
                elif isinstance(record, Message):
                    message(record.channel_id, record.log_time)
                elif isinstance(record, Footer):
                    summary.complete = True
                else:
                    take(record)
    except OSError as exc:
        raise MapFileError(f"{path}: cannot read: {exc.strerror}") from None
    except MapFileError as exc:  # damage found here: say what it is
        summary.error = f"cut short after {summary.messages} messages ({exc})"
    except Exception as exc:  # the mcap reader raises assorted errors on a cut or damaged file
        summary.error = f"cut short after {summary.messages} messages ({type(exc).__name__})"
    if summary.messages == 0 and summary.error is not None and not summary.topics:
        raise MapFileError(f"{path}: not an MCAP recording ({summary.error})")
    return summary


def _printable(text: str) -> str:
    """``text`` with control characters escaped: a name in a file must not forge a line of the
    summary or send escape sequences to the terminal."""
    return "".join(c if c.isprintable() else repr(c)[1:-1] for c in text)


def render(s: RecordingSummary) -> str:
    lines = [
        f"{s.path}: {s.messages} messages, {'complete' if s.complete else 'no footer: ' + (s.error or 'cut short')}"
    ]
    for topic, t in sorted(s.topics.items()):
        span = ((t.last_ns or 0) - (t.first_ns or 0)) / 1e9
        lines.append(
            f"  {_printable(topic):<24} {_printable(t.schema):<28} {t.messages:>6} msgs over {span:8.1f} s"
        )
    return "\n".join(lines)
