"""Read recorded flights: rosbag2 directories (metadata.yaml + .mcap / .db3) or single .mcap files.

:class:`BagReader` turns every problem a user can cause (a wrong path, a damaged metadata.yaml, a
missing or truncated storage file, a corrupt chunk found while reading) into a :class:`BagError`
whose message names the path, says what is wrong and, where there is one, what to do about it.
Messages come out as raw CDR bytes in log-time order; decoding is :mod:`cloe_ros.io.messages`'
job. No rclpy here.

MCAP files are read with the ``mcap`` library's records (:mod:`cloe_ros.io.mcap_records`): the
summary (schemas, channels, chunk indexes, statistics) when the bag is opened, each chunk when its
messages are due. The file is what counts, not ``metadata.yaml``:

* topics, types, message counts and times come from the files' summaries; where metadata.yaml
  says otherwise, :attr:`BagReader.metadata_mismatch` says how (``cloe bag info`` prints it as a
  warning). Messages metadata.yaml lists beyond those read are an error at the end of reading (the
  bag may have lost them), more messages than it lists are read;
* a channel whose message encoding is not ``cdr``, or whose schema is not a ROS 2 message
  definition, is refused when the bag is opened, naming the topic;
* the CRCs MCAP defines are checked where the file has them (bags written by this package have
  all): the summary CRC when the bag is opened, each chunk's CRC when it is read, the data
  section CRC once every message was read. A chunk without CRC (rosbags writes none) is checked
  against the message index the file holds after it. Damage names the file, the chunk (its number
  and byte offset) and the topics whose messages it holds; every message before the chunk is
  delivered first.

At the end of reading the messages read are also compared with the counts listed, so damage that
leaves the records readable does not go unseen. rosbags (``rosbags.rosbag2.Reader``) reads the
bags this path does not: sqlite3 (``.db3``) storage, per-message compression and MCAP files
without chunk index; their counts come from metadata.yaml.
"""

from __future__ import annotations

import errno
import heapq
import os
from dataclasses import dataclass, field
from pathlib import Path
from typing import TYPE_CHECKING, Any, BinaryIO

import yaml
from mcap.exceptions import McapError
from mcap.records import (
    Channel,
    Chunk,
    ChunkIndex,
    DataEnd,
    Footer,
    Header,
    Message,
    MessageIndex,
    Schema,
    Statistics,
)
from mcap.stream_reader import StreamReader
from rosbags.rosbag2 import Reader, ReaderError
from rosbags.rosbag2.metadata import parse_qos
from rosbags.rosbag2.reader import DirectoryReader

from cloe_ros.io import mcap_records as mr
from cloe_ros.io.errors import BagError

if TYPE_CHECKING:
    from collections.abc import Iterable, Iterator

    from rosbags.interfaces import Qos

__all__ = ['BagError', 'BagReader', 'TopicInfo', 'check_bag', 'missing_message', 'qos_profiles']

MCAP_MAGIC = mr.MAGIC
#: An MCAP file ends with a footer record (opcode 0x02, 20 bytes of content) and the magic.
MCAP_FOOTER_SIZE = mr.FOOTER_SIZE + mr.MAGIC_SIZE
STORAGE_SUFFIXES = {'mcap': '.mcap', 'sqlite3': '.db3'}
NS = 1_000_000_000
#: Schema encodings that carry a ROS 2 message definition (MCAP ``ros2`` profile, and what
#: rosbag2 writes for IDL-only types).
ROS2_SCHEMA_ENCODINGS = ('ros2msg', 'ros2idl', 'omgidl')


@dataclass(frozen=True)
class TopicInfo:
    """One recorded topic.

    ``count`` is the number of messages the bag's storage holds (for MCAP, its summary).
    ``offered_qos`` is the QoS of the recorded publishers as stored in the bag: a YAML list of
    profiles (rosbag2's ``offered_qos_profiles``), or ``''`` when none was recorded. Parse it with
    :func:`qos_profiles`.
    """

    name: str
    msgtype: str
    count: int
    offered_qos: str


def qos_profiles(offered_qos: str) -> list[Qos]:
    """The QoS profiles of :attr:`TopicInfo.offered_qos` (``[]`` when none was recorded)."""
    if not offered_qos.strip():
        return []
    try:
        return parse_qos(offered_qos)
    except (ReaderError, TypeError, AttributeError) as err:
        msg = f'offered QoS profiles {offered_qos!r} cannot be parsed: {err}'
        raise BagError(msg) from err


def missing_message(path: Path) -> str:
    """Why ``path`` cannot be used although a path was given: it does not exist, it is a
    symbolic link loop or a broken link, or it cannot be reached."""
    try:
        os.stat(path)
    except OSError as err:
        if err.errno == errno.ELOOP:
            return f'{path}: too many levels of symbolic links (a symbolic link loop)'
        if os.path.islink(path):
            target = os.readlink(path)
            return f'{path} is a broken symbolic link (to {target}, which does not exist)'
        if err.errno in (errno.ENOENT, errno.ENOTDIR):
            return f'{path} does not exist'
        return f'cannot access {path}: {err.strerror or err}'
    return f'{path} does not exist'


# -- MCAP files --------------------------------------------------------------------------------


@dataclass
class McapFile:
    """What the summary of one complete MCAP file says, read with the mcap library.

    ``path`` is the file read (a temporary copy for a whole-file compressed bag) and ``label``
    the one to name in messages. ``channel_counts`` and the times come from the statistics, or
    (without them) from the message indexes or a scan of the file. ``data_end`` is the offset of
    the ``DataEnd`` record (the data section lies before it) and ``data_crc`` its CRC (0: none).
    """

    path: Path
    label: Path
    header: Header
    schemas: dict[int, Schema] = field(default_factory=dict)
    channels: dict[int, Channel] = field(default_factory=dict)
    chunk_indexes: list[ChunkIndex] = field(default_factory=list)
    channel_counts: dict[int, int] = field(default_factory=dict)
    start_ns: int = 0
    end_ns: int = 0
    data_end: int | None = None
    data_crc: int = 0
    data_crc_checked: bool = False

    @property
    def message_count(self) -> int:
        return sum(self.channel_counts.values())


def _read_exact(fh: BinaryIO, size: int, what: str, file: Path) -> bytes:
    data = fh.read(size)
    if len(data) != size:
        msg = f'{file}: {what} is cut off by the end of the file'
        raise BagError(msg)
    return data


def _record_at(fh: BinaryIO, offset: int, size: int, what: str, file: Path) -> tuple[int, bytes]:
    """``(opcode, body)`` of the record at ``offset`` of a file of ``size`` bytes."""
    fh.seek(offset)
    op, length = mr.read_head(_read_exact(fh, mr.RECORD_HEAD_SIZE, what, file))
    if length > size - offset - mr.RECORD_HEAD_SIZE:
        msg = f'{file}: {what} at byte {offset} overruns the file: the file is damaged'
        raise BagError(msg)
    return op, _read_exact(fh, length, what, file)


def read_mcap_summary(file: Path, bag: Path, label: Path | None = None) -> McapFile:
    """The summary of a complete ``.mcap`` (footer and magic checked first), its summary CRC
    checked, its channels checked to be ROS 2 CDR; :class:`BagError` naming the problem."""
    label = label or file
    _check_mcap_file(file, bag, label)
    try:
        with file.open('rb') as fh:
            return _read_summary_of(fh, file, file.stat().st_size, bag, label)
    except OSError as err:
        msg = f'cannot read {label}: {err.strerror or err}'
        raise BagError(msg) from err


def _read_summary_of(fh: BinaryIO, file: Path, size: int, bag: Path, label: Path) -> McapFile:
    damaged = f'the file is damaged; `cloe bag recover {bag}` writes a bag with what can be read'
    try:
        op, body = _record_at(fh, mr.MAGIC_SIZE, size, 'the header record', label)
        header = mr.parse_record(op, body) if op == mr.Opcode.HEADER else None
        footer_at = size - mr.MAGIC_SIZE - mr.FOOTER_SIZE
        op, body = _record_at(fh, footer_at, size, 'the footer', label)
        footer = mr.parse_record(op, body) if op == mr.Opcode.FOOTER else None
    except mr.RecordError as err:
        msg = f'{label}: its header or footer record does not parse ({err}): {damaged}'
        raise BagError(msg) from err
    if not isinstance(header, Header):
        msg = f'{label}: its first record is not an MCAP header: {damaged}'
        raise BagError(msg)
    if not isinstance(footer, Footer):
        msg = f'{label}: it ends with the MCAP magic but without a footer record: {damaged}'
        raise BagError(msg)
    if header.profile != 'ros2':
        msg = (
            f'{label}: its MCAP profile is {header.profile!r}, not ros2: it is not a ROS 2 '
            'recording'
        )
        raise BagError(msg)
    out = McapFile(file, label, header)
    data_start = mr.MAGIC_SIZE
    if footer.summary_start:
        if not data_start < footer.summary_start <= footer_at:
            where = footer.summary_start
            msg = f'{label}: its footer points outside the file ({where}): {damaged}'
            raise BagError(msg)
        fh.seek(footer.summary_start)
        summary = _read_exact(fh, footer_at - footer.summary_start, 'the summary', label)
        if footer.summary_crc:
            crc = mr.crc_of_range(fh, footer.summary_start, footer_at + mr.FOOTER_CRC_PREFIX)
            if crc != footer.summary_crc:
                msg = (
                    f'{label}: its summary (the index at the end of the file) does not match '
                    f'its CRC (CRC-32 {crc:#010x}, the footer records '
                    f'{footer.summary_crc:#010x}): '
                    f'{damaged}'
                )
                raise BagError(msg)
        statistics = None
        try:
            for _, op, body in mr.iter_records(summary):
                record = mr.parse_record(op, body)
                if isinstance(record, Schema):
                    out.schemas[record.id] = record
                elif isinstance(record, Channel):
                    out.channels[record.id] = record
                elif isinstance(record, ChunkIndex):
                    out.chunk_indexes.append(record)
                elif isinstance(record, Statistics):
                    statistics = record
        except mr.RecordError as err:
            msg = f'{label}: its summary (the index at the end of the file) is damaged ({err}): '
            raise BagError(msg + damaged) from err
        out.chunk_indexes.sort(key=lambda c: c.chunk_start_offset)
        data_end = footer.summary_start - mr.DATA_END_SIZE
        if statistics is not None:
            out.channel_counts = {c: n for c, n in statistics.channel_message_counts.items() if n}
            if statistics.message_count:
                out.start_ns = statistics.message_start_time
                out.end_ns = statistics.message_end_time
        elif out.chunk_indexes:
            _count_from_message_indexes(fh, size, out)
        else:
            _scan_counts(fh, out, damaged)
    else:
        data_end = footer_at - mr.DATA_END_SIZE
        _scan_counts(fh, out, damaged)
    if data_end >= data_start:
        fh.seek(data_end)
        raw = fh.read(mr.DATA_END_SIZE)
        if len(raw) == mr.DATA_END_SIZE and mr.read_head(raw) == (mr.Opcode.DATA_END, 4):
            record = mr.parse_record(mr.Opcode.DATA_END, raw[mr.RECORD_HEAD_SIZE :])
            assert isinstance(record, DataEnd)
            out.data_end, out.data_crc = data_end, record.data_section_crc
    _check_channels(out)
    return out


def _count_from_message_indexes(fh: BinaryIO, size: int, out: McapFile) -> None:
    """Counts and times of a summary without statistics: from the chunks' message indexes."""
    counts: dict[int, int] = {}
    for chunk in out.chunk_indexes:
        for cid, offset in chunk.message_index_offsets.items():
            op, body = _record_at(fh, offset, size, 'a message index', out.label)
            record = mr.parse_record(op, body) if op == mr.Opcode.MESSAGE_INDEX else None
            if isinstance(record, MessageIndex):
                counts[cid] = counts.get(cid, 0) + len(record.records)
    out.channel_counts = {c: n for c, n in counts.items() if n}
    if out.chunk_indexes and out.channel_counts:
        out.start_ns = min(c.message_start_time for c in out.chunk_indexes)
        out.end_ns = max(c.message_end_time for c in out.chunk_indexes)


def _scan_counts(fh: BinaryIO, out: McapFile, damaged: str) -> None:
    """Declarations, counts and times of a file without summary: read from its records."""
    fh.seek(0)
    counts: dict[int, int] = {}
    times: list[int] = []
    try:
        for record in StreamReader(fh, skip_magic=False).records:
            if isinstance(record, Schema):
                out.schemas.setdefault(record.id, record)
            elif isinstance(record, Channel):
                out.channels.setdefault(record.id, record)
            elif isinstance(record, Message):
                counts[record.channel_id] = counts.get(record.channel_id, 0) + 1
                times.append(record.log_time)
    except (McapError, ValueError, OSError, UnicodeDecodeError) as err:
        msg = f'{out.label}: its records do not parse ({_text(err)}): {damaged}'
        raise BagError(msg) from err
    out.channel_counts = counts
    if times:
        out.start_ns, out.end_ns = min(times), max(times)


def _check_channels(mcap: McapFile) -> None:
    """Every channel carries ROS 2 CDR with a ROS 2 message definition as its schema."""
    for channel in mcap.channels.values():
        topic = channel.topic
        if channel.message_encoding != 'cdr':
            msg = (
                f'{mcap.label}: topic {topic} is encoded as {channel.message_encoding!r}; only '
                'cdr (ROS 2 CDR, what rosbag2 records) can be read'
            )
            raise BagError(msg)
        schema = mcap.schemas.get(channel.schema_id)
        if schema is None:
            what = 'has no schema' if channel.schema_id == 0 else (
                f'refers to schema {channel.schema_id}, which the file does not hold')  # fmt: skip
            msg = f'{mcap.label}: topic {topic} {what}: its message type is unknown'
            raise BagError(msg)
        if schema.encoding not in ROS2_SCHEMA_ENCODINGS:
            msg = (
                f'{mcap.label}: topic {topic} has a schema ({schema.name}) in encoding '
                f'{schema.encoding!r}; expected a ROS 2 message definition '
                f'({", ".join(ROS2_SCHEMA_ENCODINGS)})'
            )
            raise BagError(msg)


class _Damage(ValueError):
    """Chunk data that contradict themselves, their CRC or the file's index (internal)."""


def _read_chunk(
    fh: BinaryIO, size: int, index: ChunkIndex, wanted: dict[int, str]
) -> list[tuple[int, str, bytes]]:
    """The messages of the chunk ``index`` points at whose channel is in ``wanted`` (id ->
    topic), as ``(log time, topic, raw)`` in log-time order (recorded order for equal times).
    The chunk's header must agree with the summary's index of it, its records must decompress to
    the size and CRC it states, every record must parse, every message lie in the chunk's time
    range, and (a chunk without CRC) its messages must be those the message index lists."""
    try:
        op, body = _record_at(fh, index.chunk_start_offset, size, 'the chunk', Path())
    except BagError as err:
        raise _Damage('The chunk is cut off by the end of the file.') from err
    if op != mr.Opcode.CHUNK or mr.RECORD_HEAD_SIZE + len(body) != index.chunk_length:
        msg = (
            f'The record there ({mr.opcode_name(op)}, {len(body)} bytes) is not the chunk the '
            'summary lists.'
        )
        raise _Damage(msg)
    try:
        chunk = mr.parse_record(op, body)
        assert isinstance(chunk, Chunk)
        header = (chunk.message_start_time, chunk.message_end_time, chunk.uncompressed_size,
                  chunk.compression, len(chunk.data))  # fmt: skip
        listed = (index.message_start_time, index.message_end_time, index.uncompressed_size,
                  index.compression, index.compressed_size)  # fmt: skip
        if header != listed:
            msg = (
                "Its header (times, sizes, compression) disagrees with the summary's index of it: "
                f'{header} against {listed}.'
            )
            raise _Damage(msg)
        data = mr.chunk_records(chunk)
        found: set[tuple[int, int, int]] = set()
        out: list[tuple[int, str, bytes]] = []
        for pos, op, rec in mr.iter_records(data):
            if not mr.known_opcode(op):
                raise _Damage(f'Invalid record opcode 0x{op:02x} at {pos} inside the chunk.')
            if op != mr.Opcode.MESSAGE:
                continue
            channel_id, log_ns, data = mr.message_fields(rec)
            if not chunk.message_start_time <= log_ns <= chunk.message_end_time:
                msg = f"A message logged at {log_ns} ns lies outside the chunk's time range."
                raise _Damage(msg)
            found.add((channel_id, log_ns, pos))
            topic = wanted.get(channel_id)
            if topic is not None:
                out.append((log_ns, topic, data))
    except mr.RecordError as err:
        raise _Damage(str(err)[:1].upper() + str(err)[1:]) from err
    if not chunk.uncompressed_crc:  # a matching CRC vouches for the data; without one the index
        indexed = _chunk_index(fh, size, index)
        if found != indexed:
            msg = (
                f'Its messages differ from the message index: {len(indexed - found)} of '
                f'{len(indexed)} indexed messages not found, {len(found - indexed)} not indexed.'
            )
            raise _Damage(msg)
    out.sort(key=lambda m: m[0])
    return out


def _chunk_index(fh: BinaryIO, size: int, index: ChunkIndex) -> set[tuple[int, int, int]]:
    """``(channel, log time, offset)`` of every message the chunk's message index records list."""
    out: set[tuple[int, int, int]] = set()
    for cid, offset in index.message_index_offsets.items():
        try:
            op, body = _record_at(fh, offset, size, 'a message index', Path())
            record = mr.parse_record(op, body) if op == mr.Opcode.MESSAGE_INDEX else None
        except (BagError, mr.RecordError):
            record = None
        if not isinstance(record, MessageIndex) or record.channel_id != cid:
            raise _Damage(f'The message index record of channel {cid} is damaged.')
        out.update((cid, t, o) for t, o in record.records)
    return out


# -- the reader --------------------------------------------------------------------------------


class BagReader:
    """A recorded bag, opened with ``with BagReader(path) as bag:`` (or ``open()``/``close()``).

    After opening: ``topics`` (name -> :class:`TopicInfo`), ``start_ns`` / ``end_ns`` (log time of
    the first / last message, int ns since the epoch; both 0 for a bag without messages),
    ``duration_s`` (``end_ns - start_ns`` in s), ``message_count``, ``custom_data`` (the
    ``custom_data`` of ``metadata.yaml``; empty for a single storage file or when there is none),
    ``files`` (the storage files) and ``metadata_mismatch`` (what metadata.yaml says that the
    files contradict, one sentence each; empty when they agree or there is no metadata.yaml).
    """

    def __init__(self, path: str | Path) -> None:
        self.path = Path(path)
        self.topics: dict[str, TopicInfo] = {}
        self.start_ns = 0
        self.end_ns = 0
        self.duration_s = 0.0
        self.message_count = 0
        self.custom_data: dict[str, str] = {}
        self.files: list[Path] = []
        self.storage = ''
        self.compression_mode = ''
        self.metadata_mismatch: list[str] = []
        #: messages per topic the bag lists (the larger of metadata.yaml's and the file's count)
        self.listed_counts: dict[str, int] = {}
        self._mcap: list[McapFile] | None = None
        self._metadata_counts: dict[str, int] = {}
        self._reader: Reader | None = None

    # -- opening -------------------------------------------------------------------------------

    def open(self) -> None:
        """Check the bag and read its metadata; raises :class:`BagError` on any problem."""
        if self._reader is not None:
            msg = f'{self.path} is already open'
            raise BagError(msg)
        metadata = self._check_layout()
        reader = Reader(self.path)
        try:
            reader.open()
        except Exception as err:  # whatever rosbags trips over is a broken bag
            msg = f'{self.path}: cannot open the bag: {_text(err)}'
            raise BagError(msg) from err
        try:
            if self._mcap is None and self.storage == 'mcap':  # whole-file compressed
                storage = reader.storage
                parts = storage.storages if isinstance(storage, DirectoryReader) else [storage]
                self._mcap = [
                    read_mcap_summary(Path(p.path), self.path, label=self.path) for p in parts
                ]
            self._read_summary(reader, metadata)
        except BaseException:
            reader.close()
            raise
        self._reader = reader

    def close(self) -> None:
        reader, self._reader = self._reader, None
        if reader is not None:
            reader.close()

    def __enter__(self) -> BagReader:
        self.open()
        return self

    def __exit__(self, *exc_info: object) -> None:
        self.close()

    def _check_layout(self) -> dict[str, Any] | None:
        """Everything that can be checked before rosbags opens the bag (the path, metadata.yaml,
        each MCAP file's magic, footer and summary); the parsed metadata (``None`` for a single
        storage file)."""
        path = self.path
        if not path.exists():
            raise BagError(missing_message(path))
        if path.is_file():
            if path.suffix == '.mcap':
                self.files, self.storage = [path], 'mcap'
                self._mcap = [read_mcap_summary(path, path)]
                return None
            if path.suffix == '.db3':
                self.files, self.storage = [path], 'sqlite3'
                return None
            if path.name == 'metadata.yaml':
                msg = f'{path} is the metadata of a bag: pass its directory {path.parent} instead'
                raise BagError(msg)
            msg = (
                f'{path} is a file, not a bag: expected a rosbag2 directory holding '
                'metadata.yaml and .mcap files (or a single .mcap file)'
            )
            raise BagError(msg)
        if not path.is_dir():
            msg = f'{path} is neither a directory nor a file'
            raise BagError(msg)
        metapath = path / 'metadata.yaml'
        if not metapath.exists():
            if os.path.lexists(metapath):
                raise BagError(missing_message(metapath))
            raise BagError(_no_metadata_message(path))
        metadata = _load_metadata(metapath, path)
        self.storage = storage = metadata['storage_identifier']
        self.compression_mode = metadata['compression_mode']
        mcap = []
        self.files = []
        for name in metadata['relative_file_paths']:
            file = path / Path(name).name
            self.files.append(file)
            if not file.exists():
                if os.path.lexists(file):
                    raise BagError(missing_message(file))
                msg = (
                    f'{path}: storage file {Path(name).name} listed in metadata.yaml is missing '
                    '(was the bag copied incompletely?)'
                )
                raise BagError(msg)
            if storage == 'mcap' and not metadata['compression_mode'] == 'file':
                mcap.append(read_mcap_summary(file, path))
        self._mcap = mcap if storage == 'mcap' and metadata['compression_mode'] != 'file' else None
        return metadata

    def _read_summary(self, reader: Reader, metadata: dict[str, Any] | None) -> None:
        """Fill ``topics``, times and counts: from the MCAP files' summaries, else from rosbags
        (metadata.yaml); compare them with metadata.yaml."""
        stored_qos: dict[str, str] = {}
        custom = metadata.get('custom_data') if metadata is not None else None
        self.custom_data = (
            {str(k): str(v) for k, v in custom.items()} if isinstance(custom, dict) else {}
        )
        meta_types: dict[str, str] = {}
        if metadata is not None:
            for entry in metadata['topics_with_message_count']:
                meta = entry['topic_metadata']
                stored_qos[meta['name']] = _qos_text(meta.get('offered_qos_profiles', ''))
                meta_types[meta['name']] = meta['type']
                self._metadata_counts[meta['name']] = (
                    self._metadata_counts.get(meta['name'], 0) + entry['message_count']
                )
        if self._mcap is None:
            self._summary_from_rosbags(reader, stored_qos)
        else:
            self._summary_from_files(self._mcap, stored_qos, meta_types)
        if metadata is not None and self._mcap is not None:
            self.metadata_mismatch = self._mismatch(metadata, meta_types)
        self.listed_counts = {
            t: max(info.count, self._metadata_counts.get(t, 0)) for t, info in self.topics.items()
        }
        self.duration_s = (self.end_ns - self.start_ns) / NS

    def _summary_from_rosbags(self, reader: Reader, stored_qos: dict[str, str]) -> None:
        topics: dict[str, TopicInfo] = {}
        for name, info in reader.topics.items():
            if info.msgtype is None:
                types = sorted({c.msgtype for c in info.connections})
                msg = f'{self.path}: topic {name} is recorded with several types {types}'
                raise BagError(msg)
            topics[name] = TopicInfo(name, info.msgtype, info.msgcount, stored_qos.get(name, ''))
        self.topics = dict(sorted(topics.items()))
        self.message_count = reader.message_count
        if self.message_count:
            self.start_ns = reader.start_time
            self.end_ns = reader.end_time - 1  # rosbags' end_time is exclusive
        else:
            self.start_ns = self.end_ns = 0

    def _summary_from_files(
        self, files: list[McapFile], stored_qos: dict[str, str], meta_types: dict[str, str]
    ) -> None:
        types: dict[str, set[str]] = {}
        counts: dict[str, int] = {}
        channel_qos: dict[str, str] = {}
        for mcap in files:
            for cid, channel in mcap.channels.items():
                topic = channel.topic
                types.setdefault(topic, set()).add(mcap.schemas[channel.schema_id].name)
                counts[topic] = counts.get(topic, 0) + mcap.channel_counts.get(cid, 0)
                text = _qos_text(channel.metadata.get('offered_qos_profiles', ''))
                if text and topic not in channel_qos:
                    channel_qos[topic] = text
        for topic, msgtype in meta_types.items():  # listed by metadata.yaml, without a channel
            types.setdefault(topic, {msgtype})
            counts.setdefault(topic, 0)
        topics = {}
        for name, found in types.items():
            if len(found) > 1:
                msg = f'{self.path}: topic {name} is recorded with several types {sorted(found)}'
                raise BagError(msg)
            qos = stored_qos.get(name) or channel_qos.get(name, '')
            topics[name] = TopicInfo(name, found.pop(), counts[name], qos)
        self.topics = dict(sorted(topics.items()))
        self.message_count = sum(counts.values())
        spans = [(m.start_ns, m.end_ns) for m in files if m.message_count]
        if spans:
            self.start_ns = min(s for s, _ in spans)
            self.end_ns = max(e for _, e in spans)
        else:
            self.start_ns = self.end_ns = 0

    def _mismatch(self, metadata: dict[str, Any], meta_types: dict[str, str]) -> list[str]:
        """Where metadata.yaml and the files disagree, one sentence each."""
        out = []
        files = ', '.join(f.name for f in self.files)
        for name, info in self.topics.items():
            if name not in meta_types:
                out.append(
                    f'{name} ({info.count} messages) is in {files} but not in metadata.yaml'
                )
                continue
            if meta_types[name] != info.msgtype:
                out.append(
                    f'metadata.yaml says {name} is {meta_types[name]}, {files} says {info.msgtype}'
                )
            listed = self._metadata_counts.get(name, 0)
            if listed != info.count:
                out.append(
                    f'metadata.yaml lists {listed} messages of {name}, {files} holds {info.count}'
                )
        listed = metadata['message_count']
        if not out and listed != self.message_count:
            out.append(
                f'metadata.yaml lists {listed} messages in all, {files} holds {self.message_count}'
            )
        return out

    # -- messages ------------------------------------------------------------------------------

    def messages(self, topics: Iterable[str] | None = None) -> Iterator[tuple[str, int, bytes]]:
        """``(topic, log_time_ns, raw CDR)`` of every message, in log-time order.

        ``topics`` selects topics (``None``: all); names the bag does not hold are ignored, so
        check :attr:`topics` first where a topic is required. Messages of one topic keep their
        recorded order. Damaged data found on the way raises :class:`BagError` naming the file,
        the chunk's number, byte offset and topics where the storage tells them.
        """
        if self._reader is None:
            msg = f'{self.path} is not open: use `with BagReader(path) as bag:`'
            raise BagError(msg)
        wanted = set(self.topics) if topics is None else set(topics) & set(self.topics)
        if not wanted:
            return iter(())
        return self._messages(self._reader, wanted)

    def _messages(self, reader: Reader, wanted: set[str]) -> Iterator[tuple[str, int, bytes]]:
        files = self._mcap
        if (
            files is not None
            and reader.compression_mode != 'message'
            and all(f.chunk_indexes or not f.message_count for f in files)
        ):
            source = (item for f in files for item in self._mcap_chunk_messages(f, wanted))
        else:
            source = self._guarded(reader, wanted)
        counts = dict.fromkeys(wanted, 0)
        for item in source:
            counts[item[0]] += 1
            yield item
        self._check_counts(counts)
        for f in files or ():
            self._check_data_crc(f)

    def _check_counts(self, counts: dict[str, int]) -> None:
        """Every message the bag lists was read: damage that leaves the records readable (a
        message whose header was overwritten, say) drops messages without an error on the way,
        and messages metadata.yaml lists beyond what the files hold may have been lost."""
        listed = self.listed_counts
        short = {t: n for t, n in sorted(counts.items()) if n < listed[t]}
        if not short:
            return
        by_metadata = any(self._metadata_counts.get(t, 0) > self.topics[t].count for t in short)
        where = 'metadata.yaml' if by_metadata or not self.path.is_file() else 'its summary'
        missing = sum(listed[t] - n for t, n in short.items())
        detail = ', '.join(f'{t} {n} of {listed[t]}' for t, n in short.items())
        msg = (
            f'{self.path}: {missing} of the messages {where} lists could not be read ({detail} '
            'read): the bag is damaged. `cloe bag recover` writes a bag with every message that '
            'can still be read.'
        )
        raise BagError(msg)

    def _check_data_crc(self, mcap: McapFile) -> None:
        """The data section CRC of the ``DataEnd`` record, once per file (reads the file)."""
        if not mcap.data_crc or mcap.data_crc_checked or mcap.data_end is None:
            return
        try:
            with mcap.path.open('rb') as fh:
                crc = mr.crc_of_range(fh, 0, mcap.data_end)
        except OSError as err:
            msg = f'cannot read {mcap.label}: {err.strerror or err}'
            raise BagError(msg) from err
        if crc != mcap.data_crc:
            msg = (
                f'{mcap.label}: its data section does not match its CRC (CRC-32 {crc:#010x}, its '
                f'DataEnd record says {mcap.data_crc:#010x}), although every chunk matched its '
                'own: bytes outside the messages were changed (a message index, a chunk header '
                f'or a declaration). The file is damaged; `cloe bag recover {self.path}` writes a '
                'bag with every message that can still be read.'
            )
            raise BagError(msg)
        mcap.data_crc_checked = True

    def _guarded(self, reader: Reader, wanted: set[str]) -> Iterator[tuple[str, int, bytes]]:
        """rosbags' own iteration, errors translated (sqlite3, unindexed MCAP, compression)."""
        source = reader.messages([c for c in reader.connections if c.topic in wanted])
        last: tuple[str, int] | None = None
        count = 0
        try:
            for conn, log_ns, raw in source:
                yield conn.topic, log_ns, raw
                last = (conn.topic, log_ns)
                count += 1
        except Exception as err:  # damaged storage data
            where = 'before the first message'
            if last is not None:
                where = (
                    f'after message {count} ({last[0]} at {(last[1] - self.start_ns) / NS:.3f} s '
                    'into the bag)'
                )
            msg = f'{self.path}: damaged data {where}: {_text(err)}'
            raise BagError(msg) from err

    def _mcap_chunk_messages(
        self, mcap: McapFile, wanted: set[str]
    ) -> Iterator[tuple[str, int, bytes]]:
        """Merge the chunks of an indexed MCAP file by log time (ties: file order), each chunk
        read and checked here, so that damage names the chunk. When a chunk cannot be read, every
        message that comes before its start in that order is still delivered, then the error is
        raised."""
        channels = {cid: c.topic for cid, c in mcap.channels.items() if c.topic in wanted}
        numbers = {c.chunk_start_offset: k + 1 for k, c in enumerate(mcap.chunk_indexes)}
        chunks = [
            c
            for c in mcap.chunk_indexes
            if not c.message_index_offsets
            or any(cid in channels for cid in c.message_index_offsets)
        ]
        # (log time, chunk offset, chunk, sequence in the chunk (-1: its start), topic, raw)
        heap: list[tuple] = [
            (c.message_start_time, c.chunk_start_offset, i, -1, None, None)
            for i, c in enumerate(chunks)
        ]
        heapq.heapify(heap)
        pending: dict[int, Iterator[tuple[int, tuple[int, str, bytes]]]] = {}
        error: BagError | None = None
        limit: tuple[int, int] | None = None  # the start of the earliest chunk that failed
        try:
            fh = mcap.path.open('rb')
        except OSError as err:
            msg = f'cannot read {mcap.label}: {err.strerror or err}'
            raise BagError(msg) from err
        with fh:
            size = os.fstat(fh.fileno()).st_size
            while heap and (limit is None or heap[0][:2] < limit):
                log_ns, offset, i, seq, topic, raw = heapq.heappop(heap)
                if seq < 0:
                    try:
                        found = self._chunk(fh, size, mcap, chunks[i], channels, numbers)
                    except BagError as err:
                        if limit is None or (log_ns, offset) < limit:
                            limit, error = (log_ns, offset), err
                        continue
                    pending[i] = enumerate(found)
                else:
                    yield topic, log_ns, raw
                nxt = next(pending[i], None)
                if nxt is None:
                    del pending[i]
                else:
                    seq, (log_ns, topic, raw) = nxt
                    heapq.heappush(heap, (log_ns, offset, i, seq, topic, raw))
        if error is not None:
            raise error

    def _chunk(
        self,
        fh: BinaryIO,
        size: int,
        mcap: McapFile,
        index: ChunkIndex,
        channels: dict[int, str],
        numbers: dict[int, int],
    ) -> list[tuple[int, str, bytes]]:
        """The wanted messages of one chunk in log-time order; :class:`BagError` naming the chunk
        if it is damaged."""
        try:
            return _read_chunk(fh, size, index, channels)
        except (_Damage, OSError) as err:  # damaged chunk
            topics = sorted({channels[c] for c in index.message_index_offsets if c in channels})
            t0 = (index.message_start_time - self.start_ns) / NS
            t1 = (index.message_end_time - self.start_ns) / NS
            number = numbers[index.chunk_start_offset]
            msg = (
                f'{mcap.label}: corrupt chunk at byte offset {index.chunk_start_offset} '
                f'(messages of {", ".join(topics) or "unknown topics"} logged {t0:.3f}-{t1:.3f} s '
                f'into the bag): {_text(err)} It is chunk {number} of '
                f'{len(mcap.chunk_indexes)} in the file. The file is damaged; the messages before '
                'this chunk were read.'
            )
            raise BagError(msg) from err


# -- helpers -----------------------------------------------------------------------------------


def _text(err: BaseException) -> str:
    text = str(err).strip() or type(err).__name__
    return text if text.endswith('.') else text + '.'


def _no_metadata_message(path: Path) -> str:
    storage_files = sorted(p.name for p in path.iterdir() if p.suffix in {'.mcap', '.db3'})
    complete = [n for n in storage_files if n.endswith('.mcap') and _has_footer(path / n)]
    if complete and len(complete) == len(storage_files):
        files = ' or '.join(str(path / n) for n in complete)
        return (
            f'{path} has no metadata.yaml but holds {", ".join(storage_files)}, which ends with '
            f'its MCAP footer (complete): pass the .mcap file itself ({files}), or run '
            f'`cloe bag recover {path}` to rebuild the bag around it.'
        )
    if storage_files:
        return (
            f'{path} has no metadata.yaml but holds {", ".join(storage_files)}: the recording '
            f'was probably not closed (recorder killed?). Run `cloe bag recover {path}` to '
            'rebuild the bag.'
        )
    bags = sorted(p.name for p in path.iterdir() if (p / 'metadata.yaml').is_file())
    if bags:
        return (
            f'{path} is not a bag (no metadata.yaml) but a folder of bags: pass one of '
            f'{", ".join(bags)}'
        )
    return (
        f'{path} is not a rosbag2 bag: it has no metadata.yaml (expected a directory holding '
        'metadata.yaml and .mcap files)'
    )


_REQUIRED: list[tuple[str, type | tuple[type, ...]]] = [
    ('version', int),
    ('storage_identifier', str),
    ('relative_file_paths', list),
    ('starting_time.nanoseconds_since_epoch', int),
    ('duration.nanoseconds', int),
    ('message_count', int),
    ('topics_with_message_count', list),
]
_REQUIRED_TOPIC: list[tuple[str, type | tuple[type, ...]]] = [
    ('message_count', int),
    ('topic_metadata.name', str),
    ('topic_metadata.type', str),
    ('topic_metadata.serialization_format', str),
]


def _lookup(dct: Any, dotted: str, where: str, metapath: Path, types) -> Any:
    value = dct
    for key in dotted.split('.'):
        if not isinstance(value, dict) or key not in value:
            msg = f'{metapath} is missing the key {where}{dotted}: the metadata is incomplete'
            raise BagError(msg)
        value = value[key]
    if not isinstance(value, types) or isinstance(value, bool):
        msg = (
            f'{metapath}: {where}{dotted} is {value!r}, expected '
            f'{getattr(types, "__name__", types)}'
        )
        raise BagError(msg)
    return value


def _load_metadata(metapath: Path, bag: Path) -> dict[str, Any]:
    """metadata.yaml's ``rosbag2_bagfile_information``, checked for what reading needs."""
    try:
        text = metapath.read_text()
    except UnicodeDecodeError as err:
        msg = f'{metapath} is not a text file ({err.reason}): it is not rosbag2 metadata'
        raise BagError(msg) from err
    except OSError as err:
        msg = f'cannot read {metapath}: {err.strerror or err}'
        raise BagError(msg) from err
    try:
        dct = yaml.safe_load(text)
    except yaml.YAMLError as err:
        mark = getattr(err, 'problem_mark', None)
        where = f' (line {mark.line + 1}, column {mark.column + 1})' if mark else ''
        problem = getattr(err, 'problem', None) or ' '.join(str(err).split())
        msg = f'{metapath} is not valid YAML{where}: {problem}'
        raise BagError(msg) from err
    if not isinstance(dct, dict) or not isinstance(dct.get('rosbag2_bagfile_information'), dict):
        msg = f'{metapath} is not rosbag2 metadata: it has no rosbag2_bagfile_information mapping'
        raise BagError(msg)
    meta = dct['rosbag2_bagfile_information']
    prefix = 'rosbag2_bagfile_information.'
    for dotted, types in _REQUIRED:
        _lookup(meta, dotted, prefix, metapath, types)
    if meta['version'] > 9:
        msg = (
            f'{metapath}: rosbag2 format version {meta["version"]} is newer than this reader '
            'knows (up to 9); update rosbags'
        )
        raise BagError(msg)
    storage = meta['storage_identifier']
    if storage not in STORAGE_SUFFIXES:
        msg = (
            f'{bag}: storage {storage!r} is not supported (expected mcap or sqlite3); convert '
            'the bag with `ros2 bag convert` to MCAP'
        )
        raise BagError(msg)
    mode = str(meta.get('compression_mode') or '').lower()
    fmt = str(meta.get('compression_format') or '').lower()
    meta['compression_mode'] = '' if mode == 'none' else mode
    if meta['compression_mode'] and fmt != 'zstd':
        msg = f'{bag}: compression format {fmt!r} is not supported (only zstd)'
        raise BagError(msg)
    for i, entry in enumerate(meta['topics_with_message_count']):
        where = f'{prefix}topics_with_message_count[{i}].'
        for dotted, types in _REQUIRED_TOPIC:
            _lookup(entry, dotted, where, metapath, types)
        topic = entry['topic_metadata']
        if topic['serialization_format'] != 'cdr':
            msg = (
                f'{bag}: topic {topic["name"]} is serialized as '
                f'{topic["serialization_format"]!r}; only cdr (the ROS 2 default) can be read'
            )
            raise BagError(msg)
    return meta


def _check_mcap_file(file: Path, bag: Path, label: Path | None = None) -> None:
    """Magic at both ends: a file without its footer is truncated (recorder killed)."""
    file_label = label or file
    try:
        size = file.stat().st_size
        with file.open('rb') as fh:
            head = fh.read(len(MCAP_MAGIC))
            if size >= len(MCAP_MAGIC) + MCAP_FOOTER_SIZE:
                fh.seek(size - len(MCAP_MAGIC))
                tail = fh.read(len(MCAP_MAGIC))
            else:
                tail = b''
    except OSError as err:
        msg = f'cannot read {file_label}: {err.strerror or err}'
        raise BagError(msg) from err
    if size == 0:
        msg = f'{file_label} is empty: nothing was recorded; remove the bag {bag}'
        raise BagError(msg)
    if head == MCAP_MAGIC and size < len(MCAP_MAGIC) + 9:
        msg = (
            f'{file_label} holds the MCAP magic bytes and no record ({size} bytes): nothing was '
            f'recorded; remove the bag {bag}'
        )
        raise BagError(msg)
    if head != MCAP_MAGIC:
        msg = f'{file_label} is not an MCAP file (it does not start with the MCAP magic bytes)'
        raise BagError(msg)
    if tail != MCAP_MAGIC:
        msg = (
            f'{file_label} is truncated: it ends without the MCAP footer ({size} bytes; the '
            'recording was cut off, e.g. the recorder was killed or the disk filled up). Run '
            f'`cloe bag recover {bag}` to rescue the complete messages.'
        )
        raise BagError(msg)


def _has_footer(file: Path) -> bool:
    """Whether an .mcap file has the MCAP magic at both ends (its recording was closed)."""
    try:
        size = file.stat().st_size
        if size < len(MCAP_MAGIC) + MCAP_FOOTER_SIZE:
            return False
        with file.open('rb') as fh:
            head = fh.read(len(MCAP_MAGIC))
            fh.seek(size - len(MCAP_MAGIC))
            return head == MCAP_MAGIC == fh.read(len(MCAP_MAGIC))
    except OSError:
        return False


def check_bag(path: str | Path) -> None:
    """Everything about a bag that can be checked without reading it (what :meth:`BagReader.open`
    checks first: the path, metadata.yaml, the storage files' MCAP magic at both ends); raises
    :class:`BagError` saying what is wrong and what to do."""
    BagReader(path)._check_layout()


def _qos_text(stored: Any) -> str:
    """offered_qos_profiles as stored: a YAML string (rosbag2 <= 8) or a list (version 9)."""
    if not stored or (isinstance(stored, str) and stored.strip() in {'', '[]'}):
        return ''
    if isinstance(stored, str):
        return stored
    return yaml.safe_dump(stored, default_flow_style=False, sort_keys=True)
