"""Read recorded flights: rosbag2 directories (metadata.yaml + .mcap / .db3) or single .mcap files.

:class:`BagReader` wraps ``rosbags.rosbag2.Reader`` and turns every problem a user can cause (a
wrong path, a damaged metadata.yaml, a missing or truncated storage file, a corrupt chunk found
while reading) into a :class:`BagError` whose message names the path, says what is wrong and,
where there is one, what to do about it. Messages come out as raw CDR bytes in log-time order;
decoding is :mod:`cloe_ros.io.messages`' job. No rclpy here.

A single ``.mcap`` file (no metadata.yaml) is read directly: rosbags takes topics, counts and times
from the file's own summary. sqlite3 (``.db3``) bags work too, because rosbags reads them.
"""

from __future__ import annotations

import heapq
from dataclasses import dataclass
from pathlib import Path
from typing import TYPE_CHECKING, Any

import yaml
from rosbags.rosbag2 import Reader, ReaderError
from rosbags.rosbag2.metadata import parse_qos
from rosbags.rosbag2.reader import DirectoryReader
from rosbags.rosbag2.storage_mcap import McapReader, msgsrc

from cloe_ros.errors import CloeError

if TYPE_CHECKING:
    from collections.abc import Iterable, Iterator

    from rosbags.interfaces import Connection, Qos

MCAP_MAGIC = b'\x89MCAP0\r\n'
#: An MCAP file ends with a footer record (opcode 0x02, 20 bytes of content) and the magic.
MCAP_FOOTER_SIZE = 1 + 8 + 20 + len(MCAP_MAGIC)
STORAGE_SUFFIXES = {'mcap': '.mcap', 'sqlite3': '.db3'}
NS = 1_000_000_000


class BagError(CloeError):
    """A bag that cannot be read, with a message naming the path and what is wrong."""


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
            for part in parts:
                yield from self._mcap_chunk_messages(part, wanted, part.path if named else None)
        else:
            yield from self._guarded(reader, wanted)

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
        """Merge the chunks of an indexed MCAP file by log time, as rosbags does, but with each
        chunk's reading guarded so an error names the chunk."""
        channel_map: dict[int, Connection] = {
            c.id: c for c in part.connections if c.topic in wanted
        }
        sources = [
            self._guarded_chunk(part, chunk, channel_map, file or self.path)
            for chunk in part.chunks
            if any(chunk.channel_count.get(cid, 0) for cid in channel_map)
        ]
        for log_ns, offset, conn, raw in heapq.merge(*sources):
            if offset and conn is not None and raw is not None:  # offset 0: start marker
                yield conn.topic, log_ns, raw

    def _guarded_chunk(
        self, part: McapReader, chunk: Any, channel_map: dict[int, Connection], file: Path
    ) -> Iterator[Any]:
        try:
            assert part.bio is not None
            yield from msgsrc(
                chunk, channel_map, chunk.message_start_time, chunk.message_end_time + 1, part.bio
            )
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


# -- helpers -----------------------------------------------------------------------------------


def _text(err: BaseException) -> str:
    text = str(err).strip() or type(err).__name__
    return text if text.endswith('.') else text + '.'


def _no_metadata_message(path: Path) -> str:
    storage_files = sorted(p.name for p in path.iterdir() if p.suffix in {'.mcap', '.db3'})
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
