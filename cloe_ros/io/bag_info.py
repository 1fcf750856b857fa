"""What ``cloe bag info`` says about a bag: topics, types, counts, times, and what is wrong.

:func:`bag_info` opens the bag with :class:`~cloe_ros.io.reader.BagReader` (so the counts and
times are the files', and metadata.yaml's disagreement with them comes back as warnings), then,
for MCAP storage, reads every record of every file as ``cloe bag recover`` does
(:class:`~cloe_ros.io.recover.McapScan`) to find damaged records: chunks that do not match their
CRC or their message index, records that do not parse, a data section that does not match its
CRC, fewer messages than listed. No rclpy here.
"""

from __future__ import annotations

from dataclasses import dataclass
from datetime import datetime, timezone
from pathlib import Path

from cloe_ros.io.reader import BagReader
from cloe_ros.io.recover import DATA_CRC_MISMATCH, McapMessage, McapScan

__all__ = ['BagInfo', 'TopicSummary', 'bag_info', 'mcap_damage']


@dataclass(frozen=True)
class TopicSummary:
    topic: str
    msgtype: str
    count: int


@dataclass(frozen=True)
class BagInfo:
    """What ``cloe bag info`` shows. Times are int ns (log time)."""

    path: Path
    files: tuple[str, ...]
    storage: str
    topics: tuple[TopicSummary, ...]
    message_count: int
    start_ns: int
    end_ns: int
    #: what is wrong with the data (:func:`mcap_damage`); empty for a good bag
    damage: tuple[str, ...] = ()
    #: where metadata.yaml disagrees with the files (the files' counts are the ones shown)
    warnings: tuple[str, ...] = ()
    #: the data no CRC vouches for (:func:`mcap_damage`): damage there cannot be seen
    unchecked: tuple[str, ...] = ()

    @property
    def duration_ns(self) -> int:
        return max(0, self.end_ns - self.start_ns) if self.message_count else 0

    def lines(self) -> list[str]:
        def stamp(ns: int) -> str:
            t = datetime.fromtimestamp(ns / 1e9, tz=timezone.utc)
            return f'{t.isoformat(timespec="milliseconds")} ({ns / 1e9:.3f} s)'

        out = [
            f'bag:       {self.path}',
            f'files:     {", ".join(self.files)} ({self.storage})',
            f'messages:  {self.message_count}',
        ]
        if self.message_count:
            out += [
                f'duration:  {self.duration_ns / 1e9:.3f} s',
                f'start:     {stamp(self.start_ns)}',
                f'end:       {stamp(self.end_ns)}',
            ]
        out.append('topics:')
        width = max((len(t.topic) for t in self.topics), default=0)
        tw = max((len(t.msgtype) for t in self.topics), default=0)
        out += [f'  {t.topic:<{width}}  {t.msgtype:<{tw}}  {t.count}' for t in self.topics]
        for i, warning in enumerate(self.warnings):
            out.append(f'{"warning:" if i == 0 else "":<11}{warning}')
        for i, what in enumerate(self.unchecked):
            out.append(f'{"unchecked:" if i == 0 else "":<11}{what}')
        for i, problem in enumerate(self.damage):
            out.append(f'{"damaged:" if i == 0 else "":<11}{problem}')
        return out


def mcap_damage(files: list[Path], counts: dict[str, int]) -> tuple[list[str], list[str]]:
    """What is wrong with the data of complete ``.mcap`` files, read record by record as
    ``cloe bag recover`` reads them (``[]`` for good files): damaged records, a data section that
    does not match its CRC, a file that ends early, and topics with fewer messages than
    ``counts`` (what the bag lists) says; and the files whose chunks carry no CRC (damage to
    their messages' contents cannot be seen: the format allows a writer to leave CRCs out)."""
    problems, unchecked = [], []
    found: dict[str, int] = {}
    for path in files:
        scan = McapScan(path)
        for rec in scan:
            if isinstance(rec, McapMessage) and rec.channel_id in scan.channels:
                topic = scan.channels[rec.channel_id].topic
                found[topic] = found.get(topic, 0) + 1
        problems += [f'{path.name}: {s.line()}' for s in scan.skipped]
        if scan.data_crc_mismatch:
            problems.append(f'{path.name}: {DATA_CRC_MISMATCH}')
        if not scan.complete:
            problems.append(f'{path.name}: {scan.reason}')
        if scan.chunks_without_crc:
            unchecked.append(
                f'{path.name}: {scan.chunks_without_crc} of its {scan.chunks} chunks carry no CRC '
                '(written without): their messages\' contents cannot be checked'
                + ('' if scan.data_crc else ', nor can the data section')
            )
    for topic, n in sorted(counts.items()):
        if found.get(topic, 0) < n:
            problems.append(
                f'{topic}: {found.get(topic, 0)} of the {n} messages listed are readable'
            )
    return problems, unchecked


def bag_info(bag: Path | str) -> BagInfo:
    """Topics, types, counts and time span of a complete bag (a rosbag2 directory or a single
    ``.mcap`` file), metadata.yaml's disagreement with its files, and (MCAP storage) what
    :func:`mcap_damage` finds wrong with its data. Raises
    :class:`~cloe_ros.io.reader.BagError` for what :class:`BagReader` refuses (no bag, truncated,
    a damaged summary, ...)."""
    bag = Path(bag)
    with BagReader(bag) as reader:
        topics = tuple(
            TopicSummary(name, info.msgtype, info.count) for name, info in reader.topics.items()
        )
        single = bag.is_file()
        storage = f'{reader.storage}, a single file without metadata.yaml' if single else (
            reader.storage)  # fmt: skip
        damage: list[str] = []
        unchecked: list[str] = []
        if reader.storage == 'mcap' and reader.compression_mode != 'file':
            damage, unchecked = mcap_damage(reader.files, reader.listed_counts)
        return BagInfo(
            bag,
            tuple(f.name for f in reader.files),
            storage,
            topics,
            reader.message_count,
            reader.start_ns,
            reader.end_ns,
            tuple(damage),
            tuple(reader.metadata_mismatch),
            tuple(unchecked),
        )
