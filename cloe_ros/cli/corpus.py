"""``cloe evaluate corpus PATH...``: every flight of many bags, scored beside the baselines.

Each bag is replayed through the engine exactly as ``cloe infer`` runs it (one configuration for
every flight: the node's defaults, or ``--config``), and every published prediction issued from
``--score-from`` s after the first odometry on is scored against the odometry that followed
(:func:`~cloe_ros.core.evaluation.score_flight`). Flights run in parallel processes
(``--jobs``).

A flight with nothing to score (no prediction issued from ``--score-from`` on, or none with finite
odometry over its horizon) is treated as a bag that cannot be read: an ``ERROR:`` line names it
and says why, and the exit status is 1. It keeps its row, marked, but is left out of the medians,
the pooled coverage and the worst ratio.
"""

from __future__ import annotations

import json
import os
import sys
import warnings
from pathlib import Path

import numpy as np

from cloe_ros.cli.errors import CliError
from cloe_ros.cli.outputs import check_new_file, json_safe
from cloe_ros.cli.workers import pool, worker_count
from cloe_ros.core.evaluation import (
    BASELINES,
    HORIZONS,
    FlightRecord,
    FlightScore,
    score_flight,
)
from cloe_ros.errors import CloeError
from cloe_ros.io.config import command_settings

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
    bag; any other directory is searched for them, recursively, following symbolic links (a
    directory reached twice, e.g. through a link to a folder above it, is searched once). Sorted,
    without duplicates."""
    found: list[Path] = []
    for path in paths:
        if not path.exists():
            raise CliError(f'{path} does not exist')
        if path.is_file() or (path / 'metadata.yaml').is_file():
            found.append(path)
            continue
        seen: set[Path] = set()
        for root, dirs, files in os.walk(path, followlinks=True):
            here = Path(root)
            real = here.resolve()
            if real in seen:  # (a link loop, or a folder linked twice)
                dirs[:] = []
                continue
            seen.add(real)
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


def _evaluate(job: tuple) -> tuple[Path, list[tuple[FlightScore, str]] | str]:
    """One bag's flights, or those of its vehicles ``only`` (run in a worker process): each
    flight's scores and why it has nothing to score ('' if it has), or why the bag has no
    flight."""
    from cloe_ros.io.replay import replay_flights

    path, settings, score_from, only = job
    try:
        records = replay_flights(path, settings, only=only)
        scores = [score_flight(r, score_from) for r in records]
        return path, [(s, _nothing_to_score(r, s, score_from)) for r, s in zip(records, scores)]
    except CloeError as err:
        return path, str(err)


def _nothing_to_score(record: FlightRecord, score: FlightScore, score_from: float) -> str:
    """Why ``score`` holds no scored prediction at any horizon, or '' if it holds one."""
    if score.count.sum() > 0:
        return ''
    issued = record.issue_t
    if len(record.odom_p) == 0:
        return 'no odometry message was accepted (each was rejected or malformed)'
    if not np.isfinite(record.odom_p).all(axis=1).any():
        return f'none of its {len(record.odom_p)} odometry positions is finite'
    if len(issued) == 0:
        return 'no prediction was issued'
    if not (issued >= score_from).any():
        return (f'no prediction was issued from --score-from {score_from:g} s on (the last at '
                f'{issued.max():.1f} s after the first odometry)')  # fmt: skip
    n = int((issued >= score_from).sum())
    return (f'none of the {n} predictions issued from {score_from:g} s on has a finite position '
            'and finite odometry over any horizon')  # fmt: skip


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
    settings = command_settings(args.config, args.node)
    if args.json:
        check_new_file(args.json, args.force, '--json')
    worker_count(args.jobs, 1)  # a bad --jobs is an error before the bags are searched
    bags = find_bags(list(args.paths))
    flights: list[tuple[FlightScore, str]] = []
    failed: list[tuple[Path, str]] = []
    unread: list[tuple[Path, str]] = []  # (bags that could not be read: no flight of theirs)
    work = _jobs(bags, settings, args.score_from, args.jobs)
    with pool(_evaluate, work, worker_count(args.jobs, len(work))) as futures:
        for done, future in enumerate(futures, start=1):
            path, result = future.result()
            if isinstance(result, str):
                if (path, result) not in failed:  # (once per bag, however split)
                    failed.append((path, result))
                    unread.append((path, result))
            else:
                flights += result
                failed += [(path, f'{_flight_of(path, score)}: nothing to score: {why}')
                           for score, why in result if why]  # fmt: skip
            if not args.quiet:
                print(f'[{done}/{len(work)}] {path.name}', file=sys.stderr, flush=True)
    for _, why in failed:
        print(f'ERROR: {why}', file=sys.stderr)
    if all(why for _, why in flights):
        raise CliError('no flight could be scored')
    print(format_corpus(flights, args.score_from, unread))
    if args.json:
        summary = corpus_summary(flights, settings, args.score_from, unread)
        args.json.write_text(json.dumps(json_safe(summary), indent=2))
    return 1 if failed else 0


def _flight_of(path: Path, score: FlightScore) -> str:
    """The bag, and the flight's name when it is not the bag's (a vehicle of several)."""
    return str(path) if score.name == path.name else f'{path} ({score.name})'


def _flight_dict(score: FlightScore, why: str) -> dict:
    out = {**score.as_dict(), 'scored': not why}
    if why:
        out['nothing_to_score'] = why
    return out


def corpus_summary(
    flights: list[tuple[FlightScore, str]], settings: dict, score_from: float,
    unread: list[tuple[Path, str]] = (),
) -> dict:
    """The numbers of a corpus run (what ``--json`` writes). ``flights``: each flight's scores and
    why it has nothing to score ('' if it has); such a flight is written with ``"scored": false``
    and the reason, and the medians, the pooled coverage and the worst ratio are those of the
    scored flights alone. ``unread``: the bags that could not be read, and why (``"unread"``:
    a corpus that lost a bag does not read as whole)."""
    scored = [s for s, why in flights if not why]
    worst = worst_flight(scored)
    return {
        'settings': settings,
        'score_from_s': score_from,
        'horizons_s': list(HORIZONS),
        'flights': [_flight_dict(s, why) for s, why in flights],
        'flights_scored': len(scored),
        'unread': [{'bag': str(path), 'error': why} for path, why in unread],
        'median_rmse_m': {n: median_rmse(scored, n).tolist() for n in ('model', *BASELINES)},
        'pooled_coverage': pooled_coverage(scored).tolist(),
        'worst_ratio': worst.worst_ratio if worst else None,
        'worst_ratio_flight': worst.name if worst else None,
    }


def median_rmse(scores: list[FlightScore], name: str) -> np.ndarray:
    """The median over ``scores`` of predictor ``name``'s RMSE, per horizon, of the flights that
    scored that horizon (NaN for a horizon none did)."""
    with warnings.catch_warnings():  # (numpy warns of a horizon no flight scored: that is NaN)
        warnings.simplefilter('ignore', RuntimeWarning)
        return np.nanmedian([s.rmse[name] for s in scores], axis=0)


def worst_flight(scores: list[FlightScore]) -> FlightScore | None:
    """The flight of ``scores`` with the largest worst ratio (the first of equals), of those that
    have one; None if none has."""
    rated = [s for s in scores if not np.isnan(s.worst_ratio)]
    return max(rated, key=lambda s: s.worst_ratio) if rated else None


def pooled_coverage(scores: list[FlightScore]) -> np.ndarray:
    """The fraction of all scored positions of the corpus inside their radius, per horizon (NaN
    for a horizon no flight scored)."""
    inside = np.nansum([s.coverage * s.count for s in scores], axis=0)
    count = np.sum([s.count for s in scores], axis=0)
    return np.where(count > 0, inside / np.maximum(count, 1), np.nan)


def format_corpus(
    flights: list[tuple[FlightScore, str]], score_from: float, unread: list[tuple[Path, str]] = ()
) -> str:
    """The per-flight table and the medians, worst ratio and pooled coverage over the flights.
    ``flights``: each flight's scores and why it has nothing to score ('' if it has); such a
    flight's row says so and why, and it is left out of what follows the table. ``unread``: the
    bags that could not be read, a row each (named by the bag), and why."""
    h = '/'.join(f'{x:g}' for x in HORIZONS)
    width = max(len(name) for name in [s.name for s, _ in flights] + [p.name for p, _ in unread])
    lines = [
        f'prediction RMSE [m] at {h} s, predictions issued from {score_from:g} s after the first '
        'odometry on, against the odometry that followed',
        f'{"flight":<{width}}  {LABELS["model"]:<27} {LABELS["constant_velocity"]:<27} '
        f'{LABELS["hold_position"]:<27} worst  coverage of the 95 % radius  untracked',
    ]
    for s, why in flights:
        if why:
            lines.append(f'{s.name:<{width}}  nothing to score: {why}')
            continue
        lines.append(
            f'{s.name:<{width}}  {_row(s.rmse["model"])} {_row(s.rmse["constant_velocity"])} '
            f'{_row(s.rmse["hold_position"])} {s.worst_ratio:5.2f}  '
            + ' '.join(f'{c:5.2f}' for c in s.coverage) + f'   {100 * s.untracked:5.1f} %'
        )
    lines += [f'{path.name:<{width}}  not read (see its ERROR line)' for path, _ in unread]
    scored = [s for s, why in flights if not why]
    left_out = (f' ({len(flights) - len(scored)} flight(s) with nothing to score left out)'
                if len(scored) < len(flights) else '')  # fmt: skip
    lines.append('')
    lines.append(f'median over {len(scored)} flights{left_out}, RMSE [m] at {h} s:')
    for name in ('model', *BASELINES):
        lines.append(f'  {LABELS[name]:<12} {_row(median_rmse(scored, name))}')
    worst = worst_flight(scored)
    above = [s.name for s in scored if s.worst_ratio > 1.2]
    lines.append(
        'worst ratio to the better of constant velocity and hold (any horizon): '
        + (f'{worst.worst_ratio:.2f} ({worst.name})' if worst else 'none (no flight has one)')
        + f'; above 1.2: {len(above)} flight(s)'
        + (f' ({", ".join(above)})' if above else '')
    )
    lines.append(f'coverage of the 95 % radius, pooled over the flights{left_out}: '
                 + ' '.join(f'{c:.3f}' for c in pooled_coverage(scored)))  # fmt: skip
    return '\n'.join(lines)
