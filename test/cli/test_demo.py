"""`cloe demo` prints the real-time factor the simulator achieved (read from its last line)."""

from __future__ import annotations

from cloe_ros.cli.demo import achieved_factor

LINE = (
    '[INFO] [1796158292.4] [quadrotor_sim]: done: 50 s simulated in {wall} s of wall time '
    '(real-time factor {factor}, asked 2)\n'
)


def test_achieved_factor_held():
    text = achieved_factor('started\n' + LINE.format(wall='25.30', factor='1.98'), 2.0)
    assert text == 'real-time factor achieved 1.98 (asked 2, 25.30 s of wall time)'


def test_achieved_factor_behind_says_so():
    text = achieved_factor(LINE.format(wall='67.70', factor='0.739'), 2.0)
    assert text.startswith('real-time factor achieved 0.739 (asked 2, 67.70 s of wall time)')
    assert 'could not hold 2x real time' in text and 'message stamps' in text


def test_achieved_factor_missing():
    assert 'did not report' in achieved_factor('[INFO] started\n', 2.0)
