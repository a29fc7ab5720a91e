"""MCAP container, written in small chunks, indexed at close, recoverable after a crash.

Why our own writer: ``mcap.writer.Writer`` cannot close a chunk on demand (its chunk is closed
only by size), so a crash-safe log that uses it must go unchunked — and unchunked files have no
message indexes (the official TypeScript ``McapIndexedReader`` sees 0 messages; Foxglove opens
large files through the index) and, with the default index types, an empty ChunkIndex group
that ``pymcap-cli doctor`` reports as ``SUMMARY_OFFSET_WITHOUT_GROUP``. The record classes and
their byte layout are ``mcap``'s own (``mcap.records``, MCAP spec v0); this module only decides
*when* records are written:

- Schema and Channel records go to the data section as soon as they are registered (outside
  chunks), so a reader of a cut file knows every channel before its first message.
- Messages collect in the open chunk; :meth:`ChunkedWriter.close_chunk` writes the Chunk
  record (uncompressed, CRC'd) followed by one MessageIndex record per channel in it. The caller
  decides when (by time, by size, before anything that must be durable). ``chunk_bytes`` bounds
  a chunk's size.
- Metadata and Attachment records go outside chunks (closing the open chunk first).
- :meth:`ChunkedWriter.finish` writes DataEnd (with the data-section CRC), the summary (schemas,
  channels, statistics, chunk / attachment / metadata indexes, one SummaryOffset per non-empty
  group), the Footer (with the summary CRC) and the closing magic.

Recovery: :func:`scan` reads a file that may be cut at any byte and returns every complete
unit — a chunk counts only together with all of its message indexes, which the writer emits in
the same write — with the index needed to finish it. :func:`finish_truncated` cuts the
incomplete tail and appends DataEnd + a full summary + Footer, so a killed log becomes an
indexed MCAP file again without rewriting a single recorded byte.
"""

from __future__ import annotations

import io
import struct
import zlib
from collections import defaultdict
from dataclasses import dataclass, field
from typing import BinaryIO, Callable, Iterator

from mcap.data_stream import ReadDataStream, RecordBuilder
from mcap.exceptions import McapError
from mcap.opcode import Opcode
from mcap.records import (
    Attachment,
    AttachmentIndex,
    Channel,
    ChunkIndex,
    DataEnd,
    Footer,
    Header,
    Message,
    MessageIndex,
    Metadata,
    MetadataIndex,
    Schema,
    Statistics,
    SummaryOffset,
)

MAGIC = b"\x89MCAP0\r\n"
_REC_HEAD = struct.Struct("<BQ")
_MSG_HEAD = struct.Struct("<HIQQ")  # channel id, sequence, log time, publish time
_CHUNK_HEAD = struct.Struct("<QQQI")  # start, end, uncompressed size, uncompressed crc


class McapFileError(ValueError):
    """A file that is not MCAP, or a chunk that cannot be decoded; the message names the offset."""


# --------------------------------------------------------------------------------------------
# The index (what the summary section holds)
# --------------------------------------------------------------------------------------------
@dataclass
class McapIndex:
    """Everything the summary section is built from (kept while writing, or rebuilt by ``scan``)."""

    schemas: dict[int, Schema] = field(default_factory=dict)
    channels: dict[int, Channel] = field(default_factory=dict)
    chunk_indexes: list[ChunkIndex] = field(default_factory=list)
    attachment_indexes: list[AttachmentIndex] = field(default_factory=list)
    metadata_indexes: list[MetadataIndex] = field(default_factory=list)
    channel_message_counts: dict[int, int] = field(default_factory=lambda: defaultdict(int))
    message_count: int = 0
    message_start_time: int = 0
    message_end_time: int = 0

    def count_message(self, channel_id: int, log_time: int) -> None:
        if self.message_count == 0:
            self.message_start_time = self.message_end_time = log_time
        else:
            self.message_start_time = min(self.message_start_time, log_time)
            self.message_end_time = max(self.message_end_time, log_time)
        self.message_count += 1
        self.channel_message_counts[channel_id] += 1

    def statistics(self) -> Statistics:
        return Statistics(
            message_count=self.message_count,
            schema_count=len(self.schemas),
            channel_count=len(self.channels),
            attachment_count=len(self.attachment_indexes),
            metadata_count=len(self.metadata_indexes),
            chunk_count=len(self.chunk_indexes),
            message_start_time=self.message_start_time,
            message_end_time=self.message_end_time,
            channel_message_counts=dict(self.channel_message_counts),
        )


def summary_and_footer(index: McapIndex, summary_start: int) -> bytes:
    """Summary section + Footer + closing magic for a file whose DataEnd ends at ``summary_start``.

    Only non-empty groups get a SummaryOffset (an offset to an empty group is what
    ``pymcap-cli doctor`` rejects as SUMMARY_OFFSET_WITHOUT_GROUP).
    """
    b = RecordBuilder()
    offsets: list[SummaryOffset] = []

    def group(opcode: int, records: list) -> None:
        if not records:
            return
        start = b.count
        for r in records:
            r.write(b)
        offsets.append(SummaryOffset(group_opcode=opcode, group_start=summary_start + start, group_length=b.count - start))

    group(Opcode.SCHEMA, [index.schemas[k] for k in sorted(index.schemas)])
    group(Opcode.CHANNEL, [index.channels[k] for k in sorted(index.channels)])
    group(Opcode.STATISTICS, [index.statistics()])
    group(Opcode.CHUNK_INDEX, index.chunk_indexes)
    group(Opcode.ATTACHMENT_INDEX, index.attachment_indexes)
    group(Opcode.METADATA_INDEX, index.metadata_indexes)
    summary_offset_start = summary_start + b.count
    for o in offsets:
        o.write(b)
    summary = b.end()
    footer_head = struct.pack("<BQQQ", Opcode.FOOTER, 8 + 8 + 4, summary_start, summary_offset_start)
    crc = zlib.crc32(footer_head, zlib.crc32(summary))
    Footer(summary_start=summary_start, summary_offset_start=summary_offset_start, summary_crc=crc).write(b)
    return summary + b.end() + MAGIC


# --------------------------------------------------------------------------------------------
# Writing
# --------------------------------------------------------------------------------------------
class ChunkedWriter:
    """Writes an MCAP file to ``fh`` (opened for binary writing at position 0). Not thread-safe.

    chunk_bytes: a chunk is closed once its records reach this many bytes (and whenever the
    caller calls :meth:`close_chunk`). Nothing is flushed or fsync'd here; that is the caller's.
    """

    def __init__(self, fh: BinaryIO, *, chunk_bytes: int = 256 * 1024) -> None:
        if chunk_bytes < 1:
            raise ValueError(f"chunk_bytes must be >= 1, given {chunk_bytes}")
        self._fh = fh
        self.chunk_bytes = int(chunk_bytes)
        self.index = McapIndex()
        self._pos = 0
        self._crc = 0
        self._chunk = RecordBuilder()
        self._chunk_msgs: dict[int, list[tuple[int, int]]] = {}
        self._chunk_start = 0
        self._chunk_end = 0
        self._finished = False

    @property
    def position(self) -> int:
        """Bytes handed to ``fh`` so far."""
        return self._pos

    @property
    def pending_messages(self) -> int:
        """Messages in the open chunk (not yet handed to ``fh``)."""
        return sum(len(v) for v in self._chunk_msgs.values())

    def _out(self, data: bytes) -> None:
        self._fh.write(data)
        self._crc = zlib.crc32(data, self._crc)
        self._pos += len(data)

    def _record(self, rec) -> tuple[int, int]:
        """Write one record outside chunks; its (offset, length)."""
        b = RecordBuilder()
        rec.write(b)
        data = b.end()
        offset = self._pos
        self._out(data)
        return offset, len(data)

    def start(self, *, profile: str = "", library: str = "remaster") -> None:
        self._out(MAGIC)
        self._record(Header(profile=profile, library=library))

    def add_schema(self, name: str, encoding: str, data: bytes) -> int:
        sid = len(self.index.schemas) + 1
        schema = Schema(id=sid, name=name, encoding=encoding, data=data)
        self.index.schemas[sid] = schema
        self._record(schema)
        return sid

    def add_channel(self, topic: str, message_encoding: str, schema_id: int, metadata: dict[str, str] | None = None) -> int:
        if schema_id != 0 and schema_id not in self.index.schemas:
            raise ValueError(f"channel {topic}: unknown schema id {schema_id}; known: {sorted(self.index.schemas)}")
        cid = len(self.index.channels) + 1
        channel = Channel(id=cid, topic=topic, message_encoding=message_encoding, schema_id=schema_id, metadata=dict(metadata or {}))
        self.index.channels[cid] = channel
        self._record(channel)
        return cid

    def add_message(self, channel_id: int, log_time: int, data: bytes, publish_time: int, sequence: int = 0) -> None:
        if channel_id not in self.index.channels:
            raise ValueError(f"message on unknown channel id {channel_id}; known: {sorted(self.index.channels)}")
        if not self._chunk_msgs:
            self._chunk_start = self._chunk_end = log_time
        else:
            self._chunk_start = min(self._chunk_start, log_time)
            self._chunk_end = max(self._chunk_end, log_time)
        self._chunk_msgs.setdefault(channel_id, []).append((log_time, self._chunk.count))
        Message(channel_id=channel_id, sequence=sequence, log_time=log_time, publish_time=publish_time, data=data).write(self._chunk)
        self.index.count_message(channel_id, log_time)
        if self._chunk.count >= self.chunk_bytes:
            self.close_chunk()

    def close_chunk(self) -> bool:
        """Write the open chunk and its message indexes (one ``fh.write``); False if it was empty."""
        if not self._chunk_msgs:
            return False
        records = self._chunk.end()
        b = RecordBuilder()
        b.start_record(Opcode.CHUNK)
        b.write(_CHUNK_HEAD.pack(self._chunk_start, self._chunk_end, len(records), zlib.crc32(records)))
        b.write_prefixed_string("")
        b.write8(len(records))
        b.write(records)
        b.finish_record()
        chunk_length = b.count
        mi_offsets: dict[int, int] = {}
        for cid in sorted(self._chunk_msgs):
            mi_offsets[cid] = self._pos + b.count
            MessageIndex(channel_id=cid, records=self._chunk_msgs[cid]).write(b)
        data = b.end()
        self.index.chunk_indexes.append(
            ChunkIndex(
                message_start_time=self._chunk_start,
                message_end_time=self._chunk_end,
                chunk_start_offset=self._pos,
                chunk_length=chunk_length,
                message_index_offsets=mi_offsets,
                message_index_length=len(data) - chunk_length,
                compression="",
                compressed_size=len(records),
                uncompressed_size=len(records),
            )
        )
        self._chunk_msgs = {}
        self._out(data)
        return True

    def add_metadata(self, name: str, data: dict[str, str]) -> None:
        self.close_chunk()
        offset, length = self._record(Metadata(name=name, metadata=dict(data)))
        self.index.metadata_indexes.append(MetadataIndex(offset=offset, length=length, name=name))

    def add_attachment(self, create_time: int, log_time: int, name: str, media_type: str, data: bytes) -> None:
        self.close_chunk()
        offset, length = self._record(Attachment(create_time=create_time, log_time=log_time, name=name, media_type=media_type, data=data))
        self.index.attachment_indexes.append(
            AttachmentIndex(offset=offset, length=length, log_time=log_time, create_time=create_time, data_size=len(data),
                            name=name, media_type=media_type)
        )

    def finish(self) -> None:
        """Close the open chunk; write DataEnd, the summary, the Footer and the magic. Idempotent."""
        if self._finished:
            return
        self.close_chunk()
        self._record(DataEnd(data_section_crc=self._crc))
        self._fh.write(summary_and_footer(self.index, self._pos))
        self._finished = True


# --------------------------------------------------------------------------------------------
# Reading a file that may be cut anywhere
# --------------------------------------------------------------------------------------------
@dataclass
class ScanResult:
    """What :func:`scan` found. ``good_end``: byte offset after the last complete unit."""

    index: McapIndex = field(default_factory=McapIndex)
    size: int = 0
    has_header: bool = False
    good_end: int = 0
    data_end_start: int | None = None
    complete: bool = False
    stop_reason: str = ""


def _decompress(compression: str, data: bytes, size: int, where: str) -> bytes:
    if compression == "":
        return data
    try:
        if compression == "lz4":
            import lz4.frame

            return lz4.frame.decompress(data)
        if compression == "zstd":
            import zstandard

            return zstandard.ZstdDecompressor().decompress(data, max_output_size=size)
    except ImportError as exc:
        raise McapFileError(f"{where}: chunk compressed with {compression}; install the {exc.name} package to read it") from exc
    raise McapFileError(f"{where}: unknown chunk compression {compression!r} (known: '', lz4, zstd)")


def _chunk_records(body: bytes, where: str) -> tuple[tuple[int, int], bytes]:
    """((start, end) log times, uncompressed records) of a Chunk record body; CRC checked."""
    start, end, usize, crc = _CHUNK_HEAD.unpack_from(body, 0)
    (clen,) = struct.unpack_from("<I", body, 28)
    compression = body[32 : 32 + clen].decode("utf-8")
    p = 32 + clen
    (rlen,) = struct.unpack_from("<Q", body, p)
    records = _decompress(compression, body[p + 8 : p + 8 + rlen], usize, where)
    if len(records) != usize or (crc != 0 and zlib.crc32(records) != crc):
        raise McapFileError(f"{where}: chunk CRC or size mismatch (corrupt chunk)")
    return (start, end), records


def _iter_raw(buf: bytes, start: int = 0) -> Iterator[tuple[int, int, int]]:
    """(opcode, body start, body end) of each record in ``buf`` from ``start``; stops at a cut one."""
    p, n = start, len(buf)
    while p + 9 <= n:
        op, length = _REC_HEAD.unpack_from(buf, p)
        if op == 0 or length > n - p - 9:
            return
        yield op, p + 9, p + 9 + length
        p += 9 + length


MessageSink = Callable[[Channel, int, int, bytes], None]


def scan(fh: BinaryIO, size: int, *, wanted: Callable[[Channel], bool] = lambda ch: False, on_message: MessageSink | None = None,
         on_metadata: Callable[[Metadata], None] | None = None, where: str = "MCAP file") -> ScanResult:
    """Read every complete unit of an MCAP file that may be cut at any byte (a killed writer).

    A unit is a record outside chunks, or a Chunk together with all the MessageIndex records of
    its channels (written in one go by :class:`ChunkedWriter`). Stops at the first incomplete or
    unreadable unit, or at DataEnd (then reads on to the Footer only to tell ``complete``).
    ``on_message(channel, log_time, sequence, data)`` is called for channels with ``wanted(ch)``
    in file order; other messages are only counted. Raises McapFileError if the file does not
    start with the MCAP magic.
    """
    res = ScanResult(size=size)
    fh.seek(0)
    magic = fh.read(len(MAGIC))
    if magic != MAGIC[: len(magic)]:
        raise McapFileError(f"{where}: not an MCAP file (starts with {magic!r}, expected {MAGIC!r})")
    if len(magic) < len(MAGIC):
        res.stop_reason = "cut inside the magic"
        return res
    res.good_end = len(MAGIC)
    idx = res.index
    offset = len(MAGIC)
    pending: tuple[ChunkIndex, set[int], list] | None = None  # a chunk waiting for its message indexes

    def read_record() -> tuple[int, bytes] | None:
        nonlocal offset
        head = fh.read(9)
        if len(head) < 9:
            return None
        op, length = _REC_HEAD.unpack(head)
        if op == 0 or length > size - offset - 9:
            return None
        body = fh.read(length)
        if len(body) < length:
            return None
        offset += 9 + length
        return op, body

    def commit(msgs: list) -> None:
        for ch, log_time, seq, data in msgs:
            idx.count_message(ch.id, log_time)
            if on_message is not None and wanted(ch):
                on_message(ch, log_time, seq, data)

    while True:
        rec_start = offset
        got = read_record()
        if got is None:
            res.stop_reason = "end of file" if rec_start >= size else f"record cut by the end of the file at byte {rec_start}"
            break
        op, body = got
        if pending is not None:
            ci, missing, msgs = pending
            if op == Opcode.MESSAGE_INDEX:
                (cid,) = struct.unpack_from("<H", body, 0)
                if cid in missing:
                    missing.discard(cid)
                    ci.message_index_offsets[cid] = rec_start
                    ci.message_index_length = offset - ci.chunk_start_offset - ci.chunk_length
                    if not missing:
                        idx.chunk_indexes.append(ci)
                        commit(msgs)
                        pending = None
                        res.good_end = offset
                    continue
            res.stop_reason = f"chunk at byte {ci.chunk_start_offset} lacks message indexes for channels {sorted(missing)}"
            pending = None
            break
        try:
            if op == Opcode.HEADER:
                res.has_header = True
            elif op in (Opcode.SCHEMA, Opcode.CHANNEL):
                rec = (Schema if op == Opcode.SCHEMA else Channel).read(ReadDataStream(io.BytesIO(body)))
                (idx.schemas if op == Opcode.SCHEMA else idx.channels)[rec.id] = rec
            elif op == Opcode.MESSAGE:  # an unchunked file (older remaster logs)
                cid, seq, log_time, _ = _MSG_HEAD.unpack_from(body, 0)
                ch = idx.channels.get(cid)
                if ch is None:
                    res.stop_reason = f"message of undeclared channel {cid} at byte {rec_start}"
                    break
                commit([(ch, log_time, seq, body[_MSG_HEAD.size :])])
            elif op == Opcode.CHUNK:
                (t0, t1), records = _chunk_records(body, f"{where} byte {rec_start}")
                msgs: list = []
                for rop, b0, b1 in _iter_raw(records):
                    if rop == Opcode.MESSAGE:
                        cid, seq, log_time, _ = _MSG_HEAD.unpack_from(records, b0)
                        ch = idx.channels.get(cid)
                        if ch is None:
                            raise McapFileError(f"{where} byte {rec_start}: chunk holds a message of undeclared channel {cid}")
                        msgs.append((ch, log_time, seq, records[b0 + _MSG_HEAD.size : b1]))
                    elif rop in (Opcode.SCHEMA, Opcode.CHANNEL):
                        rec = (Schema if rop == Opcode.SCHEMA else Channel).read(ReadDataStream(io.BytesIO(records[b0:b1])))
                        (idx.schemas if rop == Opcode.SCHEMA else idx.channels)[rec.id] = rec
                ci = ChunkIndex(message_start_time=t0, message_end_time=t1, chunk_start_offset=rec_start, chunk_length=offset - rec_start,
                                message_index_offsets={}, message_index_length=0, compression="", compressed_size=0,
                                uncompressed_size=len(records))
                (clen,) = struct.unpack_from("<I", body, 28)
                ci.compression = body[32 : 32 + clen].decode("utf-8")
                (ci.compressed_size,) = struct.unpack_from("<Q", body, 32 + clen)
                channels_in = {m[0].id for m in msgs}
                if channels_in:
                    pending = (ci, channels_in, msgs)
                    continue
                idx.chunk_indexes.append(ci)
            elif op == Opcode.METADATA:
                rec = Metadata.read(ReadDataStream(io.BytesIO(body)))
                idx.metadata_indexes.append(MetadataIndex(offset=rec_start, length=offset - rec_start, name=rec.name))
                if on_metadata is not None:
                    on_metadata(rec)
            elif op == Opcode.ATTACHMENT:
                rec = Attachment.read(ReadDataStream(io.BytesIO(body)))
                idx.attachment_indexes.append(AttachmentIndex(offset=rec_start, length=offset - rec_start, log_time=rec.log_time,
                                                              create_time=rec.create_time, data_size=len(rec.data), name=rec.name,
                                                              media_type=rec.media_type))
            elif op == Opcode.DATA_END:
                res.data_end_start = rec_start
                res.good_end = offset
                res.complete = _read_to_footer(fh, offset, size)
                res.stop_reason = "closed" if res.complete else "summary incomplete"
                return res
            # message indexes of chunks already taken, chunk indexes etc.: nothing to take
        except (McapError, McapFileError, struct.error, UnicodeDecodeError, ValueError, IndexError) as exc:
            res.stop_reason = f"unreadable record (opcode 0x{op:02x}) at byte {rec_start}: {exc}"
            break
        res.good_end = offset
    return res


def _read_to_footer(fh: BinaryIO, offset: int, size: int) -> bool:
    """After DataEnd: skip summary records to the Footer; True if Footer and magic are whole."""
    fh.seek(offset)
    while True:
        head = fh.read(9)
        if len(head) < 9:
            return False
        op, length = _REC_HEAD.unpack(head)
        if op == 0 or length > size - offset - 9:
            return False
        if op == Opcode.FOOTER:
            fh.seek(length, io.SEEK_CUR)
            return fh.read(len(MAGIC)) == MAGIC
        fh.seek(length, io.SEEK_CUR)
        offset += 9 + length


def finish_truncated(fh: BinaryIO, res: ScanResult) -> int:
    """Make a cut file (``fh`` opened ``r+b``) a complete, indexed MCAP file again.

    Cuts only what follows the last complete unit (bytes that never held a complete record),
    then appends DataEnd (CRC 0: not computed) + the summary rebuilt by ``scan`` + Footer.
    A file cut before its header was complete becomes an empty valid MCAP file. Returns the
    number of bytes cut.
    """
    tail = RecordBuilder()
    if not res.has_header:
        cut = 0
        head = MAGIC
        Header(profile="", library="remaster").write(tail)
        res = ScanResult()  # nothing in it counts
    else:
        cut = res.data_end_start if res.data_end_start is not None else res.good_end
        head = b""
    DataEnd(data_section_crc=0).write(tail)
    body = head + tail.end()
    fh.truncate(cut)
    fh.seek(cut)
    fh.write(body + summary_and_footer(res.index, cut + len(body)))
    return res.size - cut if res.size else 0
