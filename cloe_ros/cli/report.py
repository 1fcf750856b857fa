"""``cloe report BAG [-o FOLDER]``: what a recorded flight says, as tables, figures and a page.

BAG is an input bag (``<ns>/odom`` + ``<ns>/reference``) or an output bag of ``cloe infer`` (which
also holds ``<ns>/<output_ns>/state``, ``parameters`` and, when the engine predicts,
``prediction``). An input bag is inferred first, into ``FOLDER/inferred_bag``. For every vehicle
and inference output the report gives the paper's metrics (§6.1.3; docs/method.md, "Metrics")
against the simulator's ground truth when the bag has one, else against the measurements; the
identified parameters (beside the true ones of a simulation); the prediction error at 0.5/1/2/5 s
beside the constant-velocity and hold-position baselines when predictions exist; and figures. A
bag of outputs alone (``cloe infer --no-inputs``) is refused: nothing to score them against.

FOLDER receives ``index.html`` (self-contained: CSS inline, figures embedded as base64 PNG),
``summary.md`` (the same tables, figures linked), ``report.json`` (the numbers) and the PNG files.
A report that fails leaves nothing behind: what it wrote into FOLDER is removed (FOLDER too, if it
created it). Each phase (inference, reading the bag, scoring, figures per vehicle, writing) shows
progress on stderr unless ``--quiet``.
"""

from __future__ import annotations

import argparse
import base64
import html
import json
import math
import re
import shutil
import textwrap
import time
from dataclasses import dataclass, field
from datetime import datetime, timezone
from pathlib import Path

import numpy as np

from cloe_ros.cli.analysis import Score, interpolate, score_output, state_errors
from cloe_ros.cli.errors import CliError
from cloe_ros.cli.infer import InferResult, check_inputs, infer_bag
from cloe_ros.cli.outputs import check_folder, json_safe, make_folder
from cloe_ros.cli.progress import ProgressBar
from cloe_ros.core.evaluation import HORIZONS, PredictionScore, score_positions
from cloe_ros.core.metrics import (
    rmse_norm,
    subsystem_itae,
    subsystem_rmse,
)
from cloe_ros.core.model import BLOCK_SLICES, BLOCKS, N_PARAMS, PARAMETER_NAMES, block_matrices
from cloe_ros.errors import CloeError
from cloe_ros.io import messages
from cloe_ros.io.config import DEFAULTS, command_settings
from cloe_ros.io.dataset import Predictions, Series, VehicleData, load_flight, vehicle_namespaces
from cloe_ros.io.reader import BagReader

NS = 1_000_000_000
#: A predicted pose counts for horizon h when its lead time is within this fraction of h.
HORIZON_TOLERANCE = 0.2
#: Where an input bag's inference goes, inside the report folder.
INFERRED_BAG = 'inferred_bag'
#: The report's own files (replaced under ``--force``), besides the PNG figures.
REPORT_FILES = ('index.html', 'summary.md', 'report.json')
SUBSYSTEM_NAMES = ('position', 'velocity', 'angles', 'rates')
AGAINST_TEXT = {
    'truth': 'the simulator ground truth (<ns>/ground_truth)',
    'measurement': 'the measurements (<ns>/odom; includes their noise)',
}


# -- prediction --------------------------------------------------------------------------------


def prediction_rmse(
    prediction: Predictions,
    measured: Series,
    horizons: tuple[float, ...] = HORIZONS,
    tolerance: float = HORIZON_TOLERANCE,
) -> PredictionScore:
    """Position RMSE of predicted paths against the measured position, at each horizon.

    For every path (issued at ``t_i``) and horizon ``h``: the pose whose stamp is nearest to
    ``t_i + h`` is taken if its lead time is within ``tolerance * h`` of ``h``, and compared with
    the measured position linearly interpolated at that pose's stamp. The baselines predict the
    same stamp from the measured state at ``t_i`` (interpolated): constant velocity
    ``p(t_i) + v(t_i) (t - t_i)`` (world-frame velocity) and hold position ``p(t_i)``. Paths
    whose pose or measurement is missing (outside the measured span) are left out. The scoring
    itself is :func:`~cloe_ros.core.evaluation.score_positions`, as in ``cloe evaluate``.

    Args:
        prediction: Paths of one output (see :class:`cloe_ros.io.dataset.Predictions`).
        measured: Measured states (T, 12) (``VehicleData.odom``).
        horizons: Horizons, s.
        tolerance: Accepted relative mismatch between lead time and horizon.

    """
    n_paths = len(prediction.t_ns)
    issue = prediction.t_ns.astype(np.int64)
    state0 = interpolate(measured, issue) if n_paths else np.zeros((0, 12))
    stamps = prediction.stamps_ns
    valid = stamps >= 0
    rows = np.arange(n_paths)
    predicted = np.full((n_paths, len(horizons), 3), np.nan)
    actual = np.full_like(predicted, np.nan)
    lead = np.zeros((n_paths, len(horizons)))
    for j, h in enumerate(horizons if n_paths and stamps.size else ()):
        target = issue + round(h * NS)
        gap = np.where(valid, np.abs(stamps - target[:, None]), np.iinfo(np.int64).max)
        k = np.argmin(gap, axis=1)
        chosen = stamps[rows, k]
        lead[:, j] = (chosen - issue) / NS
        near = valid[rows, k] & (np.abs(lead[:, j] - h) <= tolerance * h)
        predicted[near, j] = prediction.positions[rows, k][near]
        actual[:, j] = interpolate(measured, chosen)[:, [0, 4, 10]]
    return score_positions(horizons, predicted, actual, state0, lead)


# -- tables ------------------------------------------------------------------------------------


@dataclass
class Table:
    """A table for stdout, Markdown and HTML; cells are text, numbers or None (shown as '-')."""

    title: str
    columns: list[str]
    rows: list[list] = field(default_factory=list)
    note: str = ''


def _cell(value) -> str:
    if value is None:
        return '-'
    if isinstance(value, (bool, np.bool_)):
        return 'yes' if value else 'no'
    if isinstance(value, (int, np.integer)):
        return str(int(value))
    if isinstance(value, (float, np.floating)):
        return '-' if not math.isfinite(value) else f'{value:.4g}'
    return str(value)


def _numeric(table: Table) -> list[bool]:
    """Per column: does it hold numbers only (right-aligned) rather than text?"""
    return [
        i > 0 and all(v is None or isinstance(v, (int, float, np.number)) for v in col)
        for i, col in enumerate(zip(*table.rows))
    ] or [False] * len(table.columns)


def text_table(table: Table) -> str:
    cells = [[_cell(v) for v in row] for row in table.rows]
    widths = [max([len(c)] + [len(r[i]) for r in cells]) for i, c in enumerate(table.columns)]
    widths[0] = max(widths[0], 10)

    def line(values):
        first = f'  {values[0]:<{widths[0]}}'
        return first + ''.join(f'  {v:>{w}}' for v, w in zip(values[1:], widths[1:]))

    out = [table.title, line(table.columns), '  ' + '-' * (sum(widths) + 2 * len(widths) - 2)]
    out += [line(r) for r in cells]
    if table.note:
        out += textwrap.wrap(f'({table.note})', 97, initial_indent='  ', subsequent_indent='   ')
    return '\n'.join(out)


def markdown_table(table: Table) -> str:
    def esc(text: str) -> str:
        return text.replace('|', '\\|')

    out = [f'**{esc(table.title)}**', '']
    out.append('| ' + ' | '.join(esc(c) for c in table.columns) + ' |')
    out.append('|' + '|'.join('---:' if n else '---' for n in _numeric(table)) + '|')
    out += ['| ' + ' | '.join(esc(_cell(v)) for v in row) + ' |' for row in table.rows]
    if table.note:
        out += ['', f'*{esc(table.note)}*']
    return '\n'.join(out)


def html_table(table: Table) -> str:
    e = html.escape
    head = ''.join(f'<th>{e(c)}</th>' for c in table.columns)
    kinds = ['' if n else ' class="text"' for n in _numeric(table)]
    body = ''.join(
        '<tr>' + ''.join(f'<td{k}>{e(_cell(v))}</td>' for k, v in zip(kinds, row)) + '</tr>'
        for row in table.rows
    )
    note = f'<p class="note">{e(table.note)}</p>' if table.note else ''
    return (
        f'<table><caption>{e(table.title)}</caption><thead><tr>{head}</tr></thead>'
        f'<tbody>{body}</tbody></table>{note}'
    )


# -- the report's content ----------------------------------------------------------------------


@dataclass
class Figure:
    path: Path
    caption: str


@dataclass
class VehicleReport:
    label: str
    tables: list[Table]
    main: Table | None
    figures: list[Figure]
    data: dict
    #: Said instead of the tables when there is nothing to score.
    remark: str = 'no inference output for this vehicle in the bag'


def _score_errors(name: str, against: str, err: np.ndarray, t: np.ndarray) -> Score:
    """The metrics of ``err`` (T, 12) at times ``t`` (s from the first odometry)."""
    return Score(
        name=name,
        against=against,
        steps=len(err),
        rmse=float(rmse_norm(err)),
        rmse_sub={k: float(v) for k, v in subsystem_rmse(err).items()},
        itae={k: float(v) for k, v in subsystem_itae(t, err).items()},
        param_error=None,
        duration_s=float(t[-1] - t[0]) if len(t) else 0.0,
    )


def _score_dict(score: Score) -> dict:
    return {
        'against': score.against,
        'steps': score.steps,
        'duration_s': score.duration_s,
        'rmse': score.rmse,
        'rmse_sub': score.rmse_sub,
        'itae': score.itae,
        'param_error': score.param_error,
    }


def _max_real_poles(theta: np.ndarray) -> dict[str, float]:
    """Largest real part of each block's closed-loop poles (> 0: unstable model), 1/s."""
    out = {}
    for block, sl in zip(BLOCKS, BLOCK_SLICES):
        a, _ = block_matrices(theta[sl], block)
        out[block.name] = float(np.max(np.linalg.eigvals(a).real))
    return out


def _scores_table(
    vehicle: VehicleData, scores: dict[str, Score], measurement: Score | None
) -> Table:
    against = 'ground truth' if vehicle.ground_truth is not None else 'measurements'
    columns = ['metric', *scores]
    cols = dict(scores)
    noise_free = measurement is not None and measurement.rmse == 0.0
    if measurement is not None and not noise_free:
        columns.append('odom (raw measurement)')
        cols['odom (raw measurement)'] = measurement
    vals = list(cols.values())
    rows = [
        ['estimates scored', *[s.steps for s in vals]],
        [f'RMSE 12-state norm (vs {against})', *[s.rmse for s in vals]],
    ]
    rows += [[f'RMSE {sub}', *[s.rmse_sub[sub] for s in vals]] for sub in SUBSYSTEM_NAMES]
    rows += [[f'ITAE {sub}', *[s.itae[sub] for s in vals]] for sub in SUBSYSTEM_NAMES]
    if any(s.param_error for s in vals):
        for block in (*(b.name for b in BLOCKS), 'all'):
            rows.append([
                f'parameter error {block} [%]',
                *[100 * s.param_error[block] if s.param_error else None for s in vals],
            ])  # fmt: skip
    note = (
        f'errors e = {against} - estimate, at the estimate stamps; RMSE in SI units (m, m/s, '
        'rad, rad/s); ITAE = integral of t*|e_sub(t)| dt with t from the first odometry message'
    )
    if noise_free:
        note += '; the measurements equal the truth (a noise-free simulation)'
    elif measurement is not None:
        note += '; the odom column scores the noisy measurement itself against the truth'
    return Table(
        f'{vehicle.namespace or "/"}: estimation error against the {against}', columns, rows, note
    )


def _parameter_tables(
    vehicle: VehicleData,
    outputs: dict[str, np.ndarray],
    models: dict[str, np.ndarray] | None = None,
) -> list[Table]:
    """The final Θ̂ (beside the truth when known) and the poles per block of Θ̂, of the usable
    model an output predicts with where it publishes one (``models``: ``model.theta.*``), and of
    the truth."""
    models = models or {}
    truth = vehicle.true_parameters
    if truth is not None and len(truth) != N_PARAMS:
        truth = None
    columns = ['parameter', *[f'{n} Θ̂' for n in outputs]]
    if truth is not None:
        columns += ['true Θ', *[f'{n} error [%]' for n in outputs]]
    rows = []
    for j, name in enumerate(PARAMETER_NAMES):
        row = [name, *[float(theta[j]) for theta in outputs.values()]]
        if truth is not None:
            row.append(float(truth[j]))
            row += [
                100 * abs(theta[j] - truth[j]) / abs(truth[j]) if truth[j] else None
                for theta in outputs.values()
            ]
        rows.append(row)
    note = 'final values of <output>/parameters (the Θ̂ entries; the observer gains L are left out)'
    if truth is None:
        note += '; no true parameters in the bag (a real flight): Θ̂ cannot be scored directly'
    params = Table(f'{vehicle.namespace or "/"}: identified parameters Θ̂', columns, rows, note)
    pole_cols, pole_values = ['block'], []
    for n, theta in outputs.items():
        pole_cols.append(f'{n} Θ̂')
        pole_values.append(_max_real_poles(theta))
        if n in models:
            pole_cols.append(f'{n} usable model')
            pole_values.append(_max_real_poles(models[n]))
    if truth is not None:
        pole_cols.append('true')
        pole_values.append(_max_real_poles(truth))
    pole_rows = [[b.name, *[p[b.name] for p in pole_values]] for b in BLOCKS]
    note = (
        'Θ̂: the raw estimate (the final Θ̂ entries of <output>/parameters); > 0: that block of Θ̂ '
        'is unstable. cloe and cloe_sm predict with Θ̂ and withhold their predictions while a '
        'block of it is unstable; cloe_iv predicts with its usable model (model.theta.* of '
        '<output>/parameters), which it keeps stable, so an unstable block of its Θ̂ makes no '
        'prediction diverge'
    )
    if models:
        note += '; usable model: the final model.theta.* (the model the predictions used)'
    stability = Table(
        f'{vehicle.namespace or "/"}: largest real part of the closed-loop poles per block [1/s]',
        pole_cols,
        pole_rows,
        note,
    )
    return [params, stability]


def _prediction_table(vehicle: VehicleData, preds: dict[str, PredictionScore]) -> Table:
    columns = ['horizon [s]']
    for n in preds:
        columns += [f'{n} model', f'{n} const. velocity', f'{n} hold', f'{n} paths']
    rows = []
    for i, h in enumerate(HORIZONS):
        row = [f'{h:g}']
        for p in preds.values():
            row += [p.model[i], p.constant_velocity[i], p.hold_position[i], p.count[i]]
        rows.append(row)
    return Table(
        f'{vehicle.namespace or "/"}: prediction RMSE against the measured position [m]',
        columns,
        rows,
        'every path of the recording, in flight or not (cloe evaluate bag scores from 5 s on, '
        'in flight); per path, the pose nearest to issue time + horizon (within '
        f'{100 * HORIZON_TOLERANCE:g} %) against the measured position interpolated at its stamp; '
        'baselines from the measured position and velocity at the issue time',
    )


def _diagnostics(bag: Path, topics: dict[str, str]) -> dict[str, dict[str, str]]:
    """The last ``cloe_inference`` status per name from a recorded ``/diagnostics`` topic."""
    names = [t for t, m in topics.items() if m == messages.DIAGNOSTIC_ARRAY]
    if not names:
        return {}
    last: dict[str, dict[str, str]] = {}
    with BagReader(bag) as reader:
        for _, _, raw in reader.messages(names):
            try:
                _, statuses = messages.decode_diagnostics(raw)
            except messages.MessageError:
                continue
            for s in statuses:
                values = dict(s.values)
                # a vehicle's status (the node's own one, named after it, has no algorithm)
                if s.name.startswith('cloe_inference') and 'algorithm' in values:
                    key = f'{s.name} ({values.get("algorithm", "?")})'
                    last[key] = values
    return last


def _input_table(inference: InferResult | None, diagnostics: dict) -> Table | None:
    if inference is not None:
        rows = []
        for v in inference.vehicles:
            detail = ', '.join(f'{k}: {n}' for k, n in sorted(inference.rejected[v].items()))
            rows.append([
                v or '/', inference.steps[v], sum(inference.rejected[v].values()),
                inference.malformed[v], inference.time_jumps[v], detail or '-',
            ])  # fmt: skip
        return Table(
            'inputs of the inference run',
            ['vehicle', 'steps', 'rejected', 'malformed', 'time jumps', 'rejected because'],
            rows,
        )
    if diagnostics:
        keys = ('steps', 'odom_received', 'odom_accepted', 'rejected', 'malformed', 'time_jumps')
        rows = [
            [name, *[int(d[k]) if d.get(k, '').isdigit() else d.get(k) for k in keys]]
            for name, d in sorted(diagnostics.items())
        ]
        return Table(
            'inputs as the recorded /diagnostics last reported them',
            ['node: vehicle (algorithm)', *keys],
            rows,
        )
    return None


def _caption(kind: str, vehicle: VehicleData, measurement_error: bool = False) -> str:
    """The caption of a figure; ``measurement_error``: the measurements differ from the ground
    truth (a noisy simulation), so the errors figure draws their own error in grey."""
    truth = vehicle.ground_truth is not None
    against = AGAINST_TEXT['truth' if truth else 'measurement'].replace(
        '<ns>', vehicle.namespace or ''
    )
    grey = ''
    if truth:
        grey = (
            "; grey: the measurement's own error"
            if measurement_error
            else '; the measurements equal the truth (a noise-free simulation): no line of '
            'their own'
        )
    dotted = (
        'dotted: the true values'
        if vehicle.true_parameters is not None
        else 'no true values are known for this flight'
    )
    predicted = any(o.prediction is not None for o in vehicle.outputs.values())
    captions = {
        'errors': f'Estimation error norms per subsystem against {against}: thin |e(t)|, thick '
        f'its 1 s moving RMS{grey}.',
        'states': 'Position and attitude over time: reference (grey, steps), measured (black), '
        'inferred (dashed).',
        'parameters': 'Identified parameters Θ̂ per block over time (symlog axis), one colour '
        f'per parameter; {dotted}. A wide pale line in the same colour, where an output has it: '
        'the model the observer and the predictions were using (cloe_iv keeps its last stable, '
        'usable model while Θ̂ is far off).',
        'parameter_error': 'Relative parameter error per block over time against the true '
        'values; 100 % is no better than Θ̂ = 0.',
        'path': 'Top view, a zoom where the inferred path is farthest from the actual one (red '
        'circles), and the 3-D path' + ('; dotted: some predicted paths.' if predicted else '.'),
        'prediction': 'Prediction RMSE against the horizon: identified model (solid) beside the '
        'constant-velocity (dashed) and hold-position (dotted) baselines.',
    }
    return captions.get(kind, '')


def report_vehicle(vehicle: VehicleData, folder: Path, progress=None) -> VehicleReport:
    """Tables, figures and numbers of one vehicle; ``progress(stage, fraction)`` (a
    :class:`~cloe_ros.cli.progress.ProgressBar`) is told how scoring and the figures go."""
    from cloe_ros.cli.plots import flight_figures, model_columns, prediction_figure

    label = vehicle.namespace or '/'
    if not len(vehicle.odom):
        data = {'namespace': vehicle.namespace, 'odom_messages': 0, 'outputs': {}, 'figures': []}
        return VehicleReport(
            label, [], None, [], data, f'{vehicle.namespace}/odom holds no message'
        )
    has_truth = vehicle.ground_truth is not None
    against = 'truth' if has_truth else 'measurement'
    t0 = vehicle.odom.t_ns[0]
    odom_span = (vehicle.odom.t_ns[-1] - t0) / NS
    data: dict = {
        'namespace': vehicle.namespace,
        'scored_against': against,
        'odom_messages': len(vehicle.odom),
        'reference_messages': len(vehicle.reference),
        'odom_span_s': odom_span,
        'odom_rate_hz': (len(vehicle.odom) - 1) / odom_span if odom_span > 0 else None,
        'true_parameters': None
        if vehicle.true_parameters is None
        else dict(zip(PARAMETER_NAMES, map(float, vehicle.true_parameters))),
        'outputs': {},
    }
    scores: dict[str, Score] = {}
    finals: dict[str, np.ndarray] = {}
    models: dict[str, np.ndarray] = {}
    preds: dict[str, PredictionScore] = {}

    def tell(stage: str, fraction: float) -> None:
        if progress is not None:
            progress(f'{stage} {label}', fraction)

    tell('score', 0.0)
    for k, (name, out) in enumerate(sorted(vehicle.outputs.items())):
        entry: dict = {'algorithm': out.algorithm, 'score': None, 'final_parameters': None,
                       'prediction': None}  # fmt: skip
        score = score_output(vehicle, name)
        if score is not None:
            scores[out.label] = score
            entry['score'] = _score_dict(score)
        if out.parameters is not None and len(out.parameters):
            theta = out.parameters.values[-1, :N_PARAMS]
            finals[out.label] = theta
            entry['final_parameters'] = dict(zip(PARAMETER_NAMES, map(float, theta)))
            entry['parameters_time_s'] = (out.parameters.t_ns[-1] - t0) / NS
            entry['max_real_pole'] = _max_real_poles(theta)
            columns = model_columns(out)
            if columns is not None:  # cloe_iv: the usable model it predicts with
                model = out.parameters.values[-1, columns]
                models[out.label] = model
                entry['final_model_parameters'] = dict(zip(PARAMETER_NAMES, map(float, model)))
                entry['model_max_real_pole'] = _max_real_poles(model)
        if out.prediction is not None and len(out.prediction.t_ns):
            p = prediction_rmse(out.prediction, vehicle.odom)
            preds[out.label] = p
            entry['prediction'] = {
                'horizons_s': list(p.horizons),
                'model': p.model.tolist(),
                'constant_velocity': p.constant_velocity.tolist(),
                'hold_position': p.hold_position.tolist(),
                'paths': p.count.tolist(),
            }
        data['outputs'][name] = entry
        tell('score', (k + 1) / (len(vehicle.outputs) + 1))
    measurement = None
    if has_truth:
        err, t_ns = state_errors(vehicle.odom, vehicle.ground_truth)
        if len(err):
            measurement = _score_errors('odom', 'truth', err, (t_ns - t0) / NS)
            data['measurement_vs_truth'] = _score_dict(measurement)
    tables = []
    main = None
    if scores:
        main = _scores_table(vehicle, scores, measurement)
        tables.append(main)
    if preds:
        tables.append(_prediction_table(vehicle, preds))
    if finals:
        tables += _parameter_tables(vehicle, finals, models)

    tell('score', 1.0)
    tell('figures', 0.0)
    n_figures = 5 + bool(preds)  # flight_figures draws at most 5
    paths = flight_figures(  # outputs named by their label
        vehicle, folder, progress=lambda done: tell('figures', done / n_figures)
    )
    if preds:
        tag = vehicle.namespace.strip('/').replace('/', '_') or 'vehicle'
        paths.append(prediction_figure(
            HORIZONS,
            {n: {'model': p.model, 'constant velocity': p.constant_velocity,
                 'hold position': p.hold_position} for n, p in preds.items()},
            folder / f'{tag}_prediction.png',
            f'{label}: prediction RMSE against the measured position',
        ))  # fmt: skip
    tell('figures', 1.0)
    figures = []
    for path in paths:
        kind = re.sub(r'^.*?_(errors|states|parameters|parameter_error|path|prediction)\.png$',
                      r'\1', path.name)  # fmt: skip
        measured_error = measurement is not None and measurement.rmse > 0.0
        figures.append(Figure(path, _caption(kind, vehicle, measured_error)))
    data['figures'] = [f.path.name for f in figures]
    return VehicleReport(label, tables, main, figures, data)


# -- the folder --------------------------------------------------------------------------------


CSS = """
body { font-family: system-ui, -apple-system, 'Segoe UI', sans-serif; margin: 2em auto;
       max-width: 1250px; padding: 0 1em; color: #222; line-height: 1.45; }
h1 { font-size: 1.6em; margin-bottom: 0.2em; }
h2 { border-bottom: 1px solid #ccc; margin-top: 2em; }
table { border-collapse: collapse; margin: 1em 0 0.3em; font-size: 0.9em; }
caption { text-align: left; font-weight: 600; padding-bottom: 0.3em; }
th, td { border: 1px solid #ddd; padding: 0.25em 0.6em; }
th { background: #f3f3f3; } td { text-align: right; font-variant-numeric: tabular-nums; }
td.text { text-align: left; }
.note { color: #555; font-size: 0.85em; margin-top: 0; max-width: 70em; }
figure { margin: 1.5em 0; } figure img { max-width: 100%; border: 1px solid #eee; }
figcaption { color: #444; font-size: 0.9em; }
"""


def _meta_rows(meta: dict) -> list[list]:
    return [[k, v] for k, v in meta.items()]


def write_html(path: Path, title: str, meta: dict, general: list[Table], vehicles) -> None:
    e = html.escape
    parts = [
        '<!DOCTYPE html>',
        '<html lang="en"><head><meta charset="utf-8">',
        f'<title>{e(title)}</title><style>{CSS}</style></head><body>',
        f'<h1>{e(title)}</h1>',
        '<table class="meta"><tbody>'
        + ''.join(
            f'<tr><th>{e(k)}</th><td class="text">{e(_cell(v))}</td></tr>' for k, v in meta.items()
        )
        + '</tbody></table>',
    ]
    parts += [html_table(t) for t in general]
    for v in vehicles:
        parts.append(f'<h2>vehicle {e(v.label)}</h2>')
        if not v.tables:
            parts.append(f'<p>{e(v.remark[0].upper() + v.remark[1:])}.</p>')
        parts += [html_table(t) for t in v.tables]
        for f in v.figures:
            data = base64.b64encode(f.path.read_bytes()).decode('ascii')
            parts.append(
                f'<figure><img alt="{e(f.path.name)}" src="data:image/png;base64,{data}">'
                f'<figcaption>{e(f.caption)}</figcaption></figure>'
            )
    parts.append('</body></html>')
    path.write_text('\n'.join(parts), encoding='utf-8')


def write_markdown(path: Path, title: str, meta: dict, general: list[Table], vehicles) -> None:
    meta_table = Table('flight', ['item', 'value'], _meta_rows(meta))
    parts = [f'# {title}', '', markdown_table(meta_table), '']
    parts += [markdown_table(t) + '\n' for t in general]
    for v in vehicles:
        parts += [f'## vehicle {v.label}', '']
        if not v.tables:
            parts += [f'{v.remark[0].upper() + v.remark[1:]}.', '']
        parts += [markdown_table(t) + '\n' for t in v.tables]
        for f in v.figures:
            parts += [f'![{f.path.stem}]({f.path.name})', '', f'*{f.caption}*', '']
    path.write_text('\n'.join(parts), encoding='utf-8')


def _prepare_folder(folder: Path, bag: Path, force: bool) -> None:
    if folder.resolve() == bag.resolve():
        raise CliError(f'{folder} is the bag itself: choose another report folder with -o')
    check_folder(folder, force, 'the report')
    inferred = folder / INFERRED_BAG
    if inferred.exists():  # only with --force: the bag of an earlier report
        if inferred.resolve() == bag.resolve():
            raise CliError(f'{bag} is the inferred bag of this report folder: use another -o')
        if not (inferred.is_dir() and (inferred / 'metadata.yaml').exists()):
            raise CliError(f'{inferred} is in the way and is not a bag: remove it first')
        shutil.rmtree(inferred)
    for name in REPORT_FILES:
        (folder / name).unlink(missing_ok=True)
    make_folder(folder)


def output_topics(topics: dict[str, str], namespaces: list[str]) -> list[str]:
    """Topics of inference outputs (``<ns>/<output_ns>/state|parameters|prediction``)."""
    found = []
    for ns in namespaces:
        others = [o for o in namespaces if o != ns and o.startswith(ns + '/')]
        pattern = re.compile(rf'^{re.escape(ns)}/(.+)/(state|parameters|prediction)$')
        for name in topics:
            if pattern.match(name) and not any(name.startswith(o + '/') for o in others):
                found.append(name)
    return sorted(found)


def _refuse_outputs_alone(topics: dict[str, str], bag: Path) -> None:
    """A bag of inference outputs without the inputs they came from (`cloe infer --no-inputs`):
    without odometry there is nothing to score them against, so say exactly that."""
    if any(n.endswith(('/odom', '/reference')) for n in topics):
        return  # inputs, incomplete: check_inputs says what is missing
    prefixes = [n[: -len('/state')] for n, t in topics.items()
                if n.endswith('/state') and t == messages.ODOMETRY]  # fmt: skip
    found = sorted(
        f'{p}/{kind}'
        for p in prefixes
        if topics.get(f'{p}/parameters') == messages.FLOAT64_MULTI_ARRAY
        for kind in ('state', 'parameters', 'prediction')
        if f'{p}/{kind}' in topics
    )
    if found:
        raise CliError(
            f'{bag} holds only inference outputs ({", ".join(found)}), no <ns>/odom and '
            '<ns>/reference to compare them with (written by `cloe infer --no-inputs`?): report '
            'the input bag instead, or infer it again without --no-inputs'
        )


def run(args: argparse.Namespace) -> int:
    start = time.monotonic()
    bag: Path = args.bag
    folder: Path = args.output or Path(f'{bag.resolve().name or "bag"}_report')
    settings = command_settings(args.config, args.node, algorithm=args.algorithm, rate=args.rate)
    with BagReader(bag) as reader:
        topics = {name: info.msgtype for name, info in reader.topics.items()}
        counts = {name: info.count for name, info in reader.topics.items()}
        bag_start_ns, bag_duration = reader.start_ns, reader.duration_s
        message_count = reader.message_count
    namespaces = vehicle_namespaces(topics)
    if not namespaces:
        _refuse_outputs_alone(topics, bag)
        check_inputs(topics, bag)  # raises, saying what the bag lacks
        raise CliError(f'{bag}: no vehicle with <ns>/odom and <ns>/reference found')
    if message_count == 0:
        raise CliError(f'{bag}: the bag holds no messages')
    outputs = output_topics(topics, namespaces)
    if outputs and settings:
        raise CliError(
            f'{bag} already holds inference outputs ({", ".join(outputs)}): --algorithm, --rate '
            'and --config only apply to input bags; run `cloe infer` on it with the new settings '
            'first, or report on it without them'
        )
    cleanup = _Cleanup(folder)
    _prepare_folder(folder, bag, args.force)
    bar = ProgressBar(enabled=not args.quiet)
    try:
        span = (bag_start_ns, bag_duration, message_count)
        return _report(args, bag, folder, settings, topics, counts, outputs, bar, start, span)
    except BaseException:
        bar.close()
        cleanup.undo()
        raise
    finally:
        bar.close()


class _Cleanup:
    """What a failed report removes from its folder: everything it created there (the folder
    too, and the parents it made, when they did not exist), and under ``--force`` the files it
    replaces (the inferred bag, the report files, figures written since the start)."""

    def __init__(self, folder: Path) -> None:
        self.folder = folder
        self.start = time.time()
        self.before = {p.name for p in folder.iterdir()} if folder.is_dir() else set()
        created = folder
        while not created.parent.exists() and created.parent != created:
            created = created.parent
        self.created = None if folder.exists() else created

    def undo(self) -> None:
        if not self.folder.is_dir():
            return
        replaced = {INFERRED_BAG, *REPORT_FILES}
        for entry in self.folder.iterdir():
            new = entry.name not in self.before or entry.name in replaced
            if not new and entry.suffix == '.png':
                new = entry.stat().st_mtime >= self.start
            if not new:
                continue
            if entry.is_dir() and not entry.is_symlink():
                shutil.rmtree(entry, ignore_errors=True)
            else:
                entry.unlink(missing_ok=True)
        if self.created is not None:
            # the folders the report made, if nothing else was put into them meanwhile
            path = self.folder
            while True:
                try:
                    path.rmdir()
                except OSError:
                    break
                if path == self.created:
                    break
                path = path.parent


def _nothing_inferred(bag: Path, inference: InferResult, counts: dict[str, int]) -> str | None:
    """Why no vehicle of the run got a single estimate, naming the bag and topics (None if one
    did)."""
    if any(inference.steps.values()):
        return None
    parts = []
    for v in inference.vehicles:
        rejected = sum(inference.rejected[v].values())
        why = ', '.join(f'{k}: {n}' for k, n in sorted(inference.rejected[v].items()))
        parts.append(
            f'{v}/odom ({counts.get(f"{v}/odom", 0)} messages) and {v}/reference '
            f'({counts.get(f"{v}/reference", 0)}): {inference.malformed[v]} malformed, '
            f'{rejected} rejected' + (f' ({why})' if why else '')
        )
    return f'{bag}: the inference produced no estimate, nothing to report: ' + '; '.join(parts)


def _report(args, bag, folder, settings, topics, counts, outputs, bar, start, span) -> int:
    """The report's work once its folder is ready (``run`` checks everything before);
    ``span``: the bag's first log time (ns), duration (s) and message count."""
    bag_start_ns, bag_duration, message_count = span
    inference = None
    source = bag
    if not outputs:
        inferred = folder / INFERRED_BAG
        inference = infer_bag(bag, inferred, settings, progress=bar)
        reason = _nothing_inferred(bag, inference, counts)
        if reason is not None:
            raise CliError(reason)
        source = inferred
    bar('read the bag', 0.0)
    try:
        vehicles = load_flight(source)
    except CloeError as err:
        raise CliError(f'{source}: {err}') from err
    bar('read the bag', 1.0)
    diagnostics = {}
    if inference is None:
        bar('read /diagnostics', 0.0)
        diagnostics = _diagnostics(bag, topics)
        bar('read /diagnostics', 1.0)
    reports = [report_vehicle(vehicles[ns], folder, bar) for ns in sorted(vehicles)]
    for r in reports:
        if inference is not None and r.main is None and r.data.get('odom_messages'):
            r.remark = 'the inference produced no estimate (see the inputs table)'

    values = {**DEFAULTS, **settings}
    if inference is not None:
        how = (
            f'{values["algorithm"]} at {float(values["rate"]):g} Hz by `cloe report` into '
            f'{INFERRED_BAG}/ (outputs under <ns>/{values["output_ns"]}/)'
        )
    else:
        found = sorted({re.sub(r'/(state|parameters|prediction)$', '', t) for t in outputs})
        how = 'outputs found in the bag: ' + ', '.join(found)
    against = sorted({r.data['scored_against'] for r in reports if r.data.get('scored_against')})
    meta = {
        'bag': str(bag.resolve()),
        'recorded': datetime.fromtimestamp(bag_start_ns / NS, timezone.utc).strftime(
            '%Y-%m-%d %H:%M:%S UTC'
        ),
        'bag duration [s]': round(bag_duration, 3),
        'vehicles': ', '.join(r.label for r in reports),
        'inference': how,
        'errors scored against': '; '.join(AGAINST_TEXT[a].replace('<ns>/', '') for a in against)
        or 'nothing to score',
    }
    topic_table = Table(
        'topics of the bag',
        ['topic', 'type', 'messages'],
        [[t, topics[t], counts[t]] for t in sorted(topics)],
    )
    if inference is not None:
        topic_table.rows += [
            [t, 'written by the inference', n] for t, n in sorted(inference.written.items())
            if t not in topics
        ]  # fmt: skip
    general = [topic_table]
    inputs = _input_table(inference, diagnostics)
    if inputs is not None:
        general.append(inputs)

    title = f'cloe report: {bag.resolve().parent.name}/{bag.resolve().name}'
    bar('write the report', 0.0)
    write_html(folder / 'index.html', title, meta, general, reports)
    write_markdown(folder / 'summary.md', title, meta, general, reports)
    numbers = {
        'bag': str(bag.resolve()),
        'reported_bag': str(source.resolve()),
        'bag_start_ns': bag_start_ns,
        'bag_duration_s': bag_duration,
        'topics': {t: {'type': topics[t], 'messages': counts[t]} for t in sorted(topics)},
        'inference': None
        if inference is None
        else {
            'settings': {k: values[k] for k in ('algorithm', 'rate', 'output_ns')},
            'steps': inference.steps,
            'rejected': {v: dict(c) for v, c in inference.rejected.items()},
            'malformed': inference.malformed,
            'time_jumps': inference.time_jumps,
            'wall_s': inference.wall_s,
        },
        'diagnostics': diagnostics or None,
        'horizons_s': list(HORIZONS),
        'vehicles': {r.label: r.data for r in reports},
    }
    (folder / 'report.json').write_text(json.dumps(json_safe(numbers), indent=2) + '\n')
    bar('write the report', 1.0)
    bar.close()

    print(f'{bag}: {bag_duration:.1f} s, {message_count} messages; inference: {how}')
    for r in reports:
        print()
        if r.main is None:
            print(f'{r.label}: {r.remark}')
            continue
        print(text_table(r.main))
        for t in r.tables:
            if t.title.endswith('prediction RMSE against the measured position [m]'):
                print()
                print(text_table(t))
    print()
    print(f'report: {(folder / "index.html").resolve()}  ({time.monotonic() - start:.1f} s)')
    return 0
