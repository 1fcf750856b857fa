"""A crash-safe rosbag2 writer: MCAP storage, ROS 2 Jazzy types, schemas embedded.

:class:`BagWriter` wraps ``rosbags.rosbag2.Writer`` (rosbag2 version 9, MCAP storage) and adds
:meth:`BagWriter.flush`, which closes the pending MCAP chunk and hands the file to the operating
system. Whatever was written before the last ``flush()`` survives a SIGKILL of the process: the
``.mcap`` then lacks its summary and footer and the directory its ``metadata.yaml``, and
``cloe bag recover`` (:mod:`cloe_ros.io.recover`) turns it back into a complete bag. The same
holds after a write failure (a full disk): the writer stops at the first one, see
:class:`BagWriter`.

No rclpy here: messages are raw CDR bytes, times are int nanoseconds.
"""

from __future__ import annotations

from collections.abc import Mapping, Sequence
from importlib.metadata import PackageNotFoundError, version
from pathlib import Path
from types import TracebackType

from rosbags.interfaces import Connection, Qos
from rosbags.rosbag2 import Writer
from rosbags.rosbag2.enums import CompressionFormat, CompressionMode, StoragePlugin
from rosbags.rosbag2.errors import ReaderError
from rosbags.rosbag2.errors import WriterError as RosbagsWriterError
from rosbags.rosbag2.metadata import parse_qos

from cloe_ros.io.errors import WriterError
from cloe_ros.io.messages import TYPESTORE

#: Values of the ``compression`` argument: MCAP chunk compression with zstd, or none.
COMPRESSIONS = ('zstd', 'none')


def _rosbags_version() -> str:
    try:
        return version('rosbags')
    except PackageNotFoundError:  # pragma: no cover - rosbags imported from a source tree
        return 'unknown'


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


class BagWriter:
    """Write a rosbag2 directory (MCAP storage, rosbag2 version 9, ROS 2 Jazzy types).

    ``BagWriter(path)`` creates ``path/`` and opens ``path/<name>.mcap`` at once; it refuses a
    path that exists. Use it as a context manager or call :meth:`close`; messages are raw CDR.

    Durability: rosbags buffers a chunk of messages in memory (up to 1 MiB) before writing it.
    :meth:`flush` writes the pending chunk and flushes Python's file buffer to the OS, so a
    process killed with SIGKILL after ``flush()`` loses nothing written before it (a machine that
    loses power may: there is no fsync). :meth:`close` writes the MCAP summary and footer and
    ``metadata.yaml``.

    Write failures (``OSError``: a full disk, an I/O error) are final: the first one leaves the
    file with a cut record, so the writer closes it at once without summary, drops the pending
    chunk and raises :class:`WriterError`; :attr:`error` then says why, every later call but
    :meth:`flush` (which does nothing) raises, and :meth:`close` raises after marking the writer
    closed. :attr:`message_count` and :attr:`topic_counts` go back to the messages handed to the
    operating system before the failure, which ``cloe bag recover`` gets back. Nothing grows in
    memory after a failure.

    Args:
        path: the bag directory to create.
        compression: ``'zstd'`` compresses each MCAP chunk (rosbag2 "storage" compression, read by
            every MCAP reader), ``'none'`` writes plain chunks.
    """

    def __init__(self, path: Path | str, compression: str = 'zstd') -> None:
        path = Path(path)
        if compression not in COMPRESSIONS:
            msg = f'compression must be one of {", ".join(COMPRESSIONS)}, got {compression!r}'
            raise WriterError(msg)
        if path.exists():
            msg = f'{path} exists already, not overwriting.'
            raise WriterError(msg)
        self.path = path
        self.compression = compression
        self._writer = Writer(path, version=9, storage_plugin=StoragePlugin.MCAP)
        if compression == 'zstd':
            self._writer.set_compression(CompressionMode.STORAGE, CompressionFormat.ZSTD)
        try:
            self._writer.open()
        except RosbagsWriterError as err:
            raise WriterError(str(err)) from err
        except OSError as err:
            msg = f'cannot create bag {path}: {err}'
            raise WriterError(msg) from err
        self._closed = False
        self._check_storage_internals()
        self._connections: dict[str, Connection] = {}
        self._counts: dict[str, int] = {}
        self._payload_bytes = 0
        self._chunks = 0
        #: counts and payload bytes of the messages handed to the OS (by flush() or a full chunk)
        self._saved: tuple[dict[str, int], int] = ({}, 0)
        self._error: str | None = None

    # -- rosbags internals used by flush() ---------------------------------------------------

    def _check_storage_internals(self) -> None:
        """Fail at once, with the reason, if rosbags' MCAP writer no longer looks as expected."""
        storage = self._writer.storage
        chunk = getattr(storage, 'chunk', None)
        required = {
            'close_chunk()': getattr(storage, 'close_chunk', None),
            'bio.flush()': getattr(getattr(storage, 'bio', None), 'flush', None),
            'chunk.bio.tell()': getattr(getattr(chunk, 'bio', None), 'tell', None),
        }
        missing = [name for name, method in required.items() if not callable(method)]
        if missing:
            self._writer.abort()
            msg = (
                f'rosbags {_rosbags_version()} changed its MCAP storage writer: BagWriter.flush() '
                f'needs McapWriter {", ".join(missing)}. Install the rosbags version pinned in '
                'requirements.txt (0.11.x) or update cloe_ros/io/writer.py.'
            )
            raise WriterError(msg)

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
        return {name: conn.msgtype for name, conn in self._connections.items()}

    @property
    def payload_bytes(self) -> int:
        """Bytes of message data (CDR) written so far, before compression."""
        return self._payload_bytes

    @property
    def chunk_count(self) -> int:
        """MCAP chunks written to the file so far: by :meth:`flush` and on reaching rosbags' chunk
        size (1 MiB of messages)."""
        return self._chunks

    @property
    def error(self) -> str | None:
        """Why writing the file failed (the ``OSError``), or None while all is well."""
        return self._error

    def _require_open(self) -> None:
        if self._error is not None:
            msg = f'bag {self.path} failed already: {self._error}'
            raise WriterError(msg)
        if self._closed:
            msg = f'bag {self.path} is closed already'
            raise WriterError(msg)

    def _saved_to_os(self) -> None:
        self._saved = (dict(self._counts), self._payload_bytes)

    def _fail(self, err: Exception) -> WriterError:
        """Stop writing after a failed write to the file: close it as it is (what is on disk stays
        recoverable), drop the pending chunk, count only the messages handed to the OS."""
        self._error = str(err)
        try:
            self._writer.abort()  # closes the file; its buffer cannot be written and is dropped
        except (RosbagsWriterError, OSError):
            pass
        counts, self._payload_bytes = self._saved
        self._counts = {name: counts.get(name, 0) for name in self._counts}
        msg = (
            f'cannot write bag {self.path}: {err}; nothing more is written to it '
            f'({self.message_count} messages are in the file)'
        )
        return WriterError(msg)

    def add_topic(self, name: str, msgtype: str, offered_qos: str | Sequence = ()) -> None:
        """Add a topic of ``msgtype`` (e.g. ``nav_msgs/msg/Odometry``), a Jazzy type.

        ``offered_qos`` is stored in the bag's metadata: the publishers' QoS profiles as a rosbag2
        ``offered_qos_profiles`` YAML string, or a list of ``rosbags.interfaces.Qos`` or of the
        equivalent dicts. Adding the same name and type again does nothing; another type for a
        known topic raises :class:`WriterError`.
        """
        self._require_open()
        if not isinstance(name, str) or not name:
            msg = f'topic name must be a non-empty string, got {name!r}'
            raise WriterError(msg)
        known = self._connections.get(name)
        if known is not None:
            if known.msgtype == msgtype:
                return
            msg = (
                f'topic {name} is recorded as {known.msgtype} already, cannot add it as {msgtype}'
            )
            raise WriterError(msg)
        if msgtype not in TYPESTORE.types:
            msg = (
                f'message type {msgtype!r} of topic {name} is not a ROS 2 Jazzy type known to '
                'rosbags (expected e.g. nav_msgs/msg/Odometry)'
            )
            raise WriterError(msg)
        qos = _offered_qos(name, offered_qos)
        try:
            conn = self._writer.add_connection(
                name, msgtype, typestore=TYPESTORE, offered_qos_profiles=qos
            )
        except RosbagsWriterError as err:
            raise WriterError(str(err)) from err
        self._connections[name] = conn
        self._counts[name] = 0

    def add_offered_qos(self, name: str, offered_qos: str | Sequence) -> None:
        """Add the QoS profiles of publishers that joined topic ``name`` after :meth:`add_topic`
        (same forms as there); profiles the topic has already are not repeated.

        They go into ``metadata.yaml`` when the bag is closed. The MCAP channel record keeps the
        profiles given to :meth:`add_topic`: it is in the file already, and a channel cannot
        change within an MCAP file.
        """
        self._require_open()
        conn = self._connections.get(name)
        if conn is None:
            msg = f'topic {name} was not added to bag {self.path}: call add_topic() first'
            raise WriterError(msg)
        stored = conn.ext.offered_qos_profiles  # the list metadata.yaml is made from at close()
        for qos in _offered_qos(name, offered_qos):
            if qos not in stored:
                stored.append(qos)

    def write(self, topic: str, log_time_ns: int, data: bytes | memoryview) -> None:
        """Write one message: raw CDR ``data`` received at ``log_time_ns`` (int ns)."""
        self._require_open()
        conn = self._connections.get(topic)
        if conn is None:
            msg = f'topic {topic} was not added to bag {self.path}: call add_topic() first'
            raise WriterError(msg)
        log_time_ns = int(log_time_ns)
        if log_time_ns < 0:
            msg = f'log time of a message on {topic} must be >= 0 ns, got {log_time_ns}'
            raise WriterError(msg)
        storage = self._writer.storage
        pending = storage.chunk
        try:
            self._writer.write(conn, log_time_ns, data)
        except RosbagsWriterError as err:
            raise WriterError(str(err)) from err
        except OSError as err:  # a full chunk goes to the file here
            raise self._fail(err) from err
        self._counts[topic] += 1
        self._payload_bytes += len(data)
        if storage.chunk is not pending:  # the chunk reached rosbags' size and was written
            self._chunks += 1
            try:
                storage.bio.flush()
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
        storage = self._writer.storage
        try:
            if storage.chunk.bio.tell():
                storage.close_chunk()
                self._chunks += 1
            storage.bio.flush()
        except AttributeError as err:  # pragma: no cover - guarded by _check_storage_internals
            msg = f'rosbags {_rosbags_version()} changed its MCAP storage writer: {err}'
            raise WriterError(msg) from err
        except OSError as err:
            raise self._fail(err) from err
        self._saved_to_os()

    def set_custom_data(self, key: str, value: str) -> None:
        """A key-value pair for the ``custom_data`` of ``metadata.yaml`` (rosbag2's place for what
        the tool that wrote a bag wants to say about it), written when the bag is closed."""
        self._require_open()
        if not (isinstance(key, str) and isinstance(value, str)):
            msg = f'custom data must map str to str, got {key!r}: {value!r}'
            raise WriterError(msg)
        self._writer.set_custom_data(key, value)

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
                self._writer.close()
                return
            except (RosbagsWriterError, OSError) as err:
                self._fail(err)
        msg = f'cannot finish bag {self.path}: {self._error}; try `cloe bag recover {self.path}`'
        raise WriterError(msg)

    def __enter__(self) -> BagWriter:
        return self

    def __exit__(
        self,
        exc_type: type[BaseException] | None,
        exc: BaseException | None,
        tb: TracebackType | None,
    ) -> None:
        # Close completely even after an error: every message written so far is valid.
        self.close()
