"""Write (or check) the golden outputs of the inference engine on the sample bags and the corpus.

The golden test (test/test_golden.py) replays each bag through the engine with the default
settings, as ``cloe infer`` does, and compares what it publishes with the arrays written here:
the state and the ``cloe/parameters`` values of every ``--every``-th estimate, the predicted
positions and 95 % radii at 0.5, 1, 2, 5 and 10 s of every ``--every-prediction``-th prediction,
the counts, and sums over the whole run (so that no estimate goes unchecked). Both compute them
in a child process whose numeric kernels are pinned (test/golden_outputs.py), so that they are
the same on every x86-64 machine. Rebuild them only when a change is meant to change the
numbers, and say so in the commit:

    python scripts/golden.py write            # test/golden/*.npz
    python scripts/golden.py check            # what the test checks, with the largest errors

The corpus is the NanoBench flights converted with ``cloe bag nanobench`` (test/corpus.py says
where the tests find it).
"""

from __future__ import annotations

import argparse
import sys
from pathlib import Path

REPO = Path(__file__).resolve().parents[1]
sys.path.insert(0, str(REPO))

from test.golden_outputs import GOLDEN, bags, compare, pinned_golden_outputs  # noqa: E402


def main() -> int:
    parser = argparse.ArgumentParser(description=__doc__.split('\n\n')[0])
    parser.add_argument('action', choices=['write', 'check'])
    parser.add_argument('bags', nargs='*', type=Path, help='default: sample bags and corpus')
    args = parser.parse_args()
    import numpy as np

    worst = 0.0
    for bag in args.bags or bags():
        got = pinned_golden_outputs(bag)  # with the same kernels on every machine
        out = GOLDEN / f'{bag.name}.npz'
        if args.action == 'write':
            GOLDEN.mkdir(exist_ok=True)
            np.savez_compressed(out, **got)
            print(f'{out.relative_to(REPO)}: {sum(a.size for a in got.values())} values')
        else:
            errors = compare(dict(np.load(out)), got)
            largest = max(errors.values(), default=0.0)
            worst = max(worst, largest)
            print(f'{bag.name}: largest difference {largest:.3g}')
    return 0 if worst <= 1e-9 else 1


if __name__ == '__main__':
    sys.exit(main())
