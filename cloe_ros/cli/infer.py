"""``cloe infer BAG -o OUT_BAG``: the node's engine over a recorded bag, outputs into a new bag.

``cloe infer BAG... -o DIR --jobs N``: many bags, ``N`` at once in separate processes (one per
core by default), each into ``DIR/<its name>``. A bag that fails is reported and the others are
still written; the exit status is then 1. After Ctrl-C no further bag is started, the outputs in
progress are removed, and stderr lists the outputs completed and those not written (a second
Ctrl-C meanwhile is ignored: :func:`~cloe_ros.cli.workers.pool`).

One bag of several vehicles is split the same way: its vehicles in ``N`` groups, each group
inferred in a process of its own that sends its encoded outputs to this one, which writes them
into ``OUT_BAG`` beside the copies of the inputs (:func:`_split`). Each vehicle's outputs are
those of a run over all of them in one process (an engine's estimates do not depend on the
vehicles it is batched with)."""

from __future__ import annotations

import argparse
import multiprocessing
import shutil
import sys
import time
from collections import Counter
from dataclasses import dataclass, field
from pathlib import Path
from queue import Empty

from cloe_ros.cli.errors import CliError
from cloe_ros.cli.outputs import check_folder, make_folder
from cloe_ros.cli.progress import ProgressBar
from cloe_ros.cli.workers import pool, worker_count
from cloe_ros.core.engine import NS, VehicleEngine
from cloe_ros.core.fleet import Fleet, RecordingBatches
from cloe_ros.errors import CloeError
from cloe_ros.interrupts import uninterrupted
from cloe_ros.io import messages
from cloe_ros.io.config import NODE_NAME, build_configs, command_settings
from cloe_ros.io.dataset import ODOM, PLAN, REFERENCE, feed, input_routes
from cloe_ros.io.diagnostics import DIAGNOSTICS_TOPIC, OfflineReports
from cloe_ros.io.outputs import LATCHED_QOS, OutputEncoder
from cloe_ros.io.reader import BagError, BagReader
from cloe_ros.io.writer import BagWriter, WriterError
from cloe_ros.settings import default

#: Input topics copied into the output bag (under each vehicle namespace) so it stands alone.
COPIED = (ODOM, REFERENCE, PLAN, 'ground_truth', 'true_parameters')


@dataclass
class InferResult:
    """What a run did, per vehicle."""

    vehicles: list[str]
    steps: dict[str, int]
    rejected: dict[str, Counter]
    malformed: dict[str, int]
    time_jumps: dict[str, int]
    duration_s: float
    wall_s: float
    written: dict[str, int] = field(default_factory=dict)
    #: vehicles of a run that gave no estimate at all, and why (the run ends in an error when
    #: every vehicle is one of them)
    unusable: dict[str, str] = field(default_factory=dict)
    #: namespaces of the bag with an odom or reference topic but no usable pair, and why (not
    #: inferred; the others are): a ``warning:`` line each
    skipped: list[str] = field(default_factory=list)
    #: per vehicle, the first input rejected for each reason, described (what was wrong), with
    #: the log time of its message where known and how many there were, and the world frame
    #: learnt again: a ``warning:`` line each
    first_rejected: dict[str, dict[str, tuple[str, int | None, int]]] = field(
        default_factory=dict)


def check_inputs(topics: dict[str, str], path: Path) -> list[str]:
    """Vehicle namespaces with usable odom/reference pairs; a clear error otherwise."""
    return _usable(topics, path)[0]


def _usable(topics: dict[str, str], path: Path) -> tuple[list[str], list[str]]:
    """:func:`survey_inputs` of ``topics``, and a clear error when no vehicle is usable."""
    vehicles, problems = survey_inputs(topics)
    if not vehicles:
        found = ', '.join(f'{n} ({t})' for n, t in sorted(topics.items())) or 'no topics'
        detail = '; '.join(problems) if problems else f'the bag has {found}'
        msg = (
            f'{path}: no vehicle to infer: each needs <ns>/odom (nav_msgs/msg/Odometry) and '
            f'<ns>/reference (geometry_msgs/msg/PoseStamped); {detail}'
        )
        raise CliError(msg)
    return vehicles, problems


def survey_inputs(topics: dict[str, str]) -> tuple[list[str], list[str]]:
    """The vehicle namespaces of a bag's ``topics`` (name: type) with a usable odom/reference
    pair, and, in words, the namespaces with one of the two but no usable pair (one missing, or
    of another type)."""
    odoms = {n[: -len(ODOM) - 1]: t for n, t in topics.items() if n.endswith('/' + ODOM)}
    refs = {n[: -len(REFERENCE) - 1]: t for n, t in topics.items()
            if n.endswith('/' + REFERENCE)}  # fmt: skip
    problems = []
    vehicles = []
    for ns in sorted(set(odoms) | set(refs)):
        label = ns or '/'
        if ns in odoms and odoms[ns] != messages.ODOMETRY:
            problems.append(f'{ns}/{ODOM} has type {odoms[ns]}, expected {messages.ODOMETRY}')
        elif ns in refs and refs[ns] != messages.POSE_STAMPED:
            problems.append(
                f'{ns}/{REFERENCE} has type {refs[ns]}, expected {messages.POSE_STAMPED}'
            )
        elif ns not in refs:
            problems.append(f'vehicle {label} has {ns}/{ODOM} but no {ns}/{REFERENCE} topic')
        elif ns not in odoms:
            problems.append(f'vehicle {label} has {ns}/{REFERENCE} but no {ns}/{ODOM} topic')
        else:
            vehicles.append(ns)
    return vehicles, problems


def infer_bag(
    bag: Path,
    output: Path,
    settings: dict,
    vehicles: list[str] | None = None,
    copy_inputs: bool = True,
    compression: str = 'zstd',
    progress=None,
    jobs: int = 1,
    node: str = NODE_NAME,
) -> InferResult:
    """Run the engine of every vehicle over ``bag`` (of ``vehicles``: default all) and write the
    outputs to ``output``: in this process, or with the vehicles in ``jobs`` groups (0: one per
    core; never more groups than vehicles), each run in a process of its own that sends its
    outputs here, where they are written beside the copies of the inputs (:func:`_split`).
    ``node``: the node whose run this reproduces, which names the ``/diagnostics`` statuses."""
    engine_config, output_config = build_configs(settings)
    start = time.monotonic()
    with BagReader(bag) as reader:
        found, skipped = _vehicles(reader, bag, vehicles)
        if output.exists():
            raise CliError(f'{output} exists already, not overwriting.')
        count = worker_count(jobs, len(found))
        copies = _copies(reader, found) if copy_inputs else []
        encoders = {v: _encoder(v, engine_config, output_config) for v in found}
        written: Counter = Counter()
        writer = BagWriter(output, compression=compression)
        try:
            with writer:
                _add_topics(writer, reader, copies, encoders, engine_config, output_config)

                def write(topic, stamp, data):
                    writer.write(topic, stamp, data)
                    written[topic] += 1

                if count == 1:
                    engines = _engines(found, engine_config)
                    reports = _reports(node, settings, output_config)
                    stats = _run(reader, bag, engines, encoders, engine_config, write, copies,
                                 progress, reports)  # fmt: skip
                else:
                    stats = _split(reader, bag, settings, found, count, write, copies, progress,
                                   node)  # fmt: skip
                if len(stats['unusable']) == len(found):
                    raise CliError('; '.join(stats['unusable'].values()) + '.')
        except BaseException as err:
            raise _failed(err, writer, output) from err
        if progress is not None:
            progress('infer', 1.0)
        duration = (reader.end_ns - reader.start_ns) / NS
    return InferResult(vehicles=found, duration_s=duration, wall_s=time.monotonic() - start,
                       written=dict(written), skipped=[f'{bag}: {why}' for why in skipped],
                       **stats)  # fmt: skip


def _split(reader, bag, settings, found, count, write, copies, progress, node) -> dict:
    """:func:`_run` of the vehicles ``found`` in ``count`` > 1 groups, each in a forked worker
    (:func:`_run_group`) whose outputs go to ``write`` here, while this process hands it the
    messages of the topics ``copies``; the statistics of all the groups, in ``found``'s order."""
    groups = [found[len(found) * i // count : len(found) * (i + 1) // count]
              for i in range(count)]  # fmt: skip
    # forked workers inherit the engine's modules, loaded kernels and the settings checked
    ctx = multiprocessing.get_context('fork')
    queue = ctx.Queue(maxsize=4 * count)
    workers = [ctx.Process(target=_run_group, args=(bag, settings, group, queue, i, node),
                           daemon=True)
               for i, group in enumerate(groups)]  # fmt: skip
    done: dict[int, dict] = {}
    fractions = [0.0] * count

    def take(wait: bool) -> None:
        """What the workers sent, written; until they are all done if ``wait``."""
        while len(done) < count:
            try:
                index, kind, payload = (queue.get(timeout=0.5) if wait
                                        else queue.get_nowait())  # fmt: skip
            except Empty:
                if not wait:
                    return
                for i, w in enumerate(workers):
                    if i not in done and w.exitcode is not None:
                        names = ', '.join(v or '/' for v in groups[i])
                        raise CliError(f'{bag}: the process inferring {names} ended '
                                       f'(exit status {w.exitcode})') from None
                continue
            if kind == 'out':
                for topic, stamp, data in payload:
                    write(topic, stamp, data)
            elif kind == 'progress':
                fractions[index] = payload
                if progress is not None:
                    progress('infer', min(fractions))
            elif kind == 'done':
                done[index] = payload
            else:
                raise CliError(payload)

    try:
        for w in workers:
            w.start()
        for n, (topic, log_ns, raw) in enumerate(reader.messages(copies)):
            write(topic, log_ns, raw)
            if n % 200 == 0:
                take(wait=False)
        take(wait=True)
    except BaseException:
        with uninterrupted():
            for w in workers:
                if w.is_alive():
                    w.kill()
        raise
    finally:
        with uninterrupted():
            for w in workers:
                if w.pid is not None:
                    w.join()
            queue.close()
    # (the groups are consecutive slices of found: in their order, its order)
    return {key: {v: x for i in range(count) for v, x in done[i][key].items()}
            for key in done[0]}  # fmt: skip


def _run_group(bag: Path, settings: dict, group: list[str], queue, index: int,
               node: str) -> None:  # fmt: skip
    """A worker of :func:`_split`: the engines of ``group`` over ``bag``; puts on
    ``queue`` ``(index, kind, payload)``: ``'out'`` and a list of ``(topic, stamp, cdr)``,
    ``'progress'`` and a fraction, then ``'done'`` and the run's statistics, or ``'error'`` and
    why."""
    try:
        engine_config, output_config = build_configs(settings)
        engines = _engines(group, engine_config)
        encoders = {v: _encoder(v, engine_config, output_config) for v in group}
        out: list = []

        def write(topic, stamp, data):
            out.append((topic, stamp, bytes(data)))
            if len(out) >= 1000:
                queue.put((index, 'out', list(out)))
                out.clear()

        def progress(_label, fraction):
            queue.put((index, 'progress', fraction))

        reports = _reports(node, settings, output_config)
        with BagReader(bag) as reader:
            stats = _run(reader, bag, engines, encoders, engine_config, write, [], progress,
                         reports)  # fmt: skip
        queue.put((index, 'out', out))
        queue.put((index, 'done', stats))
    except (CloeError, BagError) as err:
        queue.put((index, 'error', str(err)))
    except BaseException as err:  # (whatever it is, the parent says it and removes the output)
        queue.put((index, 'error', f'{bag}: {type(err).__name__}: {err}'))


def _reports(node: str, settings: dict, output_config) -> OfflineReports:
    """The ``/diagnostics`` of a run reproducing the node ``node`` with ``settings``."""
    period = settings.get('diagnostics_period', default('diagnostics_period'))
    return OfflineReports(node.rsplit('/', 1)[-1], period, output_config.output_ns)


def _encoder(vehicle: str, engine_config, output_config) -> OutputEncoder:
    # bag topics are absolute: the un-namespaced vehicle's outputs go to /<output_ns>/...
    return OutputEncoder(output_config, vehicle or '/', engine_config.prediction.enabled)


def _engines(found: list[str], engine_config) -> dict[str, VehicleEngine]:
    """The engines of the vehicles ``found``, as one fleet (their estimators step together; the
    same estimates as each alone)."""
    fleet = Fleet()
    return {v: fleet.add(VehicleEngine(engine_config, name=v)) for v in found}


def _copies(reader: BagReader, found: list[str]) -> list[str]:
    """The input topics of the vehicles ``found`` copied into the output."""
    return [f'{v}/{name}' for v in found for name in COPIED if f'{v}/{name}' in reader.topics]


def _add_topics(writer, reader, copies, encoders, engine_config, output_config) -> None:
    """The output's custom data (what produced it: `cloe report` labels the outputs with it),
    its copies of the inputs and every output topic of the vehicles' ``encoders``."""
    key = f'cloe_ros.{output_config.output_ns.strip("/")}'
    writer.set_custom_data(f'{key}.algorithm', engine_config.estimator.algorithm)
    writer.set_custom_data(f'{key}.rate_hz', f'{engine_config.rate:g}')
    writer.set_custom_data(f'{key}.prediction_phase', engine_config.prediction.phase)
    for topic in copies:
        writer.add_topic(topic, reader.topics[topic].msgtype, reader.topics[topic].offered_qos)
    for enc in encoders.values():
        for topic, msgtype in enc.topics.items():
            writer.add_topic(topic, msgtype, [LATCHED_QOS] if topic in enc.latched_topics else ())
    writer.add_topic(DIAGNOSTICS_TOPIC, messages.DIAGNOSTIC_ARRAY)


def _run(reader, bag, engines, encoders, engine_config, write, copies, progress,
         reports: OfflineReports) -> dict:  # fmt: skip
    """The ``engines`` over the open ``reader``, in recording order and in batches (a grid step
    of recording time each: :class:`RecordingBatches`); every output, the ``/diagnostics`` of
    ``reports``, and every message of the topics ``copies``, handed to ``write(topic, stamp,
    cdr)``. Returns the run's statistics per vehicle (:class:`InferResult`'s steps, rejected,
    malformed, time_jumps, unusable, first_rejected)."""
    found = list(engines)
    topics = {name: info.msgtype for name, info in reader.topics.items()}
    route = input_routes(topics, found)
    batches = RecordingBatches(next(iter(engines.values())).fleet, engine_config.step_ns)
    malformed = {v: 0 for v in found}
    last_input = {v: reader.start_ns for v in found}
    received: Counter = Counter()
    span = max(reader.end_ns - reader.start_ns, 1)
    copied = set(copies)

    def emit(vehicle, estimates):
        engine, enc = engines[vehicle], encoders[vehicle]
        for est in estimates:
            for topic, stamp, data in enc.encode(est, engine.world_frame or '',
                                                 engine.child_frame):  # fmt: skip
                write(topic, stamp, data)
        for report in reports.reports(vehicle, vehicle or '/', engine, estimates,
                                      malformed[vehicle]):  # fmt: skip
            write(*report)

    def emit_all(estimates):
        for v, of_vehicle in estimates.items():
            emit(v, of_vehicle)

    count = 0
    for topic, log_ns, raw in reader.messages(set(route) | copied):
        if topic in copied:
            write(topic, log_ns, raw)
        target = route.get(topic)
        if target is None:
            continue
        received[topic] += 1
        vehicle, kind = target
        emit_all(batches.before(log_ns))
        last_input[vehicle] = log_ns
        try:
            feed(engines[vehicle], kind, raw)
        except messages.MessageError as err:
            malformed[vehicle] += 1
            reports.rejected(vehicle, f'malformed {kind}: {err}', log_ns)
            continue
        for r in engines[vehicle].take_rejections():
            # (a held input found an outlier by this one: its own message's time is not known)
            reports.rejected(vehicle, r.describe(), None if r.later else log_ns)
        batches.fed(vehicle, log_ns)
        count += 1
        if progress is not None and count % 500 == 0:
            progress('infer', (log_ns - reader.start_ns) / span)
    emit_all(batches.flush())
    for v in found:
        emit(v, engines[v].finish())
        for r in engines[v].take_rejections():
            reports.rejected(v, r.describe())
        write(*reports.final(v, v or '/', engines[v], last_input[v], malformed[v]))
    unusable = {v: _unusable(bag, v, engines[v], malformed[v], received)
                for v in found if engines[v].stats.steps == 0}  # fmt: skip
    return {
        'steps': {v: e.stats.steps for v, e in engines.items()},
        'rejected': {v: e.stats.rejected for v, e in engines.items()},
        'malformed': malformed,
        'time_jumps': {v: e.stats.time_jumps for v, e in engines.items()},
        'unusable': unusable,
        'first_rejected': {v: reports.first_rejected.get(v, {}) for v in found},
    }


def _failed(err: BaseException, writer: BagWriter, output: Path) -> BaseException:
    """After ``err`` while writing ``output``: the output removed (an output cut short looks
    complete to the next tool), and the error to raise, saying so."""
    with uninterrupted():  # (a second Ctrl-C would leave it half removed)
        writer.discard()
    if isinstance(err, WriterError) and err.path == output:  # the output's own failure
        reason = err.reason or writer.error or err
        return CliError(f'cannot write {output}: {reason}. No output written ({output} removed).')
    if isinstance(err, CloeError):
        return type(err)(f'{err} No output written ({output} removed).')
    return err


def _vehicles(reader: BagReader, bag: Path, vehicles: list[str] | None):
    """The vehicles of the open ``reader`` to infer: ``vehicles`` (default: every one found),
    each with messages on its odom and reference; a clear error otherwise. Also, without
    ``vehicles`` (every namespace was meant), the namespaces that cannot be inferred, in words
    (:func:`survey_inputs`)."""
    topics = {name: info.msgtype for name, info in reader.topics.items()}
    found, problems = _usable(topics, bag)
    skipped = [] if vehicles else problems
    if vehicles:
        wanted = [v.rstrip('/') for v in vehicles]
        twice = sorted({v or '/' for v in wanted if wanted.count(v) > 1})
        if twice:  # (each vehicle's outputs are written once: refused, as the node does)
            raise CliError(f'--vehicles names {", ".join(twice)} more than once')
        missing = [v for v in wanted if v not in found]
        if missing:
            raise CliError(
                f'{bag}: no odom/reference for {", ".join(missing)}; found: '
                + ', '.join(v or '/' for v in found)
            )
        found = wanted
    if reader.message_count == 0:
        raise CliError(f'{bag}: the bag holds no messages')
    empty = [f'{v}/{name}' for v in found for name in (ODOM, REFERENCE)
             if reader.topics[f'{v}/{name}'].count == 0]  # fmt: skip
    if empty:
        others = [v or '/' for v in found if not any(e.rsplit('/', 1)[0] == v for e in empty)]
        raise CliError(
            f'{bag}: no messages on {", ".join(empty)}: nothing to infer'
            + (f' (select the other vehicles with --vehicles {" ".join(others)})'
               if others else '')
        )  # fmt: skip
    return found, skipped


def _unusable(bag: Path, vehicle: str, engine: VehicleEngine, malformed: int, received) -> str:
    """Why ``vehicle`` gave no estimate: its inputs, how many came and what was rejected."""
    odom, ref = f'{vehicle}/{ODOM}', f'{vehicle}/{REFERENCE}'
    why = dict(engine.stats.rejected)
    if malformed:
        why['malformed'] = malformed
    detail = ', '.join(f'{k}: {n}' for k, n in sorted(why.items())) or 'none rejected'
    return (
        f'{bag}: no usable input for vehicle {vehicle or "/"}: {received[odom]} message(s) on '
        f'{odom} and {received[ref]} on {ref} gave 0 estimator steps (rejected: {detail})'
    )


def _print(result: InferResult, output: Path) -> None:
    """What ``cloe infer`` prints of a run: per vehicle, what was written, and a warning per
    vehicle and reason of the first input rejected (when, and what was wrong: as the node logs
    it), per world frame learnt again, per vehicle that gave no estimate and per namespace not
    inferred (no usable odom/reference pair)."""
    for v in result.vehicles:
        rejected = sum(result.rejected[v].values()) + result.malformed[v]
        detail = ', '.join(f'{k}: {n}' for k, n in sorted(result.rejected[v].items()))
        if result.malformed[v]:
            detail = ', '.join(filter(None, [detail, f'malformed: {result.malformed[v]}']))
        print(
            f'{v or "/"}: {result.steps[v]} steps, {rejected} input(s) rejected'
            + (f' ({detail})' if detail else '')
            + (f', {result.time_jumps[v]} time jump(s)' if result.time_jumps[v] else '')
        )
    per_second = result.wall_s / max(result.duration_s, 1e-9)
    print(
        f'wrote {output}: {sum(result.written.values())} messages; '
        f'{result.duration_s:.1f} s of recording (first to last message of the bag) in '
        f'{result.wall_s:.2f} s ({1000 * per_second:.1f} ms per second of recording)'
    )
    for v in result.vehicles:
        for reason, (first, log_ns, count) in result.first_rejected.get(v, {}).items():
            if reason in result.rejected[v] or reason.startswith('malformed'):
                text = f'rejected input ({first})'
            else:
                text = first  # (not a rejection: the world frame learnt again)
            if log_ns is not None:
                text += f', the message logged at {log_ns / NS:.3f} s'
            if count > 1:
                text += f'; {count - 1} more for that reason'
            print(f'warning: {v or "/"}: {text}', file=sys.stderr)
    for why in result.unusable.values():
        print(f'warning: {why}', file=sys.stderr)
    for why in result.skipped:
        print(f'warning: {why}: not inferred', file=sys.stderr)


def run(args: argparse.Namespace) -> int:
    worker_count(args.jobs, len(args.bag))  # a bad --jobs is an error before any work
    # (a bad setting is one error, before any bag is read)
    settings = command_settings(args.config, args.node, algorithm=args.algorithm, rate=args.rate)
    if len(args.bag) > 1:
        return _run_many(args, settings)
    bar = ProgressBar(enabled=not args.quiet)
    try:
        result = infer_bag(
            args.bag[0], args.output, settings, args.vehicles, not args.no_inputs,
            args.compression, bar, args.jobs, args.node,
        )  # fmt: skip
    except BagError as err:
        raise CliError(str(err)) from err
    except KeyboardInterrupt:  # (the output is removed unless it was complete)
        done = 'complete' if args.output.exists() else 'not written'
        print(f'output {done}: {args.output}', file=sys.stderr)
        raise
    finally:
        bar.close()
    _print(result, args.output)
    return 0


#: Set (in a worker of ``cloe infer BAG...``) when the run is interrupted: no bag is started
#: after it, and the bag in progress stops and is removed.
_stop = None


def _worker_start(stop) -> None:
    """A worker of ``cloe infer BAG...``: the parent sets ``stop`` when it is interrupted."""
    global _stop
    _stop = stop


def _stop_when_asked(_stage: str, fraction: float) -> None:
    """:func:`infer_bag`'s progress callback in a worker: stops the run (its output is then
    removed) once the parent has been interrupted, unless the output is complete (fraction 1)."""
    if fraction < 1.0 and _stop is not None and _stop.is_set():
        raise KeyboardInterrupt


def _infer_one(job: tuple) -> tuple[InferResult | None, str]:
    """One bag of ``cloe infer BAG...``, in a worker process: (result, ''), (None, why), or
    (None, '') when the run was interrupted before or while this bag was inferred (its output is
    not written)."""
    bag, output, settings, vehicles, copy_inputs, compression, node = job
    if _stop is not None and _stop.is_set():
        return None, ''
    try:
        return infer_bag(bag, output, settings, vehicles, copy_inputs, compression,
                         _stop_when_asked, node=node), ''  # fmt: skip
    except (CloeError, BagError) as err:
        return None, str(err)
    except KeyboardInterrupt:
        return None, ''


def _run_many(args: argparse.Namespace, settings: dict) -> int:
    """Every bag into ``args.output/<its name>`` (a single ``.mcap`` file's name without the
    suffix), ``--jobs`` at once."""
    names = [_output_name(b) for b in args.bag]
    twice = sorted(n for n, count in Counter(names).items() if count > 1)
    if twice:
        raise CliError(
            f'several input bags are named {", ".join(twice)}: their outputs would share '
            f'{args.output}/<name>; infer them into separate folders'
        )
    out = args.output
    check_folder(out, False, None)
    created = not out.exists()
    make_folder(out)
    jobs = worker_count(args.jobs, len(args.bag))
    work = [(bag, out / name, settings, args.vehicles, not args.no_inputs, args.compression,
             args.node)
            for bag, name in zip(args.bag, names)]  # fmt: skip
    failed = []
    stop = multiprocessing.get_context().Event()
    futures: list = []
    try:
        with pool(_infer_one, work, jobs, _worker_start, (stop,), stop.set) as futures:
            for done, (job, future) in enumerate(zip(work, futures), start=1):
                result, why = future.result()
                if result is None:
                    failed.append(why)
                else:
                    _print(result, job[1])
                    sys.stdout.flush()
                if not args.quiet:
                    print(f'[{done}/{len(work)}] {job[0].name}', file=sys.stderr, flush=True)
    except KeyboardInterrupt:
        # (no bag started after the Ctrl-C; those in progress stopped, their outputs removed)
        with uninterrupted():
            _say_interrupted([job[1] for job in work], futures, out if created else None)
        raise
    for why in failed:
        print(f'ERROR: {why}', file=sys.stderr)
    if len(failed) == len(work):
        if created:
            shutil.rmtree(out, ignore_errors=True)  # (empty: nothing was written)
        raise CliError(f'none of the {len(work)} bags could be inferred')
    return 1 if failed else 0


def _say_interrupted(outputs: list[Path], futures: list, created: Path | None) -> None:
    """After Ctrl-C in ``cloe infer BAG...``, the work done (``futures``, those of ``outputs``
    submitted): which outputs are complete and which were not written, on stderr; the output
    folder ``created`` removed if it holds none."""
    complete = [
        out
        for out, f in zip(outputs, futures)
        if not f.cancelled() and f.exception() is None and f.result()[0] is not None
    ]
    missing = [out for out in outputs if out not in complete]
    for out in missing:  # (a worker removes its own; this one of the run's was not finished)
        shutil.rmtree(out, ignore_errors=True)
    print(f'outputs complete: {", ".join(map(str, complete)) or "none"}', file=sys.stderr)
    if missing:
        print(f'outputs not written: {", ".join(map(str, missing))}', file=sys.stderr)
    if created is not None and not complete:
        shutil.rmtree(created, ignore_errors=True)


def _output_name(bag: Path) -> str:
    """The name of ``bag``'s output among many: the bag's folder name, or a single ``.mcap``
    file's name without its suffix."""
    name = bag.resolve().name
    return name[: -len('.mcap')] if bag.is_file() and name.endswith('.mcap') else name
