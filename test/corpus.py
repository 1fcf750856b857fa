"""Where the tests find the corpus of real flights (NanoBench flights converted with
``cloe bag nanobench``): the folder ``CLOE_FLIGHTS`` names, else ``shared/data/flights`` beside
the checkout, where the project keeps it. Tests that need it skip when it is not there."""

from __future__ import annotations

import os
from pathlib import Path

REPO = Path(__file__).resolve().parents[1]
FLIGHTS = Path(os.environ.get('CLOE_FLIGHTS', REPO.parent / 'shared' / 'data' / 'flights'))
B2 = FLIGHTS / 'nanobench_B2_circle_medium_rep1'
B3 = FLIGHTS / 'nanobench_B3_figure8_medium_rep1'
