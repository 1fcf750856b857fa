"""The `cloe` command in a shell: exit statuses as documented in `cloe --help`, quiet on a closed
pipe."""

from __future__ import annotations

import argparse
import os
import re
import subprocess
import sys
from pathlib import Path

import pytest

from cloe_ros.cli import bag as bag_command
from cloe_ros.cli.main import build_parser, main

ROOT = Path(__file__).resolve().parents[2]
POSITION = ROOT / 'bags' / 'position'


def cloe(*args: str, **kwargs) -> subprocess.CompletedProcess:
    """This source tree's `cloe` in a process of its own."""
    env = dict(os.environ, PYTHONPATH=str(ROOT))
    return subprocess.run([sys.executable, '-m', 'cloe_ros.cli.main', *args], env=env,
                          timeout=120, **kwargs)  # fmt: skip


def test_help_documents_the_exit_statuses(capsys):
    with pytest.raises(SystemExit) as info:
        main(['--help'])
    assert info.value.code == 0
    out = capsys.readouterr().out
    statuses = dict(re.findall(r'^  (\d+) +(\S.*)$', out.split('exit status:')[1], re.M))
    assert set(statuses) == {'0', '1', '2', '130', '141'}
    assert statuses['0'] == 'success'
    assert 'ERROR:' in statuses['1']
    assert 'does not parse' in statuses['2']
    assert 'Ctrl-C' in statuses['130']
    assert 'closed' in statuses['141']


def test_the_statuses_are_those_documented(tmp_path, capsys, monkeypatch):
    assert main(['bag', 'info', str(POSITION)]) == 0
    capsys.readouterr()
    assert main(['bag', 'info', str(tmp_path / 'nope')]) == 1
    assert capsys.readouterr().err == f'ERROR: {tmp_path / "nope"} does not exist\n'
    with pytest.raises(SystemExit) as info:
        main(['bag', 'info', '--no-such-option', str(POSITION)])
    assert info.value.code == 2
    assert 'unrecognized arguments' in capsys.readouterr().err

    def interrupted(args):
        raise KeyboardInterrupt

    monkeypatch.setattr(bag_command, 'bag_info', lambda path: interrupted(path))
    assert main(['bag', 'info', str(POSITION)]) == 130
    assert capsys.readouterr().err == 'interrupted\n'


def _parsers(parser: argparse.ArgumentParser, prefix: tuple[str, ...] = ('cloe',)):
    """``(command words, parser)`` of ``cloe`` and of every command and action under it."""
    yield prefix, parser
    for action in parser._actions:
        if isinstance(action, argparse._SubParsersAction):
            for name, sub in action.choices.items():
                yield from _parsers(sub, (*prefix, name))


def test_every_help_text_is_there_plain_and_complete():
    """Every argument of every command says what it is, in plain text (no RST markup); a command
    with actions names them all in ``cloe --help``; ``cloe infer --help`` names the outputs it
    writes (those of the output encoder), the option that names the output, and .mcap inputs."""
    from cloe_ros.io.outputs import OutputConfig, OutputEncoder

    parsers = dict(_parsers(build_parser()))
    for words, parser in parsers.items():
        text = parser.format_help()
        assert '``' not in text, words
        for action in parser._actions:
            if not isinstance(action, argparse._SubParsersAction):
                assert action.help, (words, action.dest)
    top = parsers[('cloe',)].format_help()
    evaluate = re.search(r'^    evaluate +(.*(\n {14}.*)*)', top, re.M).group(1)
    assert 'corpus' in evaluate
    bag = re.search(r'^    bag +(.*(\n {14}.*)*)', top, re.M).group(1)
    assert 'recover' in bag and 'NanoBench' in bag
    assert 'NanoBench' in parsers[('cloe', 'bag')].description
    infer = parsers[('cloe', 'infer')]
    description = ' '.join(infer.description.split())
    for topic in OutputEncoder(OutputConfig(), '/uav1').topics:
        assert f' {topic.rsplit("/", 1)[1]}' in description, topic
    assert 'OUT_BAG' not in infer.format_help() and 'into the bag OUTPUT' in description
    assert '.mcap' in next(a.help for a in infer._actions if a.dest == 'bag')
    scenario = parsers[('cloe', 'evaluate', 'sim')].format_help()
    assert re.search(r'--scenario \{.*\}\s+the simulated scenario \(default: position\)', scenario)


def test_a_closed_pipe_ends_quietly():
    """The reader of stdout is gone before anything is written (as `| head -0`, or `| head -1`
    once head has its line): no `ERROR: [Errno 32] Broken pipe`, no traceback, status 141 as
    `cat` killed by SIGPIPE; the other commands' statuses are unchanged."""
    read, write = os.pipe()
    os.close(read)
    try:
        proc = cloe('bag', 'info', str(POSITION), stdout=write, stderr=subprocess.PIPE)
    finally:
        os.close(write)
    assert (proc.returncode, proc.stderr) == (141, b'')


def test_head_in_a_shell_pipeline():
    env = dict(os.environ, PYTHONPATH=str(ROOT))
    command = f'{sys.executable} -m cloe_ros.cli.main bag info {POSITION} | head -1'
    proc = subprocess.run(['sh', '-c', command], env=env, capture_output=True, text=True,
                          timeout=120)  # fmt: skip
    assert proc.returncode == 0
    assert proc.stdout == f'bag:       {POSITION}\n'
    assert proc.stderr == ''


#: What `cloe --help` must not import: each takes a large part of a second (scipy.signal and
#: scipy.stats seconds on a busy machine), and only the command that runs needs it.
HEAVY = ('scipy', 'matplotlib', 'rclpy', 'rosbags', 'mcap')

HELP_SCRIPT = r'''
import argparse, contextlib, io, sys
from cloe_ros.cli.main import build_parser, main

def commands(parser, prefix=()):
    yield prefix
    for action in parser._actions:
        if isinstance(action, argparse._SubParsersAction):
            for name, sub in action.choices.items():
                yield from commands(sub, (*prefix, name))

shown = 0
for command in list(commands(build_parser())):
    with contextlib.redirect_stdout(io.StringIO()) as out:
        try:
            main([*command, '--help'])
        except SystemExit as end:
            assert end.code == 0, (command, end.code)
    assert out.getvalue().startswith('usage: cloe'), command
    shown += 1
heavy = sorted({m.split('.')[0] for m in sys.modules} & set(sys.argv[1:]))
print(shown, *heavy)
'''


def test_help_imports_nothing_heavy():
    """`cloe --help` and every `cloe COMMAND [ACTION] --help` start without scipy, matplotlib,
    rclpy, rosbags or mcap: the command modules that need them are imported when they run
    (cloe_ros.cli.commands). Checked on the modules a fresh interpreter imported, not on time."""
    env = dict(os.environ, PYTHONPATH=str(ROOT))
    proc = subprocess.run([sys.executable, '-c', HELP_SCRIPT, *HEAVY], env=env,
                          capture_output=True, text=True, timeout=120)  # fmt: skip
    assert proc.returncode == 0, proc.stderr
    shown, *heavy = proc.stdout.split()
    assert int(shown) >= 14  # cloe, 7 commands, evaluate's 3 targets, bag's 3 actions
    assert heavy == []


def test_the_command_runs_its_module(monkeypatch):
    """The parsed command calls the run function of its module, looked up when it runs."""
    from cloe_ros.cli.main import build_parser

    calls = []
    monkeypatch.setattr(bag_command, 'run_info', lambda args: calls.append(args.bag) or 7)
    args = build_parser().parse_args(['bag', 'info', 'B'])
    assert args.run(args) == 7 and calls == [Path('B')]
