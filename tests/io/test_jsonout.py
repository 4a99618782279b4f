"""Strict JSON: non-finite numbers become null at any depth."""

from __future__ import annotations

import json
import math

import numpy as np

from byoc_cli.io.jsonout import finite_or_none, strict_dumps


def test_non_finite_values_become_null():
    value = {"a": math.nan, "b": [1.0, math.inf, {"c": -math.inf}], "d": (np.float32(2.5),)}
    assert finite_or_none(value) == {"a": None, "b": [1.0, None, {"c": None}], "d": [2.5]}
    text = strict_dumps({"x": np.float64("nan"), "y": "NaN", "z": 3})
    assert json.loads(text, parse_constant=lambda c: 1 / 0) == {"x": None, "y": "NaN", "z": 3}
