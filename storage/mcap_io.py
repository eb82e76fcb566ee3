"""The MCAP plumbing that episodes and takeover segments share: a JSON-message writer with JSON
schemas (zstd chunks, a running sequence number, flush to disk), Foxglove time stamps, and a reader
that salvages what was flushed from a file cut off by a crash."""

from __future__ import annotations

import json
from pathlib import Path

from mcap.reader import NonSeekingReader, make_reader
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

    def flush(self) -> None:
        """Closes the current chunk and flushes it to disk: a crash after this keeps it."""
        self._writer.flush()
        self._file.flush()

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
