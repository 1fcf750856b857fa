"""The settings table (cloe_ros/settings.py) is the one source: the README's table, the shipped
config/inference.yaml and the core's configuration dataclasses all agree with it."""

from __future__ import annotations

import sys
from pathlib import Path

import yaml

from cloe_ros.core.anticipation import AnticipationConfig
from cloe_ros.core.engine import EngineConfig
from cloe_ros.core.estimator import EstimatorConfig
from cloe_ros.core.identifier import IdentifierConfig
from cloe_ros.core.prediction import PredictionConfig
from cloe_ros.io.config import build_configs
from cloe_ros.io.outputs import OutputConfig
from cloe_ros.settings import SETTINGS, engine_settings

REPO = Path(__file__).resolve().parent.parent
sys.path.insert(0, str(REPO / 'scripts'))

import make_settings_docs  # noqa: E402


def test_the_readme_table_is_the_one_the_table_writes():
    text = (REPO / 'README.md').read_text()
    assert make_settings_docs.readme_text(text) == text, (
        'README.md is out of date: run python scripts/make_settings_docs.py'
    )
    block = make_settings_docs.readme_block()
    for s in SETTINGS.values():
        assert f'| `{s.name}` | `{make_settings_docs.shown_default(s)}` |' in block


def test_the_shipped_config_holds_every_default():
    path = REPO / 'config' / 'inference.yaml'
    assert path.read_text() == make_settings_docs.config_text(), (
        'config/inference.yaml is out of date: run python scripts/make_settings_docs.py'
    )
    values = yaml.safe_load(path.read_text())['cloe_inference']['ros__parameters']
    expected = {
        s.name: list(s.default) if isinstance(s.default, tuple) else s.default
        for s in SETTINGS.values()
        if s.default != []  # an empty list cannot be written in an rcl parameter file
    }
    assert values == expected
    assert build_configs(values) == build_configs({})


def test_the_dataclasses_default_to_the_table():
    """Every field a setting fills defaults to the setting's default, in every dataclass."""
    defaults = {
        'engine': EngineConfig(),
        'estimator': EstimatorConfig(),
        'identifier': IdentifierConfig(),
        'prediction': PredictionConfig(),
        'anticipation': AnticipationConfig(),
        'output': OutputConfig(),
    }
    for s in engine_settings():
        value = getattr(defaults[s.group], s.field)
        assert value == s.default, (s.name, value, s.default)
    assert build_configs({}) == (EngineConfig(), OutputConfig())


def test_the_dataclasses_check_with_the_table():
    """A dataclass refuses what the table refuses, naming the setting (EngineConfig used to take
    rates up to 10000 Hz while the node stopped at 2000)."""
    import pytest

    from cloe_ros.errors import ConfigError

    for cls, field, name in [
        (EngineConfig, 'rate', 'rate'),
        (IdentifierConfig, 'bandwidth', 'id_bandwidth'),
        (PredictionConfig, 'rate', 'prediction_rate'),
        (AnticipationConfig, 'coverage', 'prediction_coverage'),
        (EstimatorConfig, 'gamma_l', 'gamma_l'),
    ]:
        low, high = SETTINGS[name].range
        cls(**{field: high})
        with pytest.raises(ConfigError) as info:
            cls(**{field: high * 1.5 + 1})
        assert info.value.name == name
        assert str(info.value).startswith(f'{name} must be within [{low:g}, {high:g}]')
