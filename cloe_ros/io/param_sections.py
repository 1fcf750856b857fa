r"""Which sections of a ROS 2 parameter file a node takes, as rclpy gives them to it.

A parameter file maps node names to ``ros__parameters``::

    /**:                      # every node
      ros__parameters: {rate: 50.0}
    fleet:                    # nested: the node /fleet/cloe_shard1
      cloe_shard1:
        ros__parameters: {shard_index: 1}
    /**/cloe_shard2:          # a node named cloe_shard2, in any namespace
      ros__parameters: {shard_index: 2}

A section's name is its keys joined by ``/`` with a leading ``/`` (``cloe_inference:`` and
``/cloe_inference:`` name the same node). It is a pattern of a node's fully qualified name in
which ``/*`` stands for one name and ``/**`` for any number of them, none included: rclcpp's
rule (``parameter_map_from``, ``/*`` becoming ``(/\w+)``), which rclpy follows. A node takes
every section that matches it, in the file's order, the later one's values winning: a ``/**``
written after a node's own section overrides it. Two spellings of one name rcl stores alike
(``fleet: cloe_shard1:`` and ``fleet/cloe_shard1:``; a key written twice) are one section, at
the place of the first. (Measured with rclpy 7.1, Jazzy.)

The file is read as rcl reads it (:func:`load`), by libyaml's parser where PyYAML has it, as rcl's
(a tab between a value and its comment, for one): keys are strings as written (``on:`` is the node
``on``, ``<<`` a name); a value that is not quoted (plain, or a block scalar) is a bool (``true``,
``yes``, ``on``, ``y``, ... and their negations), else an integer (C's ``strtoll``: ``0x10`` is 16,
``010`` is 8), else a float (``strtod``: ``5e1``, ``1.0e3``, ``.inf``, ``nan``, ``nan(1)``; one out
of range stays a string), else a string; a quoted or ``!!str`` value is a string, and other tags
are ignored (``!!float 5`` is the integer 5); several documents, and a repeated key, merge into the
first; nested parameter names are dotted (``a: {b: 1}`` is ``a.b``). What rcl refuses is refused,
saying why (aliases: a :class:`yaml.YAMLError` with its line; the rest: a :class:`ParamFileError`):
a parameter or ``ros__parameters`` without a value or a parameter without a name, an array of mixed
types, a value outside ``ros__parameters`` (:func:`check_layout`), a section name that is not a
node name (``cloe-x``, ``/fleet/cloe_*``, ``1abc``, a ``//``). (Not followed: the few layouts rcl
reads in its own odd way, such as an array of mappings, or a section holding both
``ros__parameters`` and a child node.)

Every node of the package warns at start-up of a file none of whose sections it takes
(:func:`cloe_ros.ros.common.params_files_for_others`), and ``cloe infer --config FILE --node
NAME`` reads a file as the node ``NAME`` takes it (:func:`cloe_ros.io.config.load_settings`).
No rclpy here.
"""

from __future__ import annotations

import math
import re
import sys
from typing import Any, ClassVar

import yaml

PARAMETERS = 'ros__parameters'


class ParamFileError(ValueError):
    """A parameter file rcl refuses, in words. Internal: its users say it as a
    :class:`~cloe_ros.errors.ConfigError` (``cloe infer --config``) or a
    :class:`~cloe_ros.ros.errors.StartupError` (a node's ``--params-file``) naming the file."""


_TRUE = frozenset('y Y yes Yes YES true True TRUE on On ON'.split())
_FALSE = frozenset('n N no No NO false False FALSE off Off OFF'.split())
_INT = re.compile(r'[+-]?(?:0[xX][0-9a-fA-F]+|0[0-7]*|[1-9][0-9]*)')
_DECIMAL = re.compile(r'[+-]?(?:[0-9]+\.?[0-9]*|\.[0-9]+)(?:[eE][+-]?[0-9]+)?')
_HEX = re.compile(r'[+-]?0[xX](?:[0-9a-fA-F]+\.?[0-9a-fA-F]*|\.[0-9a-fA-F]+)(?:[pP][+-]?[0-9]+)?')
_WORD = re.compile(r'[+-]?(?:inf|infinity|nan(?:\([0-9A-Za-z_]*\))?)', re.IGNORECASE)
_YAML_SPECIAL = re.compile(r'[+-]?\.(?:inf|Inf|INF)|\.(?:nan|NaN|NAN)')
_PLAIN = 'tag:cloe_ros,2026:rcl-plain'
_TOKEN = re.compile(r'\*\*?|[A-Za-z_][A-Za-z0-9_]*')


def scalar(text: str) -> bool | int | float | str:
    """A plain YAML value as rcl types it (see the module docstring)."""
    if text in _TRUE:
        return True
    if text in _FALSE:
        return False
    if _INT.fullmatch(text):
        digits = text.lstrip('+-')
        base = 16 if digits[:2] in ('0x', '0X') else 8 if digits[0] == '0' else 10
        # (over 19 decimal digits is out of range, and Python refuses to parse thousands)
        if base != 10 or len(digits) <= 19:
            value = int(digits, base) * (-1 if text[0] == '-' else 1)
            if -(2**63) <= value < 2**63:  # (else strtoll's ERANGE: strtod's turn)
                return value
    if _YAML_SPECIAL.fullmatch(text):
        return float(text.replace('.', '', 1))
    if _WORD.fullmatch(text):
        return math.nan if text.lstrip('+-')[:3].lower() == 'nan' else float(text)
    hexadecimal = _HEX.fullmatch(text) is not None
    if hexadecimal or _DECIMAL.fullmatch(text):
        try:
            value = float.fromhex(text) if hexadecimal else float(text)
        except OverflowError:  # (float.fromhex beyond the largest float: strtod's ERANGE)
            return text
        mantissa = re.split('[pP]' if hexadecimal else '[eE]', text)[0]
        zero = not re.search('[1-9a-fA-F]' if hexadecimal else '[1-9]', mantissa.lstrip('+-0xX'))
        # strtod's ERANGE (rcl then keeps the text): overflow, underflow, a subnormal result
        if math.isinf(value) or (value == 0.0 and not zero) or 0 < abs(value) < sys.float_info.min:
            return text
        return value
    return text


_Base = yaml.CSafeLoader if yaml.__with_libyaml__ else yaml.SafeLoader


class _Loader(_Base):
    """PyYAML as rcl's parser reads a parameter file (see the module docstring): libyaml's
    parser where PyYAML has it, as rcl's (tabs between values, for one); tags ignored but
    ``!!str``; aliases refused."""

    # (every plain scalar gets _PLAIN: typed by scalar())
    yaml_implicit_resolvers: ClassVar[dict] = {}

    def construct_object(self, node, deep=False):
        if node in self.constructed_objects or node in self.recursive_objects:
            # (a node met twice: an alias of an anchor, *name)
            raise yaml.constructor.ConstructorError(
                None, None, 'an alias (*name): rcl does not support aliasing', node.start_mark
            )
        return super().construct_object(node, deep=deep)

    def construct_mapping(self, node, deep=False):
        if not isinstance(node, yaml.MappingNode):
            raise yaml.constructor.ConstructorError(
                None, None, f'expected a mapping, found {node.id}', node.start_mark
            )
        mapping: dict = {}
        for key_node, value_node in node.value:
            if not isinstance(key_node, yaml.ScalarNode):
                raise yaml.constructor.ConstructorError(
                    None, None, 'a key that is not a name', key_node.start_mark
                )
            key = key_node.value  # (as written: rcl's keys are strings; '<<' is one too)
            if key == PARAMETERS and key in mapping:
                raise yaml.constructor.ConstructorError(
                    None, None, 'ros__parameters twice in one section (rcl refuses it)',
                    key_node.start_mark,
                )  # fmt: skip
            value = self.construct_object(value_node, deep=True)
            if isinstance(mapping.get(key), dict) and isinstance(value, dict):
                mapping[key] = _merged(mapping[key], value)  # (a repeated key, merged as rcl)
            else:
                mapping[key] = value
        return mapping


def _typed(loader: _Loader, node: yaml.Node):
    """A node as rcl reads it whatever its tag: a scalar by :func:`scalar` unless quoted (a
    block scalar too: ``|-`` then ``5`` is 5; ``|`` keeps its newline, so stays text); an
    empty one has no value (None)."""
    if isinstance(node, yaml.SequenceNode):
        return loader.construct_sequence(node, deep=True)
    if isinstance(node, yaml.MappingNode):
        return loader.construct_mapping(node, deep=True)
    if node.style in ('"', "'"):
        return node.value
    return scalar(node.value) if node.value else None


def _text(loader: _Loader, node: yaml.Node):
    """``!!str`` and the text a quoted or block scalar resolves to: a string, but a block
    scalar is typed as rcl types it (:func:`_typed`)."""
    if isinstance(node, yaml.ScalarNode) and node.style in ('|', '>'):
        return _typed(loader, node)
    return loader.construct_scalar(node)


_Loader.add_implicit_resolver(_PLAIN, re.compile(r'.*', re.DOTALL), None)
_Loader.add_constructor(_PLAIN, _typed)
_Loader.add_constructor('tag:yaml.org,2002:str', _text)
# (!!set is then a mapping of empty values, which a parameter cannot be)
for _tag in ('null', 'bool', 'int', 'float', 'timestamp', 'binary', 'omap', 'pairs', 'set'):
    _Loader.add_constructor(f'tag:yaml.org,2002:{_tag}', _typed)
_Loader.add_constructor(None, _typed)  # (any other tag: ignored, as rcl ignores it)


def _merged(first: dict, then: dict) -> dict:
    out = dict(first)
    for key, value in then.items():
        both = isinstance(out.get(key), dict) and isinstance(value, dict)
        out[key] = _merged(out[key], value) if both else value
    return out


def load(text: str) -> Any:
    """A parameter file's text as rcl reads it (None for an empty file; several documents are
    merged, in order). Raises :class:`yaml.YAMLError` (with its line) for what is not YAML or
    what rcl refuses in it (aliases)."""
    documents = [d for d in yaml.load_all(text, Loader=_Loader) if d is not None]  # (safe)
    if not all(isinstance(d, dict) for d in documents):  # (the callers refuse it, saying what)
        return next(d for d in documents if not isinstance(d, dict))
    merged = None
    for document in documents:
        merged = document if merged is None else _merged(merged, document)
    return merged


def check_layout(mapping: dict, where: str = '') -> None:
    """rcl's layout: ``<node>: ros__parameters: {...}``, node names possibly nested under
    namespaces; a value above ``ros__parameters`` is an error (:class:`ParamFileError`, in
    words)."""
    for key, value in mapping.items():
        here = f'{where}/{key}' if where else str(key)
        if key == PARAMETERS:
            if not where:
                raise ParamFileError('ros__parameters must be under a node name (<node>: '
                                     'ros__parameters: ..., or /**: for every node)')  # fmt: skip
            if value is not None and not isinstance(value, dict):
                raise ParamFileError(f'{here} must be a mapping of parameter names to values, '
                                     f'found {brief(value)}')  # fmt: skip
        elif isinstance(value, dict):
            check_layout(value, here)
        else:
            raise ParamFileError(f'{here} is a value outside any ros__parameters (expected '
                                 f'<node>: ros__parameters: {{{key}: ...}})')  # fmt: skip


def brief(value, width: int = 40) -> str:
    """``repr(value)``, cut to ``width`` characters."""
    text = repr(value)
    return text if len(text) <= width else text[: width - 3] + '...'


def node_sections(mapping: dict) -> list[tuple[str, dict[str, Any]]]:
    """The node sections of a parameter file's ``mapping`` (from :func:`load`), in the file's
    order: ``(name, parameters)``, the name fully qualified (nested keys joined,
    ``/fleet/cloe_shard1``), the parameters' nested names dotted; two spellings rcl stores as
    one name merged at the first's place. Values above ``ros__parameters`` that are not
    mappings are skipped (:func:`check_layout` refuses them). Raises :class:`ParamFileError`
    for a section rcl refuses."""
    merged: dict[str, dict[str, Any]] = {}
    for stored, parameters in _walk(mapping, None):
        merged.setdefault(stored, {}).update(parameters)
    return [('/' + stored.lstrip('/'), parameters) for stored, parameters in merged.items()]


def _walk(mapping: dict, where: str | None):
    """``(name as rcl stores it, parameters)`` of every section under ``mapping``."""
    for key, value in mapping.items():
        if key == PARAMETERS or not isinstance(value, dict):
            continue
        if where is None:
            stored = key
        elif key.startswith('/'):
            raise ParamFileError(f'{where}: {key}: a nested name starts with "/" (rcl: a repeated '
                                 'forward slash); write it without')  # fmt: skip
        else:
            stored = f'{where.rstrip("/")}/{key}'
        if PARAMETERS in value:
            _check_name(stored)
            parameters = value[PARAMETERS]
            if parameters is None:
                raise ParamFileError(f'{stored}: ros__parameters has no value (rcl refuses it; '
                                     'write {} for none)')  # fmt: skip
            if isinstance(parameters, dict):
                yield stored, _flat(stored, parameters, '')
        yield from _walk(value, stored)


def _check_name(stored: str) -> None:
    tokens = (stored[1:] if stored.startswith('/') else stored).split('/')
    bad = [t for t in tokens if not _TOKEN.fullmatch(t)]
    if bad:
        what = 'an empty name (a "//" or a "/" at the end)' if '' in bad else f'{bad[0]!r}'
        raise ParamFileError(
            f'{stored}: not a node name rcl accepts: {what} (names: letters, digits and "_", not '
            'starting with a digit; "*" for one name and "**" for any number, each alone '
            'between "/")'
        )


def _flat(section: str, parameters: dict, prefix: str) -> dict[str, Any]:
    """The parameters with nested names dotted (``a: {b: 1}`` is ``a.b``), each checked."""
    out: dict[str, Any] = {}
    for key, value in parameters.items():
        name = f'{prefix}{key}'
        if not key:
            raise ParamFileError(f'{section}: a parameter without a name (rcl refuses it)')
        if isinstance(value, dict):
            out.update(_flat(section, value, f'{name}.'))
            continue
        if value is None:
            raise ParamFileError(f'{section}: parameter {name} has no value (rcl refuses it)')
        if isinstance(value, list):
            if any(v is None or isinstance(v, (list, dict)) for v in value):
                raise ParamFileError(f'{section}: parameter {name}: an array holding mappings, '
                                     f'arrays or empty values, {brief(value)}: not a parameter '
                                     'value')  # fmt: skip
            if len({type(v) for v in value}) > 1:
                raise ParamFileError(f'{section}: parameter {name}: an array mixing types, '
                                     f'{brief(value)} (rcl refuses it)')  # fmt: skip
        out[name] = value
    return out


def fully_qualified(node: str) -> str:
    """A node name as a fully qualified one: ``cloe_shard1`` is ``/cloe_shard1``."""
    return '/' + node.strip('/')


def applies(section: str, node: str) -> bool:
    """Whether the section named ``section`` (as :func:`node_sections` names it) applies to the
    node of fully qualified name ``node``."""
    pattern = re.escape(section)
    pattern = pattern.replace(re.escape('/**'), r'(?:/\w+)*').replace(re.escape('/*'), r'(?:/\w+)')
    return re.fullmatch(pattern, node, re.ASCII) is not None


def parameters_for(mapping: dict, node: str) -> tuple[dict[str, Any], list[str], list[str]]:
    """The parameters the node ``node`` (fully qualified) takes from a parameter file's
    ``mapping`` (from :func:`load`), the names of all its sections, and of those that apply.
    Raises :class:`ParamFileError` for a section rcl refuses."""
    values: dict[str, Any] = {}
    sections = node_sections(mapping)
    taken = []
    for name, parameters in sections:
        if applies(name, node):
            values.update(parameters)
            taken.append(name)
    return values, [name for name, _ in sections], taken
