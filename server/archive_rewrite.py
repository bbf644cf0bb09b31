"""Rewrite a finished campaign archive: every record copied, some added or amended.

MCAP has no in-place update. The console adds a Foxglove scene channel to a finished campaign
(:mod:`server.foxglove_scene`); the campaign runner amends its ``xneck.campaign`` record when the
analysis of an identification fails (:mod:`server.campaign_runner`). Both copy the file record by
record into a temporary file that atomically replaces the archive (fsynced first): a crash leaves
the original intact.
"""

from __future__ import annotations

import os
from collections.abc import Callable, Mapping
from pathlib import Path
from typing import Any

from mcap.writer import Writer

from bridge.archive import CHUNK_SIZE, COMPRESSION, PROFILE, software_version
from bridge.archive_chunks import BoundedReader

#: Called after each message is copied: (writer, schema, channel, message) of the source file.
OnMessage = Callable[[Writer, Any, Any, Any], None]


def rewrite_archive(path: str | os.PathLike[str], *, begin: Callable[[Writer], OnMessage | None] | None = None,
                    amend: Mapping[str, Mapping[str, str]] | None = None,
                    end: Callable[[Writer], None] | None = None) -> None:
    """Copy ``path`` in log-time order. ``begin(writer)`` may register schemas and channels and
    return a callback run after each copied message; ``amend`` maps a metadata record's name to
    fields merged into it; ``end(writer)`` may add records after the copied metadata."""
    path = Path(path)
    tmp = path.with_name(path.name + ".rewrite")
    tmp.unlink(missing_ok=True)
    try:
        with open(path, "rb") as src, open(tmp, "xb") as dst:
            reader = BoundedReader(src)
            writer = Writer(dst, chunk_size=CHUNK_SIZE, compression=COMPRESSION)
            writer.start(profile=PROFILE, library=f"xneck/{software_version()}")
            after = begin(writer) if begin is not None else None
            schema_ids: dict[int, int] = {}
            channel_ids: dict[int, int] = {}
            for schema, channel, message in reader.iter_messages(log_time_order=True):
                if schema is not None and schema.id not in schema_ids:
                    schema_ids[schema.id] = writer.register_schema(schema.name, schema.encoding, schema.data)
                if channel.id not in channel_ids:
                    channel_ids[channel.id] = writer.register_channel(
                        channel.topic, channel.message_encoding, schema_ids.get(channel.schema_id, 0),
                        dict(channel.metadata))
                writer.add_message(channel_ids[channel.id], message.log_time, message.data, message.publish_time,
                                   message.sequence)
                if after is not None:
                    after(writer, schema, channel, message)
            for record in reader.iter_metadata():
                writer.add_metadata(record.name, {**record.metadata, **(amend or {}).get(record.name, {})})
            if end is not None:
                end(writer)
            writer.finish()
            dst.flush()
            os.fsync(dst.fileno())
        os.replace(tmp, path)
    finally:
        tmp.unlink(missing_ok=True)
