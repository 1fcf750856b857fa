"""`cloe bag info|recover`: what they accept and what they say about a bag."""

from __future__ import annotations

import re
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
