"""``mapd record info FILE``: what a recording holds, also when it was cut short by a crash."""

from __future__ import annotations

from dataclasses import dataclass, field
from pathlib import Path
from typing import Any

from mapd.errors import MapFileError


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


def summarize(path: Path) -> RecordingSummary:
    """Read every message of ``path`` in order (so a file without its footer reads up to its last chunk)."""
    try:
        from mcap.records import Channel, Footer, Message, Schema
        from mcap.stream_reader import StreamReader
    except ModuleNotFoundError:
        raise MapFileError("record info needs mcap (pip install 'mapd[record]')") from None
    summary = RecordingSummary(str(path), complete=False)
    schemas: dict[int, Schema] = {}
    channels: dict[int, Channel] = {}
    try:
        with open(path, "rb") as fh:
            # records over 64 MiB are refused: a map of max_cells is well under it, a hostile size is not
            for record in StreamReader(fh, skip_magic=False, record_size_limit=64 << 20).records:
                if isinstance(record, Schema):
                    schemas[record.id] = record
                elif isinstance(record, Channel):
                    channels[record.id] = record
                elif isinstance(record, Message):
                    ch = channels.get(record.channel_id)
                    if ch is None:
                        continue
                    sch = schemas.get(ch.schema_id)
                    t = summary.topics.setdefault(
                        ch.topic, TopicSummary(sch.name if sch else "", ch.message_encoding)
                    )
                    t.messages += 1
                    t.first_ns = record.log_time if t.first_ns is None else min(t.first_ns, record.log_time)
                    t.last_ns = record.log_time if t.last_ns is None else max(t.last_ns, record.log_time)
                    summary.messages += 1
                elif isinstance(record, Footer):
                    summary.complete = True
    except OSError as exc:
        raise MapFileError(f"{path}: cannot read: {exc.strerror}") from None
    except Exception as exc:  # the mcap reader raises assorted errors on a cut or damaged file
        summary.error = f"cut short after {summary.messages} messages ({type(exc).__name__})"
    if summary.messages == 0 and summary.error is not None and not summary.topics:
        raise MapFileError(f"{path}: not an MCAP recording ({summary.error})")
    return summary


def render(s: RecordingSummary) -> str:
    lines = [
        f"{s.path}: {s.messages} messages, {'complete' if s.complete else 'no footer: ' + (s.error or 'cut short')}"
    ]
    for topic, t in sorted(s.topics.items()):
        span = ((t.last_ns or 0) - (t.first_ns or 0)) / 1e9
        lines.append(f"  {topic:<24} {t.schema:<28} {t.messages:>6} msgs over {span:8.1f} s")
    return "\n".join(lines)
