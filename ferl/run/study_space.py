"""The search space of a study (docs/sweeps.md, "The study database"): Hydra's sweep syntax read as
Optuna distributions, so that a search is written the way every other ferl sweep is written.

    actor.lr.value=tag(log, interval(0.005, 0.5))   a float, sampled on a log scale
    actor.beta.end=interval(2.0, 20.0)               a float
    actor.n_hidden=tag(int, interval(10, 100))       an integer (Hydra reads interval's bounds as floats)
    actor.n_hidden=range(10, 101, 10)                an integer with a step; the stop excluded, as in Hydra
    actor.head=choice(linear, free_energy)           one of the values
    n_runs=2                                         not searched: passed to every trial as it is

Keys come from ``hydra.sweeper.params`` first, then from the command line; a key given twice keeps
its last value, so the command line can narrow the search or fix one of its keys.
"""

import json
from dataclasses import dataclass
from typing import Any

from hydra.core.override_parser.overrides_parser import OverridesParser
from hydra.core.override_parser.types import ChoiceSweep, IntervalSweep, Override, RangeSweep, Transformer
from optuna.distributions import (
    BaseDistribution,
    CategoricalDistribution,
    FloatDistribution,
    IntDistribution,
    distribution_to_json,
)
from optuna.trial import Trial

from ferl.config.params import ConfigError


@dataclass(frozen=True)
class SearchSpace:
    """What each trial searches (``distributions``) and what it is given as is (``fixed``, the
    overrides as typed, in their order)."""

    distributions: dict[str, BaseDistribution]
    fixed: list[str]

    def identity(self) -> dict:
        """What makes two studies the same search: a stored study is continued only when its
        identity equals this one (a different range or fixed override would mix incomparable trials)."""
        return {
            "space": {name: json.loads(distribution_to_json(d)) for name, d in sorted(self.distributions.items())},
            "overrides": sorted(self.fixed),
        }

    def overrides(self, params: dict) -> list[str]:
        """A trial's job: the fixed overrides, then each searched key at the trial's value."""
        return [*self.fixed, *(f"{name}={as_override(value)}" for name, value in params.items())]


def search_space(params: dict[str, str], arguments: list[str]) -> SearchSpace:
    """The space of ``hydra.sweeper.params`` (key → Hydra value text) and the command line's overrides."""
    texts = [f"{key}={value}" for key, value in params.items()] + list(arguments)
    distributions: dict[str, BaseDistribution] = {}
    fixed: dict[str, str] = {}
    for override in OverridesParser.create().parse_overrides(texts):
        key = override.get_key_element()
        distributions.pop(key, None)
        fixed.pop(key, None)
        if override.is_sweep_override():
            distributions[key] = distribution(override)
        else:
            fixed[key] = override.input_line or f"{key}={override.get_value_element_as_str()}"
    return SearchSpace(distributions, list(fixed.values()))


def distribution(override: Override) -> BaseDistribution:
    """One sweep override as an Optuna distribution (the module docstring's table)."""
    value = override.value()
    if isinstance(value, IntervalSweep):
        assert value.start is not None and value.end is not None
        if "int" in value.tags:
            return IntDistribution(int(value.start), int(value.end), log="log" in value.tags)
        return FloatDistribution(value.start, value.end, log="log" in value.tags)
    values: list[Any] = list(override.sweep_iterator(transformer=Transformer.encode))
    if isinstance(value, RangeSweep) and not value.shuffle and all(type(v) is int for v in values) and values:
        step = int(value.step) if len(values) > 1 else 1
        return IntDistribution(min(values), max(values), step=abs(step))
    if isinstance(value, (ChoiceSweep, RangeSweep)) and values:
        if any(not isinstance(v, (str, int, float, bool)) for v in values):
            raise ConfigError(f"{override.input_line}: a searched choice must be a string, number or bool")
        return CategoricalDistribution(sorted(values, key=str) if value.shuffle else values)
    raise ConfigError(f"{override.input_line}: an Optuna search takes interval(), range() or choice(), not this sweep")


def as_override(value) -> str:
    """A sampled value as Hydra override text: floats in Python's round-trip form, bools and
    None as Hydra spells them, strings as choice() gave them (already escaped)."""
    if value is None:
        return "null"
    if isinstance(value, bool):
        return "true" if value else "false"
    return str(value)


def suggest(trial: Trial, name: str, dist: BaseDistribution):
    """Sample one key through Optuna's public suggest API (an enqueued retry gets its fixed value)."""
    if isinstance(dist, FloatDistribution):
        return trial.suggest_float(name, dist.low, dist.high, step=dist.step, log=dist.log)
    if isinstance(dist, IntDistribution):
        return trial.suggest_int(name, dist.low, dist.high, step=dist.step, log=dist.log)
    assert isinstance(dist, CategoricalDistribution)
    return trial.suggest_categorical(name, dist.choices)


def described(dist: dict) -> str:
    """A stored distribution (its JSON form) in the sweep syntax, for a refusal's line."""
    a, name = dist.get("attributes", {}), dist.get("name")
    if name == "CategoricalDistribution":
        return f"choice({', '.join(map(str, a.get('choices', [])))})"
    step = a.get("step")
    if name == "IntDistribution" and step not in (None, 1):
        return f"range({a['low']}, {a['high'] + step}, {step})"
    text = f"interval({a.get('low')}, {a.get('high')})"
    tags = [t for t, on in (("int", name == "IntDistribution"), ("log", a.get("log"))) if on]
    return f"tag({', '.join(tags)}, {text})" if tags else text
