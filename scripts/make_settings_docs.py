"""Write the views of the settings table (cloe_ros/settings.py) that live in files.

* the README's `cloe_inference` parameter table and the paragraph on runtime changes above it
  (between the `<!-- settings: ... -->` markers);
* config/inference.yaml, every value the node's default.

`python scripts/make_settings_docs.py` rewrites both; `--check` only says whether they are up to
date (exit status 1 if not). `test/test_settings_docs.py` checks them against the table.
"""

from __future__ import annotations

import argparse
import math
import sys
from pathlib import Path

REPO = Path(__file__).resolve().parent.parent
sys.path.insert(0, str(REPO))

from cloe_ros.settings import (  # noqa: E402
    AT_ONCE,
    NEXT_START,
    RESTARTS,
    RESTARTS_CLOE_IV,
    SETTINGS,
    Setting,
)

README = REPO / 'README.md'
CONFIG = REPO / 'config' / 'inference.yaml'
BEGIN = '<!-- settings: cloe_inference (written by scripts/make_settings_docs.py) -->'
END = '<!-- settings: end -->'


def _number(value) -> str:
    return f'{value:g}' if isinstance(value, float) else str(value)


def shown_default(s: Setting) -> str:
    """The default as the README shows it."""
    value = s.default
    if isinstance(value, bool):
        return str(value).lower()
    if isinstance(value, (list, tuple)):
        return '[' + ', '.join(_number(v) for v in value) + ']'
    if value == '':
        return "''"
    return _number(value)


def meaning(s: Setting) -> str:
    """The description, with the range and read-only flag after it."""
    extra = []
    if s.range is not None:
        extra.append(f'[{_number(s.range[0])}, {_number(s.range[1])}]')
    if s.read_only:
        extra.append('read-only')
    text = s.full_description()
    return text + (f' ({"; ".join(extra)})' if extra else '')


def _names(on_change: str) -> list[str]:
    return [f'`{s.name}`' for s in SETTINGS.values()
            if not s.read_only and s.on_change == on_change]  # fmt: skip


def _join(names: list[str]) -> str:
    return names[0] if len(names) == 1 else ', '.join(names[:-1]) + ' and ' + names[-1]


def readme_block() -> str:
    """The generated part of the README: the paragraph on runtime changes and the table."""
    paragraph = (
        f'Changing {_join(_names(RESTARTS))} at runtime restarts the estimators and forgets the '
        'identified models (counted as `resets` in `/diagnostics`); with `cloe_iv`, so does '
        f'changing {_join(_names(RESTARTS_CLOE_IV))}. Every other change applies at once and '
        f'keeps the state and the identified models: {_join(_names(AT_ONCE))}. '
        f'{_join(_names(NEXT_START))} applies from the next (re)start. The other settings are '
        'read-only: restart the node to change them.'
    )
    lines = [BEGIN, '', *_wrap(paragraph), '']
    lines += ['| parameter | default | meaning |', '|---|---|---|']
    lines += [f'| `{s.name}` | `{shown_default(s)}` | {meaning(s)} |' for s in SETTINGS.values()]
    lines += ['', END]
    return '\n'.join(lines)


def _wrap(text: str, width: int = 99) -> list[str]:
    lines, line = [], ''
    for word in text.split():
        if line and len(line) + 1 + len(word) > width:
            lines.append(line)
            line = word
        else:
            line = f'{line} {word}' if line else word
    return [*lines, line]


def readme_text(current: str) -> str:
    """``current`` (the README) with its generated block replaced."""
    start, end = current.index(BEGIN), current.index(END) + len(END)
    return current[:start] + readme_block() + current[end:]


def _yaml_value(value) -> str:
    if isinstance(value, bool):
        return str(value).lower()
    if isinstance(value, (list, tuple)):
        return '[' + ', '.join(_yaml_value(v) for v in value) + ']'
    if isinstance(value, float):
        return repr(value) if math.isfinite(value) else str(value)
    if value == '':
        return "''"
    return str(value)


def config_text() -> str:
    """config/inference.yaml: every setting at its default (``vehicles`` as a comment: rcl's
    parameter files cannot hold an empty list)."""
    lines = [
        '# cloe_inference parameters (ros2 run cloe_ros cloe_inference --ros-args --params-file '
        '<this>).',
        "# Every value is the node's default (e.g. algorithm: cloe_sm for the paper's CLOE-SM).",
        '# Written by scripts/make_settings_docs.py from cloe_ros/settings.py; the README gives',
        '# units and ranges. `cloe infer --config` reads the same file (and ignores the settings',
        "# of the node's own).",
        'cloe_inference:',
        '  ros__parameters:',
    ]
    for s in SETTINGS.values():
        if isinstance(s.default, list) and not s.default:
            lines.append(f'    # {s.name}: [/uav1, /uav2]   (default: [])')
            continue
        lines.append(f'    {s.name}: {_yaml_value(s.default)}')
    return '\n'.join(lines) + '\n'


def main(argv: list[str] | None = None) -> int:
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument('--check', action='store_true', help='only check; exit 1 if out of date')
    args = parser.parse_args(argv)
    stale = []
    for path, text in ((README, readme_text(README.read_text())), (CONFIG, config_text())):
        if path.read_text() != text:
            stale.append(path)
            if not args.check:
                path.write_text(text)
    for path in stale:
        print(f'{path.relative_to(REPO)}: {"out of date" if args.check else "rewritten"}')
    return 1 if stale and args.check else 0


if __name__ == '__main__':
    raise SystemExit(main())
