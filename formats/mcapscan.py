"""A lean sequential reader of MCAP records for :mod:`.logreader` (contracts.md §4).

The ``mcap`` package's stream reader builds a Python object for every record, every message
index entry included; for a 1 kHz log that is most of the reading time. This module walks the
records itself: chunks are decompressed whole and their message records are cut out with one
``struct`` call each, message indexes and other summary records are skipped unread, and only
the rare records (channels, metadata, attachments, footer) are parsed by ``mcap``'s own classes.
A finished file whose chunks all have message indexes can also be read through them
(``indexed``): a chunk's message positions and log times are then one array per channel, and
only the messages wanted are cut out.
CRCs are checked as the ``mcap`` reader does with ``validate_crcs=True``: the uncompressed CRC
of each chunk and the data-section CRC in the DataEnd record.

Cut files and corruption are told apart as before: a file that ends with the MCAP closing magic
was finished by its writer, so anything that does not parse in it is corruption; in a file
without it, a record cut by the end of the file is the end of a killed writer's output.
"""

from __future__ import annotations

import importlib
import struct
import zlib
from collections.abc import Callable, Iterator
from enum import IntEnum
from io import BytesIO
from pathlib import Path
from typing import IO, Any

import numpy as np
from mcap.data_stream import ReadDataStream
from mcap.records import Attachment, Channel, Footer, Metadata

from drivegain.errors import DataError

MAGIC = b"\x89MCAP0\r\n"
#: records longer than this are corruption (the ``mcap`` reader's default limit, 4 GiB)
RECORD_SIZE_LIMIT = 4 * 2**30

_RECORD_HEADER = struct.Struct("<BQ")
_MESSAGE_HEADER = struct.Struct("<HIQQ")  # channel id, sequence, log time, publish time
_CHUNK_HEADER = struct.Struct("<QQQI")  # start, end, uncompressed size, uncompressed CRC
_INDEX_HEADER = struct.Struct("<HI")  # channel id, byte length of the entries
_U32 = struct.Struct("<I")
_U64 = struct.Struct("<Q")


class Op(IntEnum):
    """MCAP record opcodes this reader acts on (others are skipped)."""

    FOOTER = 0x02
    SCHEMA = 0x03
    CHANNEL = 0x04
    MESSAGE = 0x05
    CHUNK = 0x06
    MESSAGE_INDEX = 0x07
    ATTACHMENT = 0x09
    METADATA = 0x0C
    DATA_END = 0x0F


#: what :func:`records` yields after filling the buckets from a chunk or a message record
FILLED = object()


class IndexedChunk:
    """A chunk read through the message indexes that follow it (``records(..., indexed=...)``).

    Attributes
    ----------
    data
        The chunk's records, uncompressed.
    entries
        Channel kind -> (k, 2) uint64 array of (log time ns, offset in ``data``) of the
        messages of the kind's channels, in file order.
    damaged
        Why a message index of the chunk could not be read, or None. No reader needs the
        indexes, so this is not corruption of the data: the caller reads the chunk otherwise.
    """

    def __init__(self, data: bytes):
        self.data = data
        self.entries: dict[int, np.ndarray] = {}
        self.damaged: str | None = None
        self._channels: dict[int, set[int]] = {}  # kind -> its channels' ids

    def add(self, kind: int, channel_id: int, entries: np.ndarray) -> None:
        """Add the (k, 2) entries of one channel's message index to ``kind``'s."""
        if kind in self.entries:  # another channel of the same kind: one file order for both
            entries = np.concatenate([self.entries[kind], entries])
        self.entries[kind] = entries[np.argsort(entries[:, 1], kind="stable")]
        self._channels.setdefault(kind, set()).add(channel_id)

    def message(self, kind: int, offset: int, log_time: int) -> bytes:
        """The data of the message record at ``offset``, which must be on a channel of
        ``kind`` and have ``log_time``.

        Raises
        ------
        ValueError
            No such message record there.
        """
        data = self.data
        if offset + _RECORD_HEADER.size + _MESSAGE_HEADER.size > len(data):
            raise ValueError(f"message index offset {offset} past the chunk")
        op, length = _RECORD_HEADER.unpack_from(data, offset)
        start = offset + _RECORD_HEADER.size
        if op != Op.MESSAGE or start + length > len(data):
            raise ValueError(f"no message record at chunk offset {offset}")
        channel_id, _, when, _ = _MESSAGE_HEADER.unpack_from(data, start)
        if channel_id not in self._channels.get(kind, ()):
            raise ValueError(f"message at chunk offset {offset} is on another channel")
        if when != log_time:
            raise ValueError(f"message at chunk offset {offset} has another log time")
        return data[start + _MESSAGE_HEADER.size : start + length]


#: channel kind -> (message data, log times, ns) collected so far
Buckets = dict[int, tuple[list[bytes], list[int]]]


def _parse(cls: Any, content: bytes) -> Any:
    return cls.read(ReadDataStream(BytesIO(content)))


def records(
    fh: IO[bytes],
    size: int,
    path: Path,
    finished: bool,
    classify: Callable[[Channel], int | None],
    buckets: Buckets,
    indexed: dict[int, int] | None = None,
) -> Iterator[Any]:
    """Read the top-level records in file order; stops quietly at a cut.

    Channel, Metadata, Attachment and Footer records are yielded as ``mcap`` record objects
    (channels met inside chunks too). Messages are not yielded: each message of a channel that
    ``classify`` gave a kind to is appended to ``buckets[kind]``, and :data:`FILLED` is yielded
    after each chunk or message record so the caller can drain the buckets.

    With ``indexed`` (channel id -> kind, from a finished file's summary), chunks are not cut
    into records: each is yielded as an :class:`IndexedChunk` holding the entries of the message
    index records that follow it for the channels of those kinds, and the caller takes what it
    needs from it.

    Raises
    ------
    DataError
        ``corrupt MCAP data at byte ...`` for anything that does not parse where the file is
        not cut (see the module docstring); DataErrors from ``classify`` pass through.
    """
    kinds: dict[int, int] = dict(indexed or {})
    pending: list[IndexedChunk] = []  # the chunk whose message indexes are being read
    fh.seek(0)
    crc = zlib.crc32(fh.read(len(MAGIC)))
    while True:
        try:
            header = fh.read(_RECORD_HEADER.size)
            if len(header) < _RECORD_HEADER.size:
                raise EOFError("record header cut short")
            op, length = _RECORD_HEADER.unpack(header)
            if length > RECORD_SIZE_LIMIT:
                raise ValueError(f"record length {length} over the limit")
            if length > size - fh.tell():
                fh.seek(size)  # as far as a reader of the full length would get
                raise EOFError(f"record of {length} bytes runs past the end of the file")
            content = fh.read(length)
            if op == Op.DATA_END:
                expected = _U32.unpack_from(content)[0]
                if expected != 0 and expected != crc:
                    raise ValueError(f"data section CRC {crc:#x}, expected {expected:#x}")
            crc = zlib.crc32(content, zlib.crc32(header, crc))
            if indexed is not None and op == Op.MESSAGE_INDEX:
                if pending:
                    _add_index(pending[0], content, kinds)
                continue
            found = pending[:]
            pending.clear()
            if indexed is not None and op == Op.CHUNK:
                pending.append(IndexedChunk(_chunk_data(content)))
            else:
                found += _record(op, content, kinds, classify, buckets)
        except DataError:
            raise
        except Exception as exc:  # struct.error, zstd errors, bad UTF-8... from any record
            if fh.tell() >= size and not finished:
                return
            raise DataError(
                f"corrupt MCAP data at byte {fh.tell()} of {size} ({type(exc).__name__}: {exc})",
                file=path,
            ) from None
        yield from found
        if op == Op.FOOTER:
            return


def _register(
    channel: Channel, kinds: dict[int, int], classify: Callable[[Channel], int | None]
) -> None:
    kind = classify(channel)
    if kind is None:
        kinds.pop(channel.id, None)
    else:
        kinds[channel.id] = kind


_ZSTD: Any = None


def _decompress(compression: str, data: bytes, size: int) -> bytes:
    global _ZSTD
    if compression == "":
        return data
    if compression == "zstd":
        if _ZSTD is None:
            import zstandard

            _ZSTD = zstandard.ZstdDecompressor()
        return bytes(_ZSTD.decompress(data, max_output_size=size))
    if compression == "lz4":
        # optional (other writers' files): a missing lz4 is reported as a corrupt chunk's cause
        lz4_frame = importlib.import_module("lz4.frame")
        return bytes(lz4_frame.decompress(data))
    raise ValueError(f"unsupported chunk compression {compression!r}")


def _chunk_data(content: bytes) -> bytes:
    """The records of a chunk record, decompressed and their CRC checked."""
    _, _, usize, ucrc = _CHUNK_HEADER.unpack_from(content)
    at = _CHUNK_HEADER.size
    (n,) = _U32.unpack_from(content, at)
    compression = content[at + 4 : at + 4 + n].decode()
    at += 4 + n
    (n,) = _U64.unpack_from(content, at)
    at += 8
    if at + n > len(content):
        raise ValueError("chunk records run past the chunk")
    data = _decompress(compression, content[at : at + n], usize)
    if len(data) != usize:
        raise ValueError(f"chunk holds {len(data)} bytes, its header says {usize}")
    if ucrc != 0 and zlib.crc32(data) != ucrc:
        raise ValueError("chunk CRC mismatch")
    return data


def _add_index(chunk: IndexedChunk, content: bytes, kinds: dict[int, int]) -> None:
    """Keep a message index record's entries if its channel has a kind."""
    if len(content) < _INDEX_HEADER.size:
        chunk.damaged = f"message index record of {len(content)} bytes"
        return
    channel_id, n = _INDEX_HEADER.unpack_from(content)
    kind = kinds.get(channel_id)
    if kind is None:
        return
    if n % 16 or _INDEX_HEADER.size + n > len(content):
        chunk.damaged = f"message index of channel {channel_id} holds {n} bytes of entries"
        return
    entries = np.frombuffer(content, dtype="<u8", count=n // 8, offset=_INDEX_HEADER.size)
    chunk.add(kind, channel_id, entries.reshape(-1, 2))


def _record(
    op: int,
    content: bytes,
    kinds: dict[int, int],
    classify: Callable[[Channel], int | None],
    buckets: Buckets,
) -> list[Any]:
    if op == Op.CHUNK:
        return [*_split_chunk(_chunk_data(content), kinds, classify, buckets), FILLED]
    if op == Op.MESSAGE:
        channel_id, _, log_time, _ = _MESSAGE_HEADER.unpack_from(content)
        kind = kinds.get(channel_id)
        if kind is not None:
            buckets[kind][0].append(content[_MESSAGE_HEADER.size :])
            buckets[kind][1].append(log_time)
        return [FILLED]
    if op == Op.CHANNEL:
        channel = _parse(Channel, content)
        _register(channel, kinds, classify)
        return [channel]
    if op == Op.METADATA:
        return [_parse(Metadata, content)]
    if op == Op.ATTACHMENT:
        return [_parse(Attachment, content)]
    if op == Op.FOOTER:
        return [_parse(Footer, content)]
    return []  # header, schema, indexes, statistics, summary offsets, data end


def _split_chunk(
    data: bytes,
    kinds: dict[int, int],
    classify: Callable[[Channel], int | None],
    buckets: Buckets,
) -> list[Channel]:
    """Cut a chunk's message records out into the buckets; returns its channel records."""
    channels: list[Channel] = []
    unpack = _RECORD_HEADER.unpack_from
    unpack_msg = _MESSAGE_HEADER.unpack_from
    skip = _MESSAGE_HEADER.size
    get = kinds.get
    at, size = 0, len(data)
    # The hot loop of reading: one struct call and one slice per message.
    while at < size:
        op, length = unpack(data, at)
        at += 9
        end = at + length
        if end > size:
            raise ValueError("a record runs past the end of its chunk")
        if op == Op.MESSAGE:
            channel_id, _, log_time, _ = unpack_msg(data, at)
            kind = get(channel_id)
            if kind is not None:
                bucket = buckets[kind]
                bucket[0].append(data[at + skip : end])
                bucket[1].append(log_time)
        elif op == Op.CHANNEL:
            channel = _parse(Channel, data[at:end])
            _register(channel, kinds, classify)
            channels.append(channel)
        at = end
    return channels
