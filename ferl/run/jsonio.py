"""Strict JSON for every file ferl writes (summary.json, records/*.json, analysis, headers).

Python's ``json`` writes a non-finite float as ``NaN`` / ``Infinity``, which no JSON parser but
Python's accepts. ``strict_dumps`` maps each non-finite float (NumPy's included) to ``null`` —
summary.json's value of a run without one (docs/records.md); ``ferl.stats`` treats null and NaN alike — and dumps
with ``allow_nan=False``, so a value that escapes the mapping raises instead of being written.
"""

import json
import math

import numpy as np


def finite_or_null(value):
    """``value`` with every non-finite float in it (dicts, lists, tuples) replaced by None."""
    if isinstance(value, (float, np.floating)):
        return float(value) if math.isfinite(value) else None
    if isinstance(value, dict):
        return {key: finite_or_null(v) for key, v in value.items()}
    if isinstance(value, (list, tuple)):
        return [finite_or_null(v) for v in value]
    return value


def strict_dumps(value, **kwargs) -> str:
    """``json.dumps`` of ``value`` with non-finite floats as null and ``allow_nan=False``."""
    return json.dumps(finite_or_null(value), allow_nan=False, **kwargs)
