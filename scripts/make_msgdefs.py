"""Write cloe_ros/io/msgdefs.py: the definitions and type hashes of the message types the package
writes, as rosbags' ROS 2 Jazzy type store gives them.

With them a bag is written without the type store, whose import and construction take about
0.15 s of CPU, a tenth of what ``cloe infer`` imports (EVALUATION.md, section 4). Rerun it when
the list below or rosbags changes; ``--check`` only says whether the file is up to date (exit
status 1 if not). test/io/test_writer.py checks it.
"""

from __future__ import annotations

import argparse
import sys
from pathlib import Path

REPO = Path(__file__).resolve().parent.parent
sys.path.insert(0, str(REPO))

from cloe_ros.io import messages  # noqa: E402

OUT = REPO / 'cloe_ros' / 'io' / 'msgdefs.py'
#: What the package's bags hold: the contract's inputs and every output, diagnostics, the clock.
TYPES = (messages.ODOMETRY, messages.POSE_STAMPED, messages.PATH, messages.FLOAT64_MULTI_ARRAY,
         messages.PARAMETER_EVENT, messages.STRING, messages.MARKER_ARRAY,
         messages.DIAGNOSTIC_ARRAY, messages.CLOCK)  # fmt: skip

HEAD = '''"""The definitions (``ros2msg`` text) and type hashes (RIHS01) of the message types
the package writes, as rosbags' ROS 2 Jazzy type store gives them, so that
:class:`~cloe_ros.io.writer.BagWriter` needs no type store for them (its import and construction
cost about 0.15 s).

Written by ``python scripts/make_msgdefs.py``: do not edit. test/io/test_writer.py checks that they
are still rosbags'.
"""

#: message type -> (definition, RIHS01 hash)
MSGDEFS: dict[str, tuple[str, str]] = {
'''


def render() -> str:
    store = messages.TYPESTORE
    parts = [HEAD]
    for msgtype in TYPES:
        text = store.generate_msgdef(msgtype, ros_version=2)[0]
        if '\\' in text or '"""' in text or not text.endswith('\n'):
            msg = f'the definition of {msgtype} does not fit a triple-quoted string'
            raise SystemExit(msg)
        parts.append(f"    '{msgtype}': (\n        \"\"\"\\\n{text}\"\"\",\n"
                     f"        '{store.hash_rihs01(msgtype)}',\n    ),\n")  # fmt: skip
    parts.append('}\n')
    return ''.join(parts)


def main() -> int:
    parser = argparse.ArgumentParser(description=__doc__.split('\n\n')[0])
    parser.add_argument('--check', action='store_true', help='only say whether it is up to date')
    args = parser.parse_args()
    text = render()
    if args.check:
        current = OUT.read_text() == text
        print(f'{OUT.relative_to(REPO)} is {"up to date" if current else "out of date"}')
        return 0 if current else 1
    OUT.write_text(text)
    print(f'wrote {OUT.relative_to(REPO)}: {len(TYPES)} types')
    return 0


if __name__ == '__main__':
    sys.exit(main())
