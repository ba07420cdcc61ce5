"""The types and ranges of config keys, declared once: as annotations of the constructor that takes them.

A component's YAML keys are its constructor's arguments, so its signature is its schema:

    def __init__(self, n_runs: PositiveInt, corridor_length: Annotated[int, at_least(2, "T_min")] = 3, ...)

``check_arguments`` checks values against such a signature — before any work, on the composed
config (``ferl.config.validate``), with one line per error naming the full key and what is
allowed — and ``@checked`` applies the same checks when a component is built from Python. A
class checks what involves several of its keys in a ``check_config(args)`` classmethod, raising
``ArgumentError`` for the key at fault. Nothing here is keyed by a config path.
"""

import functools
import inspect
import types
import typing
from collections.abc import Callable
from dataclasses import dataclass
from typing import Annotated, Any, Literal, Protocol

from omegaconf import DictConfig, ListConfig, OmegaConf


class ConfigError(ValueError):
    """A config that cannot work; str(e) is the one line shown to the user."""


class ArgumentError(ValueError):
    """A component's argument ``key`` is not allowed; ``expected`` says what is."""

    def __init__(self, key: str, expected: str):
        super().__init__(key, expected)
        self.key, self.expected = key, expected


class ConfigTarget(Protocol):
    """The optional hooks of a ``_target_`` that the config checks read. A target is any callable —
    a class, a function (``ferl.predictors.recurrent.predictor``), a third-party one — so they are
    looked up on it (``getattr`` with a default) rather than inherited from a base class."""

    # (class, (names, …)): the class its ``**kwargs`` go to and the names it sets there itself
    # (``signature``; ``DBNPreprocessor`` → each layer's RBM); default: its base class, none
    kwargs_to: tuple

    @classmethod
    def check_config(cls, args: dict) -> None:
        """Rules across several of its keys: ArgumentError for the key at fault (default: none)."""

    @staticmethod
    def resolve(values: dict) -> tuple[Callable, dict]:
        """A factory's choice of the class it builds from one of its keys: (class, the other
        values) (``predictor.<name>.memory``); the class is checked in its place (default: itself)."""


@dataclass(frozen=True)
class Allowed:
    """A range rule of an annotation: ``test(value)`` must hold; ``text`` says what is allowed."""

    test: Callable[[Any], bool]
    text: str


def at_least(low, why: str = "") -> Allowed:
    return Allowed(lambda x: x >= low, f"≥ {low}" + (f" ({why})" if why else ""))


PositiveInt = Annotated[int, Allowed(lambda x: x >= 1, "≥ 1")]
NonNegativeInt = Annotated[int, Allowed(lambda x: x >= 0, "≥ 0")]
Positive = Annotated[float, Allowed(lambda x: x > 0, "> 0")]
NonNegative = Annotated[float, Allowed(lambda x: x >= 0, "≥ 0")]
UnitInterval = Annotated[float, Allowed(lambda x: 0 <= x <= 1, "in [0, 1]")]
Momentum = Annotated[float, Allowed(lambda x: 0 <= x < 1, "in [0, 1)")]
Share = Annotated[float, Allowed(lambda x: 0 < x <= 1, "in (0, 1] (a share of the training)")]
Discount = Annotated[float, Allowed(lambda x: 0 <= x < 1, "in [0, 1) (a discount factor)")]


def plain(value):
    """OmegaConf containers as Python ones (what the checks and the components see)."""
    return OmegaConf.to_container(value, resolve=True) if isinstance(value, (DictConfig, ListConfig)) else value


def describe(annotation) -> str:
    """What an annotation allows, in words."""
    origin, args = typing.get_origin(annotation), typing.get_args(annotation)
    if origin is Annotated:
        rules = " and ".join(rule.text for rule in args[1:] if isinstance(rule, Allowed))
        return f"{describe(args[0])} {rules}".strip()
    if origin is Literal:
        return "one of " + ", ".join(map(str, args))
    if origin in (typing.Union, types.UnionType):
        text = " or ".join(describe(a) for a in args if a is not type(None))
        return f"null or {text}" if type(None) in args else text
    if origin in (list, tuple):
        return "a list"
    if origin is dict:
        return "a map"
    return {int: "an integer", float: "a number", bool: "true or false", str: "a string"}.get(annotation, "a value")


def conforms(value, annotation) -> bool:
    """Whether a plain value fits an annotation (types, Literal values and range rules)."""
    origin, args = typing.get_origin(annotation), typing.get_args(annotation)
    if origin is Annotated:
        return conforms(value, args[0]) and all(rule.test(value) for rule in args[1:] if isinstance(rule, Allowed))
    if origin is Literal:
        return value in args
    if origin in (typing.Union, types.UnionType):
        return any(conforms(value, a) for a in args)
    if annotation is type(None):
        return value is None
    if origin in (list, tuple):
        return (
            isinstance(value, (list, tuple)) and all(conforms(v, args[0]) for v in value)
            if args
            else isinstance(value, (list, tuple))
        )
    if origin is dict:
        return isinstance(value, dict) and all(conforms(v, args[1]) for v in value.values())
    if annotation is int:
        return isinstance(value, int) and not isinstance(value, bool)
    if annotation is float:
        return isinstance(value, (int, float)) and not isinstance(value, bool)
    if annotation in (bool, str):
        return isinstance(value, annotation)
    return True  # a tensor, a generator, a schedule object: given by code, not checked here


def entry_at_fault(key: str, value, annotation) -> tuple[str, object, object]:
    """The entry of a map that breaks its annotation (``digit_classes.start_0``), else the value."""
    inner = typing.get_args(annotation)[0] if typing.get_origin(annotation) is Annotated else annotation
    if typing.get_origin(inner) is dict and isinstance(value, dict):
        entry = typing.get_args(inner)[1]
        for k, v in value.items():
            if not conforms(v, entry):
                return f"{key}.{k}", v, entry
    return key, value, annotation


@functools.cache
def signature(fn) -> tuple[dict, dict, bool]:
    """The parameters a callable takes by name (a class: its constructor's), their annotations
    (extras kept) and whether it takes any keyword. A constructor that passes ``**kwargs`` on to
    its base class takes the base class's parameters too (``DigitTMaze`` → ``TMaze``); one that
    passes them to another class names it, and the parameters it sets there itself, in the class
    attribute ``kwargs_to = (class, (names, …))`` (``DBNPreprocessor`` → each layer's RBM)."""
    init = fn.__init__ if inspect.isclass(fn) else fn
    init = getattr(init, "__wrapped__", init)
    params = {
        n: p
        for n, p in inspect.signature(init).parameters.items()
        if n != "self" and p.kind not in (p.VAR_POSITIONAL, p.VAR_KEYWORD)
    }
    hints = typing.get_type_hints(init, include_extras=True)
    takes_any = any(p.kind == p.VAR_KEYWORD for p in inspect.signature(init).parameters.values())
    base, fixed = getattr(fn, "kwargs_to", (fn.__mro__[1], ())) if inspect.isclass(fn) else (object, ())
    if takes_any and base is not object:
        base_params, base_hints, takes_any = signature(base)
        params = {**{n: p for n, p in base_params.items() if n not in fixed}, **params}
        hints = {**base_hints, **hints}
    return params, hints, takes_any


def check_arguments(fn, values: dict, prefix: str = "") -> None:
    """Raise ConfigError for the first of ``values`` that ``fn``'s signature does not take or
    whose annotation it breaks, then for the class's own cross-key rules (``check_config``).
    Keys are reported as ``prefix + key``; a value that is itself a node with a ``_target_``
    is checked against its target in turn. A callable that chooses the class it builds from one
    of its keys (``resolve(values)`` → class, the other values) is checked as that class."""
    resolve = getattr(fn, "resolve", None)
    if resolve is not None:
        try:
            fn, values = resolve(values)
        except ArgumentError as e:
            raise ConfigError(f"{prefix}{e.key}={values.get(e.key)!r} is not allowed: {e.expected}") from None
    params, hints, takes_any = signature(fn)
    for key, value in values.items():
        if key not in params and not takes_any:
            raise ConfigError(f"{prefix}{key} is not allowed: {getattr(fn, '__name__', fn)} takes {', '.join(params)}")
        if isinstance(value, dict) and "_target_" in value:
            check_node(value, f"{prefix}{key}.")
        elif components(value):  # a map of components (a trainer's phases): each against its target
            for name, part in value.items():
                check_node(part, f"{prefix}{key}.{name}.")
        elif key in hints and not conforms(value, hints[key]):
            where, value, annotation = entry_at_fault(key, value, hints[key])
            raise ConfigError(f"{prefix}{where}={value!r} is not allowed: expected {describe(annotation)}")
    rules = getattr(fn, "check_config", None)
    if rules is not None:
        args = {n: p.default for n, p in params.items() if p.default is not inspect.Parameter.empty}
        args.update({k: v for k, v in values.items() if k in params})
        try:
            rules(args)
        except ArgumentError as e:
            shown = f"={args[e.key]!r}" if e.key in args else ""
            raise ConfigError(f"{prefix}{e.key}{shown} is not allowed: {e.expected}") from None


def components(value) -> bool:
    """Whether ``value`` is a non-empty map of component nodes (each with a ``_target_``)."""
    return (
        isinstance(value, dict) and bool(value) and all(isinstance(v, dict) and "_target_" in v for v in value.values())
    )


def target(path: str):
    """The callable a ``_target_`` names (ConfigError naming the key if it cannot be imported)."""
    from hydra.utils import get_object

    try:
        return get_object(path)
    except Exception as e:  # noqa: BLE001 — any import failure is the config's fault
        raise ConfigError(f"_target_={path!r} cannot be imported: {str(e).splitlines()[0]}") from None


def check_node(node: dict, prefix: str) -> None:
    """A plain config node with a ``_target_``: its other keys against the target's signature."""
    try:
        fn = target(node["_target_"])
    except ConfigError as e:
        raise ConfigError(f"{prefix}{e}") from None
    check_arguments(fn, {k: v for k, v in node.items() if k != "_target_"}, prefix)


def checked(init):
    """Check a constructor's arguments against its annotations and ``check_config`` when called,
    as the config's validation does (ValueError naming the argument)."""
    sig = inspect.signature(init)
    extra = next((n for n, p in sig.parameters.items() if p.kind == p.VAR_KEYWORD), "")  # **kwargs, if any

    @functools.wraps(init)
    def wrapper(self, *args, **kwargs):
        bound = sig.bind(self, *args, **kwargs)
        values = {k: plain(v) for k, v in list(bound.arguments.items())[1:]}
        values.update(values.pop(extra, {}))
        # the class whose constructor this is; a subclass that inherits it is checked as itself
        # (its own check_config), one that calls it through super() already checked its values
        first = next(c for c in type(self).__mro__ if "__init__" in c.__dict__)
        owner = (
            type(self)
            if first.__dict__["__init__"] is wrapper
            else next(c for c in type(self).__mro__ if c.__dict__.get("__init__") is wrapper)
        )
        try:
            check_arguments(owner, values)
        except ConfigError as e:
            raise ValueError(str(e)) from None
        init(self, *args, **kwargs)

    return wrapper
