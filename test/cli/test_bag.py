"""`cloe bag info|recover`: what they accept and what they say about a bag."""

from __future__ import annotations

import re
import struct
from pathlib import Path

import numpy as np

from cloe_ros.cli.main import main
from cloe_ros.core.samples import OdometrySample
from cloe_ros.io import messages
from cloe_ros.io.writer import BagWriter

ROOT = Path(__file__).resolve().parents[2]
POSITION = ROOT / 'bags' / 'position'


def run(capsys, *args) -> tuple[int, str, str]:
    status = main(['bag', *map(str, args)])
    captured = capsys.readouterr()
    return status, captured.out, captured.err


def test_info_of_a_single_mcap_file_matches_its_bag(capsys):
    status, of_dir, err = run(capsys, 'info', POSITION)
    assert status == 0, err
    status, of_file, err = run(capsys, 'info', POSITION / 'position.mcap')
    assert status == 0, err
    # the same messages, times and topics; only the path and the files line differ
    assert of_file.splitlines()[2:] == of_dir.splitlines()[2:]
    assert 'messages:  ' in of_file and '/odom' in of_file
    assert 'a single file without metadata.yaml' in of_file


def test_info_of_a_missing_path_or_another_file(tmp_path, capsys):
    assert run(capsys, 'info', tmp_path / 'nope') == (
        1, '', f'ERROR: {tmp_path / "nope"} does not exist\n')  # fmt: skip
    status, _, err = run(capsys, 'info', ROOT / 'README.md')
    assert status == 1
    assert err.startswith(f'ERROR: {ROOT / "README.md"} is a file, not a bag')


def test_recover_counts_the_messages_of_a_cut_chunk_as_usable(tmp_path, capsys):
    """A file cut inside its first (uncompressed) chunk: its complete records end after the
    header, yet messages are recovered from the chunk's part on disk; the summary must not call
    the header the only usable bytes."""
    bag = tmp_path / 'plain'
    with BagWriter(bag, compression='none') as writer:
        writer.add_topic('/odom', messages.ODOMETRY)
        for k in range(200):
            stamp = 1_000_000_000 + k * 10_000_000
            writer.write('/odom', stamp, messages.encode_odometry(OdometrySample(
                stamp, 'world', 'base_link', np.full(3, k), np.array([0.0, 0, 0, 1]),
                np.zeros(3), np.zeros(3))))  # fmt: skip
    (mcap,) = bag.glob('*.mcap')
    cut = tmp_path / 'cut.mcap'
    cut.write_bytes(mcap.read_bytes()[: mcap.stat().st_size // 2])
    status, out, err = run(capsys, 'recover', cut, '-o', tmp_path / 'fixed')
    assert status == 0, err
    first = out.splitlines()[0]
    recovered = int(re.search(r'recovered (\d+) messages', out).group(1))
    assert 0 < recovered < 200
    assert 'bytes usable' not in first
    assert re.fullmatch(
        rf'{re.escape(str(cut))}: incomplete \({cut.stat().st_size} bytes\), complete records up '
        rf'to byte \d+, then a chunk cut off by the end of the file: file cut inside a Chunk '
        rf'record \(\d+ bytes, \d+ on disk\); {recovered} complete messages taken from the part '
        rf'on disk; {recovered} messages read',
        first,
    ), first


def odometry(k: int, stamp: int) -> bytes:
    return messages.encode_odometry(OdometrySample(
        stamp, 'world', 'base_link', np.full(3, k), np.array([0.0, 0, 0, 1]), np.zeros(3),
        np.zeros(3)))  # fmt: skip


def damaged_bag(tmp_path: Path) -> tuple[Path, Path]:
    """A complete bag (uncompressed) in which one message was moved to another channel: every
    record still parses, only the message index disagrees."""
    bag = tmp_path / 'damaged'
    with BagWriter(bag, compression='none') as writer:
        writer.add_topic('/odom', messages.ODOMETRY)
        writer.add_topic('/reference', messages.POSE_STAMPED)
        for k in range(20):
            writer.write('/odom', 1_000 + k, odometry(k, 1_000 + k))
    (mcap,) = bag.glob('*.mcap')
    data = bytearray(mcap.read_bytes())
    record = struct.pack('<BQHIQ', 0x05, 22 + len(odometry(7, 1_007)), 1, 0, 1_007)
    at = data.index(record)
    struct.pack_into('<H', data, at + 9, 2)  # /odom (channel 1) -> /reference (2)
    mcap.write_bytes(bytes(data))
    return bag, mcap


def test_info_and_recover_say_a_bag_is_damaged(tmp_path, capsys):
    bag, mcap = damaged_bag(tmp_path)
    for path in (bag, mcap):
        status, out, err = run(capsys, 'info', path)
        assert status == 1
        assert 'messages:  20' in out  # what the bag says of itself is shown all the same
        assert re.search(r'^damaged: +\S+\.mcap: damaged Chunk at byte \d+ ', out, re.M), out
        assert '/odom: 19 of the 20 messages listed are readable' in out
        assert err.startswith(f'ERROR: {path} is damaged')
        assert f'cloe bag recover {path}' in err
    status, out, err = run(capsys, 'recover', bag, '-o', tmp_path / 'fixed')
    assert status == 0, err
    assert out.startswith(f'{mcap}: damaged (its footer is there); 19 messages read of the 20')
    assert '19 of its messages kept (they match the message index), 1 lost' in out
    assert 'recovered 19 messages' in out
    status, out, err = run(capsys, 'info', tmp_path / 'fixed')
    assert (status, err) == (0, '')
    assert 'messages:  19' in out and 'damaged' not in out


def test_info_of_unreadable_storage_files(tmp_path, capsys):
    # metadata.yaml gone, the .mcap complete: it can be read as it is
    bag = tmp_path / 'nometa'
    with BagWriter(bag, compression='none') as writer:
        writer.add_topic('/odom', messages.ODOMETRY)
        writer.write('/odom', 1_000, odometry(0, 1_000))
    (bag / 'metadata.yaml').unlink()
    (mcap,) = bag.glob('*.mcap')
    status, _, err = run(capsys, 'info', bag)
    assert status == 1
    assert f'pass the .mcap file itself ({mcap})' in err
    assert run(capsys, 'info', mcap)[0] == 0
    # a file cut after the magic bytes: no rosbags internals in the message
    with BagWriter(tmp_path / 'cut', compression='none') as writer:
        writer.add_topic('/odom', messages.ODOMETRY)
    (cut,) = (tmp_path / 'cut').glob('*.mcap')
    cut.write_bytes(cut.read_bytes()[:8])
    status, out, err = run(capsys, 'info', tmp_path / 'cut')
    assert (status, out) == (1, '')
    assert err == (
        f'ERROR: {cut} holds the MCAP magic bytes and no record (8 bytes): nothing was '
        f'recorded; remove the bag {tmp_path / "cut"}\n'
    )
