"""The batched estimator step alone: microseconds per vehicle per step, for N vehicles at once.

    .venv/bin/python scripts/engine_benchmark.py [--vehicles 1 10 100] [--steps 2000]

For each algorithm and each N: one estimator holding N vehicles (``make_estimator`` with (N, 12)
states), stepped ``--steps`` times on a circle flown by every vehicle with its own phase; the
median over 5 repeats of the process CPU time per step, divided by N (with one BLAS thread, as in
the nodes: cloe_ros/threads.py). This is the estimator's cost only: the engine around it (input
checks, the grid, anticipation, one per vehicle) and rclpy are not in it;
``scripts/swarm_benchmark.py`` measures the whole node.

For cloe_iv it also prints the floor that LAPACK sets: the identifier's solves (every 0.05 s)
and its excitation measures' decompositions (every 0.25 s), as numpy makes them on the same
batches of random matrices of the same sizes, per vehicle-step. Those calls are part of the
method's numbers (the golden test holds them to 1e-9), so no rewrite of the code around them
goes below it.
"""

from __future__ import annotations

import argparse
import statistics
import sys
import time
from pathlib import Path

import numpy as np

sys.path.insert(0, str(Path(__file__).resolve().parents[1]))  # (this checkout's package)

from cloe_ros.core.algorithms import ALGORITHMS, make_estimator
from cloe_ros.core.estimator import EstimatorConfig
from cloe_ros.threads import limit_blas_threads


def circle(n: int, steps: int, h: float) -> tuple[np.ndarray, np.ndarray]:
    """Measurements (steps, N, 12) and references (steps, N, 4) of N vehicles on circles."""
    t = h * np.arange(steps)[:, None] + np.linspace(0.0, 2 * np.pi, n, endpoint=False)[None]
    zeta = np.zeros((steps, n, 12))
    zeta[..., 0], zeta[..., 1] = np.cos(0.5 * t), -0.5 * np.sin(0.5 * t)
    zeta[..., 4], zeta[..., 5] = np.sin(0.5 * t), 0.5 * np.cos(0.5 * t)
    zeta[..., 10] = 1.0
    r = np.zeros((steps, n, 4))
    r[..., 0], r[..., 1], r[..., 3] = zeta[..., 0], zeta[..., 4], 1.0
    return zeta, r


def per_vehicle_us(algorithm: str, n: int, steps: int, h: float = 0.01) -> float:
    zeta, r = circle(n, steps + 1, h)
    times = []
    for _ in range(5):
        est = make_estimator(EstimatorConfig(algorithm=algorithm), zeta[0], r[0], h)
        start = time.process_time()
        for k in range(1, steps + 1):
            est.step(zeta[k], r[k], h)
        times.append(time.process_time() - start)
    return 1e6 * statistics.median(times) / steps / n


def lapack_floor_us(n: int, repeats: int = 5) -> float:
    """CPU time per vehicle-step of the cloe_iv identifier's LAPACK calls alone, for N vehicles
    stepped together: per row, ``solve`` of its (WIDTH, WIDTH) normal equations every
    ``_solve_every`` steps, and two ``eigh``, one ``svd`` and one ``inv`` of its size every
    ``_excitation_every`` steps (the median over ``repeats`` of random positive definite
    matrices, in the numpy code's batches: all vehicles, the rows of one size together)."""
    from cloe_ros.core import identifier

    zeta, r = circle(n, 1, 0.01)
    ident = make_estimator(EstimatorConfig(algorithm='cloe_iv'), zeta[0], r[0], 0.01).identifier
    rng = np.random.default_rng(0)

    def spd(size: int, count: int) -> np.ndarray:
        x = rng.standard_normal((n, count, size, size + 2))
        return x @ np.swapaxes(x, -1, -2)

    times = []
    for _ in range(repeats):
        lhs = spd(identifier.WIDTH, identifier.N_ROWS)
        rhs = rng.standard_normal((n, identifier.N_ROWS, identifier.WIDTH, 1))
        groups = [(size, int(np.sum(identifier.ROW_SIZE == size)))
                  for size in np.unique(identifier.ROW_SIZE)
                  if ident._mask[np.flatnonzero(identifier.ROW_SIZE == size)[0], 0]]  # fmt: skip
        mats = [spd(size, count) for size, count in groups]
        start = time.process_time()
        np.linalg.solve(lhs, rhs)
        solve = time.process_time() - start
        start = time.process_time()
        for g in mats:
            np.linalg.eigh(g)
            np.linalg.eigh(g)
            np.linalg.svd(g, compute_uv=False)
            np.linalg.inv(g)
        excitation = time.process_time() - start
        times.append(solve / ident._solve_every + excitation / ident._excitation_every)
    return 1e6 * statistics.median(times) / n


def main(argv: list[str] | None = None) -> int:
    parser = argparse.ArgumentParser(description=__doc__.split('\n\n')[0])
    parser.add_argument('--vehicles', type=int, nargs='+', default=[1, 10, 100])
    parser.add_argument('--steps', type=int, default=2000)
    parser.add_argument('--algorithms', nargs='+', default=list(ALGORITHMS), choices=ALGORITHMS)
    args = parser.parse_args(argv)
    limit_blas_threads()  # as the nodes do: the CPU time is then this thread's work alone
    print('| algorithm | ' + ' | '.join(f'N = {n}: µs per vehicle-step' for n in args.vehicles)
          + ' |')  # fmt: skip
    print('|---|' + '---|' * len(args.vehicles))
    for algorithm in args.algorithms:
        cells = [f'{per_vehicle_us(algorithm, n, args.steps):.2f}' for n in args.vehicles]
        print(f'| {algorithm} | ' + ' | '.join(cells) + ' |', flush=True)
    if 'cloe_iv' in args.algorithms:
        cells = [f'{lapack_floor_us(n):.2f}' for n in args.vehicles]
        print('| cloe_iv: its LAPACK calls alone | ' + ' | '.join(cells) + ' |', flush=True)
    return 0


if __name__ == '__main__':
    raise SystemExit(main())
