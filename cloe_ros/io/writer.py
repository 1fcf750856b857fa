"""A crash-safe rosbag2 writer: MCAP storage with CRCs, ROS 2 Jazzy types, schemas embedded.

:class:`BagWriter` writes a rosbag2 directory (``metadata.yaml`` + one ``.mcap``, rosbag2 version
9, ``ros_distro: jazzy``) with :class:`~cloe_ros.io.mcap_writer.McapWriter`, which writes the file
the ``mcap`` library's writer writes, byte for byte, at a fraction of its cost per message. It
fills the CRCs MCAP defines: each chunk's CRC of its uncompressed records, the data section CRC
(``DataEnd``) and the summary CRC (footer). Readers that check them (``cloe bag info``,
``cloe infer``, ``cloe bag recover``, the mcap tools) find a changed bit anywhere in the file,
zstd-compressed chunk data included. The file follows the MCAP ``ros2`` profile: ``ros2msg``
schemas, ``cdr`` channels carrying ``offered_qos_profiles``, a ``rosbag2`` metadata record;
rosbags, the mcap readers and ``ros2 bag`` read it.

:meth:`BagWriter.flush` closes the pending chunk and hands the file to the operating system.
Whatever was written before the last ``flush()`` survives a SIGKILL of the process: the ``.mcap``
then lacks its summary and footer and the directory its ``metadata.yaml``, and
``cloe bag recover`` (:mod:`cloe_ros.io.recover`) turns it back into a complete bag. The same
holds after a write failure (a full disk): the writer stops at the first one, see
:class:`BagWriter`.

No rclpy here: messages are raw CDR bytes, times are int nanoseconds.
"""

from __future__ import annotations

import shutil
from collections.abc import Mapping, Sequence
from dataclasses import dataclass
from importlib.metadata import PackageNotFoundError, version
from pathlib import Path
from types import TracebackType
from typing import BinaryIO

import yaml
from mcap.well_known import MessageEncoding, Profile, SchemaEncoding
from rosbags.interfaces import Qos
from rosbags.rosbag2.errors import ReaderError
from rosbags.rosbag2.metadata import dump_qos_v9, parse_qos

from cloe_ros import __version__
from cloe_ros.io.errors import WriterError
from cloe_ros.io.mcap_writer import McapWriter
from cloe_ros.io.messages import typestore
from cloe_ros.io.msgdefs import MSGDEFS

__all__ = ['CHUNK_SIZE', 'COMPRESSIONS', 'ROS_DISTRO', 'BagWriter', 'WriterError']

#: Values of the ``compression`` argument: MCAP chunk compression with zstd, or none.
COMPRESSIONS = ('zstd', 'none')
#: A chunk is written to the file once its records exceed this many bytes (as rosbag2 and
#: rosbags do).
CHUNK_SIZE = 1 << 20
#: The ROS 2 distribution whose message types the bags hold (``ros_distro`` of metadata.yaml).
ROS_DISTRO = 'jazzy'
#: rosbag2's bag format version written to metadata.yaml.
ROSBAG2_VERSION = 9
#: rosbag2's start time of a bag without messages (the largest int64, as rosbag2 writes it).
NO_START = 2**63 - 1
_IDL_PREFIX = '=' * 80 + '\nIDL: '


def _library() -> str:
    try:
        mcap_version = version('mcap')
    except PackageNotFoundError:  # pragma: no cover - mcap imported from a source tree
        mcap_version = 'unknown'
    return f'cloe_ros-{__version__}; mcap-python-{mcap_version}'


def _offered_qos(topic: str, offered_qos: str | Sequence) -> list[Qos]:
    """rosbags ``Qos`` profiles from a rosbag2 YAML string, a list of dicts or of ``Qos``."""
    if isinstance(offered_qos, str):
        if not offered_qos.strip():
            return []
        items: Sequence = offered_qos
    else:
        items = list(offered_qos)
        if all(isinstance(q, Qos) for q in items):
            return list(items)
        if not all(isinstance(q, Mapping) for q in items):
            msg = (
                f'offered QoS of {topic}: expected a rosbag2 YAML string, or a list of '
                f'rosbags Qos or of dicts, got {offered_qos!r}'
            )
            raise WriterError(msg)
    try:
        return parse_qos(items)  # type: ignore[arg-type]
    except (ReaderError, KeyError, TypeError, AttributeError) as err:
        msg = f'offered QoS of {topic} cannot be read: {err!r}'
        raise WriterError(msg) from err


def _qos_yaml(qos: list[Qos]) -> str:
    """The profiles as the YAML text rosbag2 stores in an MCAP channel's metadata."""
    return yaml.safe_dump(dump_qos_v9(qos), default_flow_style=False, sort_keys=False).strip()


@dataclass
class _Topic:
    msgtype: str
    channel_id: int
    rihs01: str
    qos: list[Qos]


class BagWriter:
    """Write a rosbag2 directory (MCAP storage, rosbag2 version 9, ROS 2 Jazzy types).

    ``BagWriter(path)`` creates ``path/`` and opens ``path/<name>.mcap`` at once; it refuses a
    path that exists. Use it as a context manager or call :meth:`close`; messages are raw CDR.

    Durability: a chunk of messages is buffered in memory (up to 1 MiB, :data:`CHUNK_SIZE`)
    before it is written. :meth:`flush` writes the pending chunk and flushes Python's file buffer
    to the OS, so a process killed with SIGKILL after ``flush()`` loses nothing written before it
    (a machine that loses power may: there is no fsync). :meth:`close` writes the MCAP summary
    and footer and ``metadata.yaml``.

    Write failures (``OSError``: a full disk, an I/O error) are final: the first one leaves the
    file with a cut record, so the writer closes it at once without summary, drops the pending
    chunk and raises :class:`WriterError` (its ``reason`` is the operating system's words);
    :attr:`error` then says why, every later call but :meth:`flush` (which does nothing),
    :meth:`metadata`, :meth:`abort` and :meth:`discard` raises, and :meth:`close` raises after
    marking the writer closed. :attr:`message_count` and
    :attr:`topic_counts` go back to the messages handed to the operating system before the
    failure, which ``cloe bag recover`` gets back. Nothing grows in memory after a failure.

    Args:
        path: the bag directory to create.
        compression: ``'zstd'`` compresses each MCAP chunk (rosbag2 "storage" compression, read by
            every MCAP reader), ``'none'`` writes plain chunks.
    """

    def __init__(self, path: Path | str, compression: str = 'zstd') -> None:
        path = Path(path)
        if compression not in COMPRESSIONS:
            msg = f'compression must be one of {", ".join(COMPRESSIONS)}, got {compression!r}'
            raise WriterError(msg, path)
        if path.exists() or path.is_symlink():
            msg = f'{path} exists already, not overwriting.'
            raise WriterError(msg, path)
        self.path = path
        self.compression = compression
        self.mcap_path = path / f'{path.name}.mcap'
        try:
            path.mkdir(mode=0o755, parents=True)
        except FileExistsError:
            msg = f'{path} exists already, not overwriting.'
            raise WriterError(msg, path) from None
        except OSError as err:
            reason = err.strerror or str(err)
            msg = f'cannot create bag {path}: {reason}'
            raise WriterError(msg, path, reason) from err
        self._file: BinaryIO | None = None
        try:
            self._file = self.mcap_path.open('xb')
            chunks = '' if compression == 'none' else compression
            self._mcap = McapWriter(self._file, CHUNK_SIZE, chunks, Profile.ROS2, _library())
        except OSError as err:
            if self._file is not None:
                self._close_file()
            reason = err.strerror or str(err)
            msg = f'cannot create bag {path}: {reason}'
            raise WriterError(msg, path, reason) from err
        self._closed = False
        self._topics: dict[str, _Topic] = {}
        self._schemas: dict[tuple[str, str], int] = {}
        self._counts: dict[str, int] = {}
        self._custom: dict[str, str] = {}
        self._payload_bytes = 0
        self._chunks = 0
        self._pending = 0  # messages in the chunk not written yet
        self._start_ns = NO_START
        self._end_ns = 0
        #: counts and payload bytes of the messages handed to the OS (by flush() or a full chunk)
        self._saved: tuple[dict[str, int], int] = ({}, 0)
        self._error: str | None = None

    # -- public API ----------------------------------------------------------------------------

    @property
    def closed(self) -> bool:
        return self._closed

    @property
    def message_count(self) -> int:
        """Messages written so far, all topics."""
        return sum(self._counts.values())

    @property
    def topic_counts(self) -> dict[str, int]:
        """Messages written so far per topic (a copy)."""
        return dict(self._counts)

    @property
    def topics(self) -> dict[str, str]:
        """Message type of every added topic."""
        return {name: topic.msgtype for name, topic in self._topics.items()}

    @property
    def payload_bytes(self) -> int:
        """Bytes of message data (CDR) written so far, before compression."""
        return self._payload_bytes

    @property
    def chunk_count(self) -> int:
        """MCAP chunks written to the file so far: by :meth:`flush` and on reaching the chunk
        size (1 MiB of records)."""
        return self._chunks

    @property
    def error(self) -> str | None:
        """Why writing the file failed (the operating system's words), or None while all is
        well."""
        return self._error

    def _require_open(self) -> None:
        if self._error is not None:
            msg = f'bag {self.path} failed already: {self._error}'
            raise WriterError(msg, self.path, self._error)
        if self._closed:
            msg = f'bag {self.path} is closed already'
            raise WriterError(msg, self.path)

    def _saved_to_os(self) -> None:
        self._saved = (dict(self._counts), self._payload_bytes)

    def _close_file(self) -> None:
        file, self._file = self._file, None
        if file is None:
            return
        try:
            file.close()  # a buffer that cannot be written is dropped; the file is closed anyway
        except OSError:
            pass

    def _fail(self, err: OSError) -> WriterError:
        """Stop writing after a failed write to the file: close it as it is (what is on disk stays
        recoverable), drop the pending chunk, count only the messages handed to the OS."""
        self._error = err.strerror or str(err)
        self._close_file()
        counts, self._payload_bytes = self._saved
        self._counts = {name: counts.get(name, 0) for name in self._counts}
        self._pending = 0
        msg = (
            f'cannot write bag {self.path}: {self._error}; nothing more is written to it '
            f'({self.message_count} messages are in the file)'
        )
        return WriterError(msg, self.path, self._error)

    def add_topic(
        self,
        name: str,
        msgtype: str,
        offered_qos: str | Sequence = (),
        *,
        msgdef: str | None = None,
        rihs01: str | None = None,
    ) -> None:
        """Add a topic of ``msgtype`` (e.g. ``nav_msgs/msg/Odometry``).

        The type is a ROS 2 Jazzy type whose definition rosbags knows, or ``msgdef`` gives its
        definition (``.msg`` text, or rosbag2's concatenated IDL) and ``rihs01`` its type hash
        (as ``cloe bag recover`` copies them from a recorded file). ``offered_qos`` is stored in
        the bag's metadata: the publishers' QoS profiles as a rosbag2 ``offered_qos_profiles``
        YAML string, or a list of ``rosbags.interfaces.Qos`` or of the equivalent dicts. Adding
        the same name and type again does nothing; another type for a known topic raises
        :class:`WriterError`.
        """
        self._require_open()
        if not isinstance(name, str) or not name:
            msg = f'topic name must be a non-empty string, got {name!r}'
            raise WriterError(msg, self.path)
        known = self._topics.get(name)
        if known is not None:
            if known.msgtype == msgtype:
                return
            msg = (
                f'topic {name} is recorded as {known.msgtype} already, cannot add it as {msgtype}'
            )
            raise WriterError(msg, self.path)
        if (msgdef is None or rihs01 is None) and msgtype in MSGDEFS:
            msgdef, rihs01 = MSGDEFS[msgtype]  # (the type store's, without making it)
        elif msgdef is None or rihs01 is None:
            store = typestore()
            if msgtype not in store.types:
                msg = (
                    f'message type {msgtype!r} of topic {name} is not a ROS 2 Jazzy type known '
                    'to rosbags (expected e.g. nav_msgs/msg/Odometry)'
                )
                raise WriterError(msg, self.path)
            msgdef = store.generate_msgdef(msgtype, ros_version=2)[0]
            rihs01 = store.hash_rihs01(msgtype)
        qos = _offered_qos(name, offered_qos)
        idl = msgdef.startswith(_IDL_PREFIX)
        encoding = SchemaEncoding.ROS2IDL if idl else SchemaEncoding.ROS2
        try:
            schema_id = self._schemas.get((msgtype, msgdef))
            if schema_id is None:
                schema_id = self._mcap.register_schema(msgtype, encoding, msgdef.encode())
                self._schemas[(msgtype, msgdef)] = schema_id
            channel_id = self._mcap.register_channel(
                name, MessageEncoding.CDR, schema_id, {'offered_qos_profiles': _qos_yaml(qos)}
            )
        except OSError as err:  # pragma: no cover - declarations go into the chunk in memory
            raise self._fail(err) from err
        self._topics[name] = _Topic(msgtype, channel_id, rihs01, qos)
        self._counts[name] = 0

    def add_offered_qos(self, name: str, offered_qos: str | Sequence) -> None:
        """Add the QoS profiles of publishers that joined topic ``name`` after :meth:`add_topic`
        (same forms as there); profiles the topic has already are not repeated.

        They go into ``metadata.yaml`` when the bag is closed. The MCAP channel record keeps the
        profiles given to :meth:`add_topic`: it is in the file already, and a channel cannot
        change within an MCAP file.
        """
        self._require_open()
        topic = self._topics.get(name)
        if topic is None:
            msg = f'topic {name} was not added to bag {self.path}: call add_topic() first'
            raise WriterError(msg, self.path)
        for qos in _offered_qos(name, offered_qos):
            if qos not in topic.qos:
                topic.qos.append(qos)

    def write(self, topic: str, log_time_ns: int, data: bytes | memoryview) -> None:
        """Write one message: raw CDR ``data`` received at ``log_time_ns`` (int ns)."""
        self._require_open()
        known = self._topics.get(topic)
        if known is None:
            msg = f'topic {topic} was not added to bag {self.path}: call add_topic() first'
            raise WriterError(msg, self.path)
        log_time_ns = int(log_time_ns)
        if not 0 <= log_time_ns < 2**64:
            msg = f'log time of a message on {topic} must be in [0, 2**64) ns, got {log_time_ns}'
            raise WriterError(msg, self.path)
        assert self._file is not None
        try:
            chunk_written = self._mcap.add_message(known.channel_id, log_time_ns, data)
        except OSError as err:  # a full chunk goes to the file here
            raise self._fail(err) from err
        self._counts[topic] += 1
        self._payload_bytes += len(data)
        self._pending += 1
        if log_time_ns < self._start_ns:
            self._start_ns = log_time_ns
        if log_time_ns > self._end_ns:
            self._end_ns = log_time_ns
        if chunk_written:
            self._chunks += 1
            self._pending = 0
            try:
                self._file.flush()
            except OSError as err:
                raise self._fail(err) from err
            self._saved_to_os()

    def flush(self) -> None:
        """Write the pending chunk (if it holds anything) and flush the file to the OS.

        After this returns, every message written so far is in the operating system's hands and
        survives a SIGKILL of this process. A closed writer has nothing to flush.
        """
        if self._closed or self._error is not None:
            return
        try:
            self._mcap.flush()  # the pending chunk (none if empty), then the file's buffer
        except OSError as err:
            raise self._fail(err) from err
        if self._pending:
            self._chunks += 1
            self._pending = 0
        self._saved_to_os()

    def set_custom_data(self, key: str, value: str) -> None:
        """A key-value pair for the ``custom_data`` of ``metadata.yaml`` (rosbag2's place for what
        the tool that wrote a bag wants to say about it), written when the bag is closed."""
        self._require_open()
        if not (isinstance(key, str) and isinstance(value, str)):
            msg = f'custom data must map str to str, got {key!r}: {value!r}'
            raise WriterError(msg, self.path)
        self._custom[key] = value

    def metadata(self) -> dict:
        """``metadata.yaml`` as rosbag2 (version 9) writes it, for the messages written so far."""
        count = self.message_count
        start = self._start_ns if count else NO_START
        duration = self._end_ns - self._start_ns if count else 0
        name = self.mcap_path.name
        return {
            'rosbag2_bagfile_information': {
                'version': ROSBAG2_VERSION,
                'storage_identifier': 'mcap',
                'relative_file_paths': [name],
                'duration': {'nanoseconds': duration},
                'starting_time': {'nanoseconds_since_epoch': start},
                'message_count': count,
                'topics_with_message_count': [
                    {
                        'topic_metadata': {
                            'name': topic,
                            'type': info.msgtype,
                            'serialization_format': MessageEncoding.CDR,
                            'offered_qos_profiles': dump_qos_v9(info.qos),
                            'type_description_hash': info.rihs01,
                        },
                        'message_count': self._counts[topic],
                    }
                    for topic, info in self._topics.items()
                ],
                'compression_format': '',
                'compression_mode': '',
                'files': [
                    {
                        'path': name,
                        'starting_time': {'nanoseconds_since_epoch': start},
                        'duration': {'nanoseconds': duration},
                        'message_count': count,
                    }
                ],
                'custom_data': dict(self._custom) or None,
                'ros_distro': ROS_DISTRO,
            }
        }

    def close(self) -> None:
        """Finish the bag: pending chunk, MCAP summary and footer, ``metadata.yaml``.

        Idempotent. If finishing fails, or writing failed before, the ``.mcap`` is left as it is
        (recoverable with ``cloe bag recover``), :attr:`error` and :class:`WriterError` say why,
        and the counts are those of the messages handed to the OS.
        """
        if self._closed:
            return
        self._closed = True
        if self._error is None:
            try:
                self._finish()
                return
            except OSError as err:
                self._fail(err)
        msg = f'cannot finish bag {self.path}: {self._error}; try `cloe bag recover {self.path}`'
        raise WriterError(msg, self.path, self._error)

    def _finish(self) -> None:
        meta = self.metadata()
        self._mcap.flush()
        if self._pending:
            self._chunks += 1
            self._pending = 0
        self._saved_to_os()
        # rosbag2 keeps a copy of metadata.yaml inside the file, so that the file alone says it
        inner = yaml.safe_dump(meta['rosbag2_bagfile_information'], default_flow_style=False)
        self._mcap.add_metadata('rosbag2', {'serialized_metadata': inner.strip()})
        self._mcap.finish()
        assert self._file is not None
        file, self._file = self._file, None
        file.close()
        tmp = self.path / 'metadata.yaml.tmp'
        tmp.write_text(yaml.safe_dump(meta, default_flow_style=False), 'utf8')
        tmp.replace(self.path / 'metadata.yaml')

    def abort(self) -> None:
        """Close the file as it is (no summary, no ``metadata.yaml``), for a caller that removes
        the bag; idempotent, never raises."""
        self._closed = True
        self._close_file()

    def discard(self) -> None:
        """:meth:`abort`, then remove the bag (the directory this writer created): for a caller
        whose output failed on the way, since a bag cut short looks complete to the next tool.
        Idempotent, never raises; run it where Ctrl-C cannot cut it short
        (:func:`~cloe_ros.interrupts.uninterrupted`)."""
        self.abort()
        shutil.rmtree(self.path, ignore_errors=True)

    def __enter__(self) -> BagWriter:
        return self

    def __exit__(
        self,
        exc_type: type[BaseException] | None,
        exc: BaseException | None,
        tb: TracebackType | None,
    ) -> None:
        # Close completely even after an error: every message written so far is valid. When an
        # error is on its way already, it is the one to report, not a failure to finish.
        if exc is None:
            self.close()
            return
        try:
            self.close()
        except WriterError:
            pass
