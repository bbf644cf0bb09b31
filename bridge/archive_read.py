"""Reading a campaign archive back (the file layout: :mod:`bridge.archive`).

:func:`read_campaign` reads a finished file, each message of the contract decoded to its type and
checked against its schema; a missing, non-MCAP, truncated or unfinished file, or a message that
does not match, is an :class:`bridge.archive.ArchiveError` naming the file and why (an unfinished
one is repaired by :func:`bridge.archive_recovery.recover`).

Decoded, a message takes 5-10 times its JSON (floats and lists are Python objects): a 28 s
identification campaign of 13.5 MB took 117 MB, half of it the Foxglove scene no computation
reads, so a 600 s campaign would take 2.5 GB. A reader that needs some keys names them
(``keys=``): the other topics are counted, not decoded or kept, and asking the campaign for one
of them is an error rather than an empty list (``benchmarks/archive_read.py`` prints both). A
reader that needs a few numbers of each message of a 500 Hz topic folds them (``fold=``): each
message, decoded and checked, is handed to its function and not kept (``xneck identify`` of a
577 s campaign peaked at 565 MB of Python objects reading its motor states and commands).
"""

from __future__ import annotations

import os
from collections.abc import Callable, Iterable, Mapping
from dataclasses import dataclass, field
from pathlib import Path
from typing import Any

import msgspec
import numpy as np
from mcap.records import Channel, Message

from bridge import bus
from bridge.archive import CAMPAIGN, CAMPAIGN_START, MAGIC, ArchiveError
from bridge.archive_chunks import BoundedReader, ReadRefused


@dataclass
class Campaign:
    """A campaign read back. ``topics`` maps each MCAP topic to ``[(log_time_ns, message), ...]``
    in log-time order; messages of the contract are decoded to their types, others (written by
    other tools) to plain JSON values."""

    path: Path
    metadata: dict[str, dict[str, str]]
    topics: dict[str, list[tuple[int, Any]]]
    schemas: dict[str, str] = field(default_factory=dict)
    #: Messages per topic in the file, read or not (what an error lists as present).
    counts: dict[str, int] = field(default_factory=dict)
    #: Which topics were read (``None``: all of them); :meth:`messages` refuses the others.
    selected: Callable[[str], bool] | None = None
    #: The topics handed to :func:`read_campaign`'s ``fold`` functions, not kept.
    folded: frozenset[str] = frozenset()

    @property
    def info(self) -> dict[str, str]:
        """The ``xneck.campaign`` record (falls back to ``xneck.campaign.start``)."""
        return self.metadata.get(CAMPAIGN) or self.metadata.get(CAMPAIGN_START, {})

    def messages(self, key: str) -> list[tuple[int, Any]]:
        """Messages of a key (``xneck/motor/state``) or topic (``/xneck/motor/state``). A key the
        campaign was read without (:func:`read_campaign`'s ``keys``) is a :class:`KeyError`: an
        empty list would read as "not recorded"."""
        topic = bus.mcap_topic(key)
        if topic in self.folded:
            raise KeyError(f"{topic} of {self.path} was folded as it was read (read_campaign(fold=...)), not kept")
        if self.selected is not None and not self.selected(topic):
            raise KeyError(f"{topic} was not read from {self.path} (read_campaign(keys=...) left it out)")
        return self.topics.get(topic, [])

    def series(self, key: str, field_name: str) -> tuple[np.ndarray, np.ndarray]:
        """``(log_time_ns int64 (N,), values (N, ...))`` of one field over a key's messages."""
        msgs = self.messages(key)
        t = np.array([t for t, _ in msgs], dtype=np.int64)
        values = np.array([getattr(m, field_name) for _, m in msgs])
        return t, values


def _check_file(path: Path) -> int:
    if not path.exists():
        raise ArchiveError(path, "no such file")
    if not path.is_file():
        raise ArchiveError(path, "not a regular file")
    size = path.stat().st_size
    with open(path, "rb") as f:
        head = f.read(len(MAGIC))
    if head != MAGIC:
        raise ArchiveError(path, "not an MCAP file (bad magic at the start)")
    return size


def is_complete(path: str | os.PathLike[str]) -> bool:
    """Whether ``path`` is an MCAP file that was finished (magic at both ends). Raises
    :class:`ArchiveError` if it is missing or not MCAP at all."""
    path = Path(path)
    size = _check_file(path)
    if size < 2 * len(MAGIC):
        return False
    with open(path, "rb") as f:
        f.seek(size - len(MAGIC))
        return f.read() == MAGIC


def check_finished(path: str | os.PathLike[str]) -> Path:
    """``path`` if it is a finished MCAP file (what :func:`read_campaign` reads), else
    :class:`ArchiveError` saying why (missing, not a regular file, not MCAP, truncated or
    unfinished, with how to repair the latter). Reads 16 bytes: a command checks its input with it
    before loading what the work needs."""
    path = Path(path)
    if not is_complete(path):
        raise ArchiveError(path, "truncated or unfinished MCAP file (no footer): if its recording was "
                                 "interrupted, copy it into <data dir>/campaigns/ and start `xneck server` (or "
                                 "`xneck up`): the console repairs such files at start-up, as interrupted campaigns")
    return path


def read_campaign_info(path: str | os.PathLike[str]) -> dict[str, str]:
    """The ``xneck.campaign`` record of a finished campaign file (falls back to
    ``xneck.campaign.start``; ``{}`` if it has neither), read from its metadata alone: a command
    judges the campaign (its ``outcome``) before it reads the messages (seconds for a long one).
    :class:`ArchiveError` as :func:`read_campaign` raises it."""
    path = check_finished(path)
    metadata: dict[str, dict[str, str]] = {}
    try:
        with open(path, "rb") as f:
            for record in BoundedReader(f).iter_metadata():
                metadata[record.name] = dict(record.metadata)  # the last record of a name wins
    except Exception as exc:  # noqa: BLE001 - mcap raises many types on a damaged file
        raise ArchiveError(path, f"damaged MCAP file ({type(exc).__name__}: {exc})") from None
    return metadata.get(CAMPAIGN) or metadata.get(CAMPAIGN_START, {})


def read_campaign(path: str | os.PathLike[str],
                  keys: Iterable[str] | Callable[[str], bool] | None = None,
                  fold: Mapping[str, Callable[[int, Any], None]] | None = None) -> Campaign:
    """Read a finished campaign file: every message, or those of ``keys`` only (bus keys or MCAP
    topics, or a test of the MCAP topic), the others counted in :attr:`Campaign.counts` and
    neither decoded nor checked. The messages of a key of ``fold`` are decoded and checked, then
    handed to its function as ``(log_time_ns, message)`` in file order (not log-time order: the
    caller orders what it keeps) and not kept. Raises :class:`ArchiveError` for a missing,
    non-MCAP, truncated or unfinished file (run :func:`recover` on the latter two), a message
    read that does not match its schema, or a file whose chunks decompress to more than
    :func:`bridge.archive_chunks.read_limit` of its size (a decompression bomb); a fold function
    raises :class:`FoldError` to have its own error raised as it is."""
    path = check_finished(path)
    wanted = _selection(keys)
    folds = {bus.mcap_topic(k): f for k, f in (fold or {}).items()}
    topics: dict[str, list[tuple[int, Any]]] = {}
    schemas: dict[str, str] = {}
    counts: dict[str, int] = {}
    metadata: dict[str, dict[str, str]] = {}
    try:
        with open(path, "rb") as f:
            reader = BoundedReader(f, validate_crcs=True)  # a chunk is decompressed within bounds
            for record in reader.iter_metadata():
                metadata[record.name] = dict(record.metadata)  # the last record of a name wins
            # In file order, then each topic sorted by log time: the order mcap's log_time_order=True
            # gives (ties in file order; the sort is stable), without its Python heap, which took half
            # of the read (1.4 of 2.7 s for a 14 s control campaign).
            for schema, channel, message in reader.iter_messages(log_time_order=False):
                topic = channel.topic
                counts[topic] = counts.get(topic, 0) + 1
                if topic in folds:
                    schemas.setdefault(topic, schema.name if schema is not None else "")
                    folds[topic](message.log_time, decode_archived(path, channel, message))
                    continue
                if wanted is not None and not wanted(topic):
                    continue
                if topic not in topics:
                    topics[topic] = []
                    schemas[topic] = schema.name if schema is not None else ""
                topics[topic].append((message.log_time, decode_archived(path, channel, message)))
        for msgs in topics.values():
            msgs.sort(key=_log_time)
    except ArchiveError:
        raise
    except FoldError as exc:
        raise exc.error from None
    except ReadRefused as exc:  # a bomb of many chunks: not a damaged file, and not read
        raise ArchiveError(path, str(exc)) from None
    except Exception as exc:  # noqa: BLE001 - mcap raises many types on a damaged file
        raise ArchiveError(path, f"damaged MCAP file ({type(exc).__name__}: {exc})") from None
    return Campaign(path=path, metadata=metadata, topics=topics, schemas=schemas, counts=counts, selected=wanted,
                    folded=frozenset(folds))


class FoldError(Exception):
    """Raised by a ``fold`` function to have :func:`read_campaign` raise ``error`` as it is (not as
    a damaged file): a message the caller cannot use, in a file that reads."""

    def __init__(self, error: Exception) -> None:
        super().__init__(str(error))
        self.error = error


def _selection(keys: Iterable[str] | Callable[[str], bool] | None) -> Callable[[str], bool] | None:
    if keys is None or callable(keys):
        return keys
    if isinstance(keys, str):  # its characters would be read as keys
        raise TypeError("keys: an iterable of keys, not one key")
    return frozenset(bus.mcap_topic(k) for k in keys).__contains__


def _log_time(item: tuple[int, Any]) -> int:
    return item[0]


def decode_archived(path: Path, channel: Channel, message: Message) -> Any:
    msg_type = bus.message_type(bus.key_of_topic(channel.topic))
    if msg_type is None or channel.message_encoding != "json":
        if channel.message_encoding == "json":
            try:
                return msgspec.json.decode(message.data)
            except msgspec.DecodeError as exc:
                raise ArchiveError(path, f"{channel.topic}: invalid JSON ({exc})") from None
        return bytes(message.data)
    try:
        return bus.decode(msg_type, message.data)
    except bus.BusDecodeError as exc:
        raise ArchiveError(path, f"{channel.topic} at log time {message.log_time} ns: {exc.reason}") from None


__all__ = ["Campaign", "FoldError", "check_finished", "decode_archived", "is_complete", "read_campaign"]
