"""Read recorded flights: rosbag2 directories (metadata.yaml + .mcap / .db3) or single .mcap files.

:class:`BagReader` wraps ``rosbags.rosbag2.Reader`` and turns every problem a user can cause (a
wrong path, a damaged metadata.yaml, a missing or truncated storage file, a corrupt chunk found
while reading) into a :class:`BagError` whose message names the path, says what is wrong and,
where there is one, what to do about it. Messages come out as raw CDR bytes in log-time order;
decoding is :mod:`cloe_ros.io.messages`' job. No rclpy here.

Damage that leaves the records readable is found too: the chunks of an MCAP file are checked
against the message index the file holds after each of them (rosbags writes no chunk CRC), and at
the end the messages read are compared with the per-topic counts the bag lists.

A single ``.mcap`` file (no metadata.yaml) is read directly: rosbags takes topics, counts and times
from the file's own summary. sqlite3 (``.db3``) bags work too, because rosbags reads them.
"""

from __future__ import annotations

import heapq
import struct
from dataclasses import dataclass
from pathlib import Path
from typing import TYPE_CHECKING, Any, BinaryIO

import yaml
from rosbags.rosbag2 import Reader, ReaderError
from rosbags.rosbag2.metadata import parse_qos
from rosbags.rosbag2.reader import DirectoryReader
from rosbags.rosbag2.storage_mcap import McapReader, decompress, read_exact

from cloe_ros.io.errors import BagError

if TYPE_CHECKING:
    from collections.abc import Iterable, Iterator

    from rosbags.interfaces import Connection, Qos

MCAP_MAGIC = b'\x89MCAP0\r\n'
#: An MCAP file ends with a footer record (opcode 0x02, 20 bytes of content) and the magic.
MCAP_FOOTER_SIZE = 1 + 8 + 20 + len(MCAP_MAGIC)
STORAGE_SUFFIXES = {'mcap': '.mcap', 'sqlite3': '.db3'}
NS = 1_000_000_000


@dataclass(frozen=True)
class TopicInfo:
    """One recorded topic.

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


class BagReader:
    """A recorded bag, opened with ``with BagReader(path) as bag:`` (or ``open()``/``close()``).

    After opening: ``topics`` (name -> :class:`TopicInfo`), ``start_ns`` / ``end_ns`` (log time of
    the first / last message, int ns since the epoch; both 0 for a bag without messages),
    ``duration_s`` (``end_ns - start_ns`` in s), ``message_count`` and ``custom_data`` (the
    ``custom_data`` of ``metadata.yaml``; empty for a single storage file or when there is none).
    """

    def __init__(self, path: str | Path) -> None:
        self.path = Path(path)
        self.topics: dict[str, TopicInfo] = {}
        self.start_ns = 0
        self.end_ns = 0
        self.duration_s = 0.0
        self.message_count = 0
        self.custom_data: dict[str, str] = {}
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
        """Everything that can be checked before rosbags opens the bag; the parsed metadata
        (``None`` for a single storage file)."""
        path = self.path
        if not path.exists():
            msg = f'{path} does not exist'
            raise BagError(msg)
        if path.is_file():
            if path.suffix == '.mcap':
                _check_mcap_file(path, path)
                return None
            if path.suffix == '.db3':
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
            raise BagError(_no_metadata_message(path))
        metadata = _load_metadata(metapath, path)
        storage = metadata['storage_identifier']
        for name in metadata['relative_file_paths']:
            file = path / Path(name).name
            if not file.exists():
                msg = (
                    f'{path}: storage file {Path(name).name} listed in metadata.yaml is missing '
                    '(was the bag copied incompletely?)'
                )
                raise BagError(msg)
            if storage == 'mcap' and not metadata['compression_mode'] == 'file':
                _check_mcap_file(file, path)
        return metadata

    def _read_summary(self, reader: Reader, metadata: dict[str, Any] | None) -> None:
        """Fill ``topics``, times and count from an open rosbags reader."""
        stored_qos: dict[str, str] = {}
        custom = metadata.get('custom_data') if metadata is not None else None
        self.custom_data = (
            {str(k): str(v) for k, v in custom.items()} if isinstance(custom, dict) else {}
        )
        if metadata is not None:
            for entry in metadata['topics_with_message_count']:
                meta = entry['topic_metadata']
                stored_qos[meta['name']] = _qos_text(meta.get('offered_qos_profiles', ''))
        else:
            stored_qos = _mcap_channel_qos(reader)
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
        self.duration_s = (self.end_ns - self.start_ns) / NS

    # -- messages ------------------------------------------------------------------------------

    def messages(self, topics: Iterable[str] | None = None) -> Iterator[tuple[str, int, bytes]]:
        """``(topic, log_time_ns, raw CDR)`` of every message, in log-time order.

        ``topics`` selects topics (``None``: all); names the bag does not hold are ignored, so
        check :attr:`topics` first where a topic is required. Messages of one topic keep their
        recorded order. Damaged data found on the way raises :class:`BagError` naming the file,
        the chunk's byte offset and its topics where the storage tells them.
        """
        if self._reader is None:
            msg = f'{self.path} is not open: use `with BagReader(path) as bag:`'
            raise BagError(msg)
        wanted = set(self.topics) if topics is None else set(topics) & set(self.topics)
        if not wanted:
            return iter(())
        return self._messages(self._reader, wanted)

    def _messages(self, reader: Reader, wanted: set[str]) -> Iterator[tuple[str, int, bytes]]:
        storage = reader.storage
        parts = storage.storages if isinstance(storage, DirectoryReader) else [storage]
        if reader.compression_mode != 'message' and all(
            isinstance(p, McapReader) and p.chunks for p in parts
        ):
            # a file-compressed bag is read from temporary copies: name the bag, not them
            named = reader.compression_mode != 'file'
            source = (
                item
                for part in parts
                for item in self._mcap_chunk_messages(part, wanted, part.path if named else None)
            )
        else:
            source = self._guarded(reader, wanted)
        counts = dict.fromkeys(wanted, 0)
        for item in source:
            counts[item[0]] += 1
            yield item
        self._check_counts(counts)

    def _check_counts(self, counts: dict[str, int]) -> None:
        """Every message the bag lists was read: damage that leaves the records readable (a
        message whose header was overwritten, say) drops messages without an error on the way."""
        short = {t: n for t, n in sorted(counts.items()) if n < self.topics[t].count}
        if not short:
            return
        where = 'its summary' if self.path.is_file() else 'metadata.yaml'
        missing = sum(self.topics[t].count - n for t, n in short.items())
        detail = ', '.join(f'{t} {n} of {self.topics[t].count}' for t, n in short.items())
        msg = (
            f'{self.path}: {missing} of the messages {where} lists could not be read ({detail} '
            'read): the bag is damaged. `cloe bag recover` writes a bag with every message that '
            'can still be read.'
        )
        raise BagError(msg)

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
        self, part: McapReader, wanted: set[str], file: Path | None
    ) -> Iterator[tuple[str, int, bytes]]:
        """Merge the chunks of an indexed MCAP file by log time (ties: file order), as rosbags
        does, but with each chunk read and checked here, so that damage names the chunk. When a
        chunk cannot be read, every message that comes before its start in that order is still
        delivered, then the error is raised."""
        channel_map: dict[int, Connection] = {
            c.id: c for c in part.connections if c.topic in wanted
        }
        chunks = [
            chunk
            for chunk in part.chunks
            if any(chunk.channel_count.get(cid, 0) for cid in channel_map)
        ]
        # (log time, chunk offset, chunk, sequence in the chunk (-1: its start), connection, raw)
        heap: list[tuple] = [
            (c.message_start_time, c.chunk_start_offset, i, -1, None, None)
            for i, c in enumerate(chunks)
        ]
        heapq.heapify(heap)
        pending: dict[int, Iterator[tuple[int, tuple[int, Connection, bytes]]]] = {}
        error: BagError | None = None
        limit: tuple[int, int] | None = None  # the start of the earliest chunk that failed
        while heap and (limit is None or heap[0][:2] < limit):
            log_ns, offset, i, seq, conn, raw = heapq.heappop(heap)
            if seq < 0:
                try:
                    pending[i] = enumerate(
                        self._chunk(part, chunks[i], channel_map, file or self.path)
                    )
                except BagError as err:
                    if limit is None or (log_ns, offset) < limit:
                        limit, error = (log_ns, offset), err
                    continue
            else:
                yield conn.topic, log_ns, raw
            nxt = next(pending[i], None)
            if nxt is None:
                del pending[i]
            else:
                seq, (log_ns, conn, raw) = nxt
                heapq.heappush(heap, (log_ns, offset, i, seq, conn, raw))
        if error is not None:
            raise error

    def _chunk(
        self, part: McapReader, chunk: Any, channel_map: dict[int, Connection], file: Path
    ) -> list[tuple[int, Connection, bytes]]:
        """The wanted messages of one chunk in log-time order; :class:`BagError` naming the chunk
        if it is damaged."""
        try:
            assert part.bio is not None
            return _read_chunk(part.bio, chunk, channel_map)
        except Exception as err:  # damaged chunk
            topics = sorted(
                {channel_map[cid].topic for cid in chunk.channel_count if cid in channel_map}
            )
            t0 = (chunk.message_start_time - self.start_ns) / NS
            t1 = (chunk.message_end_time - self.start_ns) / NS
            msg = (
                f'{file}: corrupt chunk at byte offset '
                f'{chunk.chunk_start_offset} (messages of {", ".join(topics)} logged {t0:.3f}-'
                f'{t1:.3f} s into the bag): {_text(err)} The file is damaged; the messages '
                'before this chunk were read.'
            )
            raise BagError(msg) from err


# -- MCAP chunks ---------------------------------------------------------------------------------

_RECORD_HEAD = struct.Struct('<BQ')
_MESSAGE_HEAD = struct.Struct('<HIQQ')  # channel id, sequence, log time, publish time
_INDEX_ENTRY = struct.Struct('<QQ')  # log time, offset


class _Damage(ValueError):
    """Chunk data that contradict themselves or the file's index (internal)."""


def _read_chunk(
    bio: BinaryIO, chunk: Any, channel_map: dict[int, Connection]
) -> list[tuple[int, Connection, bytes]]:
    """The messages of ``chunk`` whose channel is in ``channel_map``, as ``(log time, connection,
    raw)`` in log-time order (recorded order for equal times). Besides rosbags' size and CRC
    checks, every record must parse, every message must lie in the chunk's time range, and the
    messages must be those the file's message index lists (rosbags writes no chunk CRC)."""
    bio.seek(chunk.chunk_start_offset + 9 + 24)
    (crc,) = struct.unpack('<I', read_exact(bio, 4))
    bio.seek(chunk.chunk_start_offset + 9 + 40 + len(chunk.compression))
    compressed = read_exact(bio, chunk.compressed_size)
    data = decompress(compressed, chunk.compression, chunk.uncompressed_size, crc)
    view = memoryview(data)
    found: set[tuple[int, int, int]] = set()
    out: list[tuple[int, Connection, bytes]] = []
    pos = 0
    while pos < len(view):
        if pos + _RECORD_HEAD.size > len(view):
            raise _Damage(f'The chunk ends inside a record header (at {pos}).')
        op, length = _RECORD_HEAD.unpack_from(view, pos)
        start = pos + _RECORD_HEAD.size
        if not (0x01 <= op <= 0x0F or op >= 0x80):
            raise _Damage(f'Invalid record opcode 0x{op:02x} at {pos} inside the chunk.')
        if length > len(view) - start:
            raise _Damage(f'The record at {pos} inside the chunk overruns it.')
        if op == 0x05:
            if length < _MESSAGE_HEAD.size:
                raise _Damage(f'The message record at {pos} is shorter than its header.')
            cid, _, log_ns, _ = _MESSAGE_HEAD.unpack_from(view, start)
            if not chunk.message_start_time <= log_ns <= chunk.message_end_time:
                msg = f"A message logged at {log_ns} ns lies outside the chunk's time range."
                raise _Damage(msg)
            found.add((cid, log_ns, pos))
            conn = channel_map.get(cid)
            if conn is not None:
                out.append(
                    (log_ns, conn, bytes(view[start + _MESSAGE_HEAD.size : start + length]))
                )
        pos = start + length
    if not crc:  # a matching CRC vouches for the data; without one the index is the check
        indexed = _chunk_index(bio, chunk)
        if found != indexed:
            msg = (
                f'Its messages differ from the message index: {len(indexed - found)} of '
                f'{len(indexed)} indexed messages not found, {len(found - indexed)} not indexed.'
            )
            raise _Damage(msg)
    out.sort(key=lambda m: m[0])
    return out


def _chunk_index(bio: BinaryIO, chunk: Any) -> set[tuple[int, int, int]]:
    """``(channel, log time, offset)`` of every message the chunk's message index records list."""
    out: set[tuple[int, int, int]] = set()
    for cid, offset in chunk.message_index_offsets.items():
        bio.seek(offset)
        op, length = _RECORD_HEAD.unpack(read_exact(bio, _RECORD_HEAD.size))
        body = read_exact(bio, length) if op == 0x07 and length >= 6 else b''
        if not body or struct.unpack_from('<H', body)[0] != cid:
            raise _Damage(f'The message index record of channel {cid} is damaged.')
        (size,) = struct.unpack_from('<I', body, 2)
        if size % _INDEX_ENTRY.size or 6 + size > len(body):
            raise _Damage(f'The message index record of channel {cid} is damaged.')
        out.update((cid, t, o) for t, o in _INDEX_ENTRY.iter_unpack(body[6 : 6 + size]))
    return out


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


def _check_mcap_file(file: Path, bag: Path) -> None:
    """Magic at both ends: a file without its footer is truncated (recorder killed)."""
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
        msg = f'cannot read {file}: {err.strerror or err}'
        raise BagError(msg) from err
    if size == 0:
        msg = f'{file} is empty: nothing was recorded; remove the bag {bag}'
        raise BagError(msg)
    if head == MCAP_MAGIC and size < len(MCAP_MAGIC) + 9:
        msg = (
            f'{file} holds the MCAP magic bytes and no record ({size} bytes): nothing was '
            f'recorded; remove the bag {bag}'
        )
        raise BagError(msg)
    if head != MCAP_MAGIC:
        msg = f'{file} is not an MCAP file (it does not start with the MCAP magic bytes)'
        raise BagError(msg)
    if tail != MCAP_MAGIC:
        msg = (
            f'{file} is truncated: it ends without the MCAP footer ({size} bytes; the recording '
            'was cut off, e.g. the recorder was killed or the disk filled up). Run '
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


def _mcap_channel_qos(reader: Reader) -> dict[str, str]:
    """offered_qos_profiles from the channel metadata of a single MCAP file."""
    out: dict[str, str] = {}
    storage = reader.storage
    for channel in getattr(storage, 'channels', {}).values():
        text = _qos_text(_channel_metadata(channel.metadata).get('offered_qos_profiles', ''))
        if text and channel.topic not in out:
            out[channel.topic] = text
    return out


def _channel_metadata(raw: bytes) -> dict[str, str]:
    """MCAP channel metadata: a sequence of (uint32 length, utf-8 key, uint32 length, value)."""
    out: dict[str, str] = {}
    pos = 0
    try:
        while pos < len(raw):
            items = []
            for _ in range(2):
                n = int.from_bytes(raw[pos : pos + 4], 'little')
                items.append(raw[pos + 4 : pos + 4 + n].decode())
                pos += 4 + n
            out[items[0]] = items[1]
    except UnicodeDecodeError:
        return out
    return out
