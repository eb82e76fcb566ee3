"""The MCAP plumbing that episodes and takeover segments share: a JSON-message writer with JSON
schemas (zstd chunks, a running sequence number, flush to disk), Foxglove time stamps, a reader
that salvages what was flushed from a file cut off by a crash, and ``rebuild``, which turns such a
file back into a complete, indexed MCAP that any standard reader opens."""

from __future__ import annotations

import json
import os
from pathlib import Path

from mcap.reader import NonSeekingReader, make_reader
from mcap.records import Channel, DataEnd, Message, Metadata, Schema
from mcap.stream_reader import StreamReader
from mcap.writer import CompressionType, Writer

from storage import keys


def stamp(ns: int) -> dict:
    """A Foxglove ``time`` from nanoseconds."""
    return {"sec": ns // 1_000_000_000, "nsec": ns % 1_000_000_000}


class JsonMcapWriter:
    """One MCAP file of JSON messages. ``schemas``: schema name -> JSON schema, all registered up front."""

    def __init__(self, path: str | Path, schemas: dict[str, dict], chunk_size: int) -> None:
        self.path = Path(path)
        self.path.parent.mkdir(parents=True, exist_ok=True)
        self._file = open(self.path, "wb")  # noqa: SIM115 - closed in close()
        self._writer = Writer(self._file, compression=CompressionType.ZSTD, chunk_size=chunk_size)
        self._writer.start(profile=keys.MCAP_PROFILE, library="hitl")
        self._schemas = {
            name: self._writer.register_schema(name, "jsonschema", json.dumps(schema).encode())
            for name, schema in schemas.items()
        }
        self._seq = 0
        self.closed = False

    def channel(self, topic: str, schema: str) -> int:
        return self._writer.register_channel(topic, "json", self._schemas[schema])

    def add(self, channel: int, ns: int, payload: dict) -> None:
        self._writer.add_message(
            channel, log_time=ns, publish_time=ns, sequence=self._seq, data=json.dumps(payload).encode()
        )
        self._seq += 1

    def add_metadata(self, name: str, values: dict) -> None:
        self._writer.add_metadata(name, {k: json.dumps(v) for k, v in values.items()})

    def flush(self, sync: bool = False) -> None:
        """Closes the current chunk and hands it to the operating system: a crash of this process after
        this keeps it. ``sync``: also ``fsync``, so that a crash of the machine keeps it too."""
        self._writer.flush()
        self._file.flush()
        if sync:
            os.fsync(self._file.fileno())

    def close(self) -> None:
        """Writes the summary and footer."""
        if self.closed:
            return
        self.closed = True
        try:
            self._writer.finish()
        finally:
            self._file.close()


def read_all(path: Path) -> list:
    """Every (schema, channel, message) of an intact file, in file order (raises on a broken one)."""
    with open(path, "rb") as f:
        return list(make_reader(f, validate_crcs=True).iter_messages(log_time_order=False))


def salvage(path: Path) -> tuple[list, str | None]:
    """Reads records in file order until the data ends or breaks: (messages, why it stopped)."""
    out: list = []
    with open(path, "rb") as f:
        try:
            for item in NonSeekingReader(f, validate_crcs=True).iter_messages(log_time_order=False):
                out.append(item)
        except Exception as exc:  # noqa: BLE001 - any decode failure marks the truncation point
            return out, f"{type(exc).__name__}: {exc}"
    return out, None


def rebuild(path: Path, append: dict[str, dict] | None = None) -> tuple[int, str | None]:
    """Rewrites a file cut off by a crash as a complete, indexed MCAP: every schema, channel, message
    and metadata record up to the point where the data breaks is copied to ``<path>.rebuild``, then
    ``append`` (topic -> JSON payload, on channels the file already has) is added after the last
    message, and the new file replaces the old one atomically (``os.replace``). Returns (messages
    kept, why the old data stopped: None if it ended cleanly)."""
    path = Path(path)
    records, why = [], None
    with open(path, "rb") as f:
        try:
            for record in StreamReader(f, validate_crcs=True).records:
                if isinstance(record, DataEnd):  # the summary that follows repeats schemas and channels
                    break
                if isinstance(record, Schema | Channel | Message | Metadata):
                    records.append(record)
        except Exception as exc:  # noqa: BLE001 - any decode failure marks the truncation point
            why = f"{type(exc).__name__}: {exc}"
    tmp = path.with_name(path.name + ".rebuild")
    try:
        kept = _write_rebuilt(path, tmp, records, append)
        os.replace(tmp, path)
    finally:
        tmp.unlink(missing_ok=True)
    directory = os.open(path.parent, os.O_RDONLY)  # the rename itself survives a power loss
    try:
        os.fsync(directory)
    finally:
        os.close(directory)
    return kept - len(append or {}), why


def _write_rebuilt(path: Path, tmp: Path, records: list, append: dict[str, dict] | None) -> int:
    kept, last_ns, topics = 0, 0, {}
    with open(tmp, "wb") as out:
        writer = Writer(out, compression=CompressionType.ZSTD)
        writer.start(profile=keys.MCAP_PROFILE, library="hitl")
        schema_ids: dict[int, int] = {}
        channel_ids: dict[int, int] = {}
        for r in records:
            if isinstance(r, Schema):
                schema_ids[r.id] = writer.register_schema(r.name, r.encoding, r.data)
            elif isinstance(r, Channel) and r.schema_id in schema_ids | {0: 0}:
                channel_ids[r.id] = writer.register_channel(
                    r.topic, r.message_encoding, ({0: 0} | schema_ids)[r.schema_id], dict(r.metadata)
                )
                topics[r.topic] = channel_ids[r.id]
            elif isinstance(r, Message) and r.channel_id in channel_ids:
                writer.add_message(channel_ids[r.channel_id], r.log_time, r.data, r.publish_time, r.sequence)
                kept, last_ns = kept + 1, max(last_ns, r.log_time)
            elif isinstance(r, Metadata):
                writer.add_metadata(r.name, dict(r.metadata))
        for topic, payload in (append or {}).items():
            if topic not in topics:
                raise ValueError(f"{path}: no channel {topic!r} to append to")
            last_ns += 1
            writer.add_message(topics[topic], last_ns, json.dumps(payload).encode(), last_ns, kept)
            kept += 1
        writer.finish()
        out.flush()
        os.fsync(out.fileno())
    return kept
