"""`cloe bag info|recover`: what they accept and what they say about a bag."""

from __future__ import annotations

import re
import shutil
import struct
from pathlib import Path

import numpy as np
import pytest
import yaml
from bag_fixtures import (
    fill_disk_under,
    flip_inside_compressed_chunk,
    run_on_small_disk,
    write_sim_bag,
)
from mcap.reader import make_reader

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


# -- CRCs, what the file says, full disks, links --------------------------------------------------


@pytest.fixture(scope='module')
def sim_bag(tmp_path_factory) -> Path:
    """15 s of the simulated position flight, written by the package (three zstd chunks)."""
    return write_sim_bag(tmp_path_factory.mktemp('bags') / 'sim')


def messages_of(bag: Path) -> list[tuple[str, int, bytes]]:
    """Every message, read with the mcap library (its CRC checks on)."""
    (mcap,) = bag.glob('*.mcap')
    with mcap.open('rb') as fh:
        return [(c.topic, m.log_time, m.data)
                for _, c, m in make_reader(fh, validate_crcs=True).iter_messages()]  # fmt: skip


def test_a_bit_flip_inside_compressed_chunk_data_is_damage(sim_bag, tmp_path, capsys):
    """One bit flipped in the second zstd chunk; the data still decompress and parse (before,
    info and recover said nothing, and recover copied the changed message). info: damaged, the
    chunk named. recover: the chunk is left out and said so, every message it writes is one that
    was written."""
    bag = tmp_path / 'bag'
    shutil.copytree(sim_bag, bag)
    (mcap,) = bag.glob('*.mcap')
    offset, _ = flip_inside_compressed_chunk(mcap, chunk=1)
    status, out, err = run(capsys, 'info', bag)
    assert status == 1
    assert re.search(
        rf'^damaged: +{mcap.name}: damaged Chunk at byte {offset} \(\d+ bytes\): corrupt Chunk '
        r'record: chunk CRC does not match its data, and nothing shows which of its messages '
        r'changed; \d+ messages lost$', out, re.M), out  # fmt: skip
    assert err.startswith(f'ERROR: {bag} is damaged')

    status, out, err = run(capsys, 'recover', bag, '-o', tmp_path / 'fixed')
    assert status == 0, err
    assert f'damaged Chunk at byte {offset}' in out
    original = messages_of(sim_bag)
    recovered = messages_of(tmp_path / 'fixed')
    assert 0 < len(recovered) < len(original)
    assert set(recovered) < set(original)  # nothing changed is copied
    assert run(capsys, 'info', tmp_path / 'fixed')[0] == 0


def test_an_uncompressed_chunk_failing_its_crc_unlocated_is_left_out(tmp_path, capsys):
    """A byte of one message's data changed in an uncompressed chunk: every record parses and
    matches the message index, only the CRC tells. Before, recover kept all (the index was the
    only check); the chunk is left out now, the others kept."""
    bag = tmp_path / 'plain'
    with BagWriter(bag, compression='none') as writer:
        writer.add_topic('/odom', messages.ODOMETRY)
        for k in range(30):
            writer.write('/odom', 1_000 + k, odometry(k, 1_000 + k))
            if k % 10 == 9:
                writer.flush()  # three chunks of ten
    (mcap,) = bag.glob('*.mcap')
    data = bytearray(mcap.read_bytes())
    at = data.index(odometry(15, 1_015)) + 40  # inside the data of message 15 (second chunk)
    data[at] ^= 0x01
    mcap.write_bytes(bytes(data))
    status, out, err = run(capsys, 'recover', bag, '-o', tmp_path / 'fixed')
    assert status == 0, err
    assert 'nothing shows which of its messages changed; 10 messages lost' in out
    assert 'recovered 20 messages' in out
    assert [t for _, t, _ in messages_of(tmp_path / 'fixed')] == (
        [1_000 + k for k in range(30) if not 10 <= k < 20])  # fmt: skip


def test_damage_outside_the_chunks_is_said_and_the_messages_kept(tmp_path, capsys):
    """A byte changed in the copy of metadata.yaml inside the file: only the data section CRC
    covers it. info says so (status 1); recover keeps every message, they are intact."""
    bag = tmp_path / 'bag'
    with BagWriter(bag) as writer:
        writer.add_topic('/odom', messages.ODOMETRY)
        for k in range(20):
            writer.write('/odom', 1_000 + k, odometry(k, 1_000 + k))
    (mcap,) = bag.glob('*.mcap')
    data = bytearray(mcap.read_bytes())
    data[data.index(b'serialized_metadata') + 40] ^= 0x20
    mcap.write_bytes(bytes(data))
    status, out, err = run(capsys, 'info', bag)
    assert status == 1
    assert f'{mcap.name}: its data section does not match its CRC, although every chunk' in out
    status, out, err = run(capsys, 'recover', bag, '-o', tmp_path / 'fixed')
    assert status == 0, err
    assert 'recovered 20 messages' in out and 'the messages are intact' in out


def test_info_counts_what_the_file_holds(sim_bag, tmp_path, capsys):
    """metadata.yaml claiming 10 /odom messages (before: info printed 10 for a file holding
    1501): the file's counts, and a warning line; the bag is not damaged (status 0)."""
    bag = tmp_path / 'bag'
    shutil.copytree(sim_bag, bag)
    meta_path = bag / 'metadata.yaml'
    meta = yaml.safe_load(meta_path.read_text())
    for entry in meta['rosbag2_bagfile_information']['topics_with_message_count']:
        if entry['topic_metadata']['name'] == '/odom':
            entry['message_count'] = 10
    meta_path.write_text(yaml.safe_dump(meta))
    status, out, err = run(capsys, 'info', bag)
    assert (status, err) == (0, '')
    assert re.search(r'^  /odom +nav_msgs/msg/Odometry +1501$', out, re.M), out
    assert 'warning:   metadata.yaml lists 10 messages of /odom, sim.mcap holds 1501\n' in out
    assert 'damaged' not in out


def test_info_says_what_no_crc_vouches_for(sim_bag, tmp_path, capsys):
    """A bag written without CRCs (as rosbags writes MCAP, and so the NanoBench corpus): its
    messages' contents cannot be checked, and info says so in an ``unchecked:`` line, status 0
    (before: the same output as for a bag whose every byte was checked, so that damage to its
    messages went unseen and unsaid). The package's own bags carry CRCs, the sample bags in
    bags/ among them: no such line."""
    from rosbags.rosbag2 import StoragePlugin, Writer
    from rosbags.typesys import Stores, get_typestore

    store = get_typestore(Stores.ROS2_JAZZY)
    String = store.types['std_msgs/msg/String']
    bag = tmp_path / 'plain'
    with Writer(bag, version=9, storage_plugin=StoragePlugin.MCAP) as writer:
        chatter = writer.add_connection('/chatter', String.__msgtype__, typestore=store)
        for k in range(3):
            data = store.serialize_cdr(String(data=f'message {k}'), String.__msgtype__)
            writer.write(chatter, 1_000_000_000 + k, data)
    status, out, err = run(capsys, 'info', bag)
    assert (status, err) == (0, '')
    (line,) = [line for line in out.splitlines() if line.startswith('unchecked:')]
    assert line == ('unchecked: plain.mcap: 1 of its 1 chunks carry no CRC (written without): '
                    "their messages' contents cannot be checked, nor can the data section")
    for own in (sim_bag, POSITION, ROOT / 'bags' / 'trajectory'):  # (the sample bags too)
        status, out, err = run(capsys, 'info', own)
        assert (status, err) == (0, '') and 'unchecked' not in out, own


def test_recover_onto_a_full_disk(sim_bag, tmp_path, capsys, monkeypatch):
    """One ERROR line naming the output (before: `ERROR: [Errno 28] No space left on device`),
    nothing left behind."""
    out = tmp_path / 'full' / 'out'
    out.parent.mkdir()
    fill_disk_under(monkeypatch, out.parent, room=100_000)
    status, stdout, err = run(capsys, 'recover', sim_bag, '-o', out)
    assert (status, stdout) == (1, '')
    assert err == (
        f'ERROR: cannot write {out}: No space left on device; nothing recovered ({out} '
        'removed)\n'
    )
    assert not out.exists()


def test_recover_onto_a_real_full_disk(sim_bag, tmp_path):
    disk = tmp_path / 'disk'
    status, out, err, left = run_on_small_disk(
        disk, '64k', 'bag', 'recover', str(sim_bag), '-o', str(disk / 'out')
    )
    assert (status, out, left) == (1, '', '')
    assert err == (
        f'ERROR: cannot write {disk / "out"}: No space left on device; nothing recovered '
        f'({disk / "out"} removed)\n'
    )


def test_a_symlink_loop_is_said_to_be_one(tmp_path, capsys):
    loop = tmp_path / 'loop'
    loop.symlink_to(loop)
    for action in ('info', 'recover'):
        expected = f'ERROR: {loop}: too many levels of symbolic links (a symbolic link loop)\n'
        assert run(capsys, action, loop) == (1, '', expected)
