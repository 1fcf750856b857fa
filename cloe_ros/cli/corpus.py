"""``cloe evaluate corpus PATH...``: every flight of many bags, scored beside the baselines.

Each bag is replayed through the engine exactly as ``cloe infer`` runs it (one configuration for
every flight: the node's defaults, or ``--config``), and every published prediction issued from
``--score-from`` s after the first odometry on is scored against the odometry that followed
(:func:`~cloe_ros.core.evaluation.score_flight`). Flights run in parallel processes
(``--jobs``).
"""

from __future__ import annotations

import json
import os
import sys
from concurrent.futures import ProcessPoolExecutor
from pathlib import Path

import numpy as np

from cloe_ros.cli.errors import CliError
from cloe_ros.cli.outputs import check_new_file, json_safe
from cloe_ros.cli.workers import worker_count
from cloe_ros.core.evaluation import BASELINES, HORIZONS, FlightScore, score_flight
from cloe_ros.errors import CloeError
from cloe_ros.io.config import build_configs, load_settings

#: Column labels of the predictors.
LABELS = {
    'model': 'cloe_ros',
    'constant_velocity': 'const. vel.',
    'hold_position': 'hold pos.',
    'reference_held': 'ref. held',
    'reference_lag': 'ref. + lag',
}


def find_bags(paths: list[Path]) -> list[Path]:
    """The bags under ``paths``: a bag directory (with metadata.yaml) or a ``.mcap`` file is a
    bag; any other directory is searched for them, recursively. Sorted, without duplicates."""
    found: list[Path] = []
    for path in paths:
        if not path.exists():
            raise CliError(f'{path} does not exist')
        if path.is_file() or (path / 'metadata.yaml').is_file():
            found.append(path)
            continue
        for root, dirs, files in os.walk(path):
            here = Path(root)
            if 'metadata.yaml' in files:
                found.append(here)
                dirs[:] = []
                continue
            found += [here / f for f in files if f.endswith('.mcap')]
            dirs.sort()
    out = sorted(dict.fromkeys(p.resolve() for p in found))
    if not out:
        raise CliError(f'no bag (a directory with metadata.yaml, or a .mcap file) under '
                       f'{", ".join(map(str, paths))}')  # fmt: skip
    return out


def _evaluate(job: tuple) -> tuple[Path, list[FlightScore] | str]:
    """One bag's flights, or those of its vehicles ``only`` (run in a worker process): their
    scores, or why there are none."""
    from cloe_ros.io.replay import replay_flights

    path, settings, score_from, only = job
    try:
        records = replay_flights(path, settings, only=only)
        return path, [score_flight(r, score_from) for r in records]
    except CloeError as err:
        return path, str(err)


def _jobs(bags: list[Path], settings: dict, score_from: float, jobs: int) -> list[tuple]:
    """The work of a corpus: a bag per job, or, with more worker processes than bags, each
    vehicle of a bag of several a job of its own (a bag that cannot be listed is one job, which
    says why)."""
    from cloe_ros.io.replay import bag_vehicles

    work = []
    split = worker_count(jobs, 1 << 30) > len(bags)
    for bag in bags:
        vehicles = None
        if split:
            try:
                vehicles = bag_vehicles(bag)
            except CloeError:
                pass  # (its job says why)
        if vehicles is not None and len(vehicles) > 1:
            work += [(bag, settings, score_from, [v]) for v in vehicles]
        else:
            work.append((bag, settings, score_from, None))
    return work


def _row(values: np.ndarray) -> str:
    return ' '.join(f'{v:6.3f}' for v in values)


def run_corpus(args) -> int:
    settings = load_settings(args.config) if args.config else {}
    settings = {k: v for k, v in settings.items() if k != 'vehicles'}
    build_configs(settings)
    if args.json:
        check_new_file(args.json, args.force, '--json')
    worker_count(args.jobs, 1)  # a bad --jobs is an error before the bags are searched
    bags = find_bags(list(args.paths))
    scores: list[FlightScore] = []
    failed: list[tuple[Path, str]] = []
    work = _jobs(bags, settings, args.score_from, args.jobs)
    with ProcessPoolExecutor(max_workers=worker_count(args.jobs, len(work))) as pool:
        for done, (path, result) in enumerate(pool.map(_evaluate, work), start=1):
            if isinstance(result, str):
                if (path, result) not in failed:  # (once per bag, however split)
                    failed.append((path, result))
            else:
                scores += result
            if not args.quiet:
                print(f'[{done}/{len(work)}] {path.name}', file=sys.stderr, flush=True)
    for _, why in failed:
        print(f'ERROR: {why}', file=sys.stderr)
    if not scores:
        raise CliError('no flight could be scored')
    print(format_corpus(scores, args.score_from))
    if args.json:
        args.json.write_text(json.dumps(json_safe(corpus_summary(scores, settings,
                                                                 args.score_from)), indent=2))
    return 1 if failed else 0


def corpus_summary(scores: list[FlightScore], settings: dict, score_from: float) -> dict:
    """The numbers of a corpus run (what ``--json`` writes)."""
    names = ('model', *BASELINES)
    return {
        'settings': settings,
        'score_from_s': score_from,
        'horizons_s': list(HORIZONS),
        'flights': [s.as_dict() for s in scores],
        'median_rmse_m': {n: np.nanmedian([s.rmse[n] for s in scores], axis=0).tolist()
                          for n in names},
        'pooled_coverage': pooled_coverage(scores).tolist(),
        'worst_ratio': max(s.worst_ratio for s in scores),
    }


def pooled_coverage(scores: list[FlightScore]) -> np.ndarray:
    """The fraction of all scored positions of the corpus inside their radius, per horizon (NaN
    for a horizon no flight scored)."""
    inside = np.nansum([s.coverage * s.count for s in scores], axis=0)
    count = np.sum([s.count for s in scores], axis=0)
    return np.where(count > 0, inside / np.maximum(count, 1), np.nan)


def format_corpus(scores: list[FlightScore], score_from: float) -> str:
    """The per-flight table and the medians over flights."""
    h = '/'.join(f'{x:g}' for x in HORIZONS)
    width = max(len(s.name) for s in scores)
    lines = [
        f'prediction RMSE [m] at {h} s, predictions issued from {score_from:g} s after the first '
        'odometry on, against the odometry that followed',
        f'{"flight":<{width}}  {LABELS["model"]:<27} {LABELS["constant_velocity"]:<27} '
        f'{LABELS["hold_position"]:<27} worst  coverage of the 95 % radius  untracked',
    ]
    for s in scores:
        lines.append(
            f'{s.name:<{width}}  {_row(s.rmse["model"])} {_row(s.rmse["constant_velocity"])} '
            f'{_row(s.rmse["hold_position"])} {s.worst_ratio:5.2f}  '
            + ' '.join(f'{c:5.2f}' for c in s.coverage) + f'   {100 * s.untracked:5.1f} %'
        )
    lines.append('')
    lines.append(f'median over {len(scores)} flights, RMSE [m] at {h} s:')
    for name in ('model', *BASELINES):
        med = np.nanmedian([s.rmse[name] for s in scores], axis=0)
        lines.append(f'  {LABELS[name]:<12} {_row(med)}')
    worst = max(scores, key=lambda s: s.worst_ratio)
    above = [s.name for s in scores if s.worst_ratio > 1.2]
    lines.append(
        'worst ratio to the better of constant velocity and hold (any horizon): '
        f'{worst.worst_ratio:.2f} ({worst.name}); above 1.2: {len(above)} flight(s)'
        + (f' ({", ".join(above)})' if above else '')
    )
    lines.append('coverage of the 95 % radius, pooled over the flights: '
                 + ' '.join(f'{c:.3f}' for c in pooled_coverage(scores)))  # fmt: skip
    return '\n'.join(lines)
