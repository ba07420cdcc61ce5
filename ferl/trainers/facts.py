"""Facts first: what the environment says about itself, handed to the components that need it, and
every component checked against its protocol as soon as it is built (docs/architecture.md, "How a
run is put together").

Sizes are the environment's facts, not config keys. The number of reward values that chapter 4's
reward bits encode (§4.2 fn. 1), the observation size a preprocessor takes and the episode limit
T_max that a transformer memory's context must cover are read off the built environment and
passed to every constructor that takes them, once, by the ``Job``; no YAML repeats them. A config that states one anyway must agree with the environment, or the run is
refused in one line before anything is trained or written. The observation and action sizes of
predictors and actors (``n_obs``, ``n_state``, ``n_actions``) are passed the same way by the Job.

A user's component that lacks an attribute or method of its protocol (``ferl.interfaces``) would
otherwise fail with an AttributeError somewhere in the first phase, after the run directory
exists; ``check_conforms`` names everything it lacks at once, with the recipe that lists them.
"""

from collections.abc import Callable
from dataclasses import dataclass
from typing import Any

from ferl import exploration, interfaces
from ferl.config.params import ConfigError, plain, signature, target
from ferl.conformance import missing_members


@dataclass(frozen=True)
class Fact:
    """A constructor argument (``argument``) that the environment decides: its ``value`` (None:
    the environment does not say, the constructor's default stands) and the fact in words, for
    the line that refuses a config disagreeing with it."""

    argument: str
    value: Callable[[Any], int | None]  # of the environment
    words: Callable[[Any], str]


def _reward_values(env) -> tuple:
    """The reward values an episodic environment declares; a continuing one declares none."""
    return tuple(env.reward_values) if isinstance(env, interfaces.EpisodicEnvironment) else ()


FACTS = (
    # one reward bit per reward value (§4.2 fn. 1); an environment without a few known reward
    # values (a third-party one: reward_values = ()) gives none, and its predictors take the scalar
    Fact(
        "n_reward",
        lambda env: len(_reward_values(env)) or None,
        lambda env: f"has {len(_reward_values(env))} reward values {_reward_values(env)}",
    ),
    Fact(
        "n_visible", lambda env: env.observation_size, lambda env: f"has observations of {env.observation_size} values"
    ),
    # T_max, the longest episode: what a memory of bounded context must see whole (a transformer's)
    Fact(
        "max_steps",
        lambda env: env.max_steps if isinstance(env, interfaces.EpisodicEnvironment) else None,
        lambda env: f"has episodes of at most {env.max_steps} steps",
    ),
)

# what each protocol is called in an error line, where its members are listed, and the base class
# that gives its hooks' defaults
NEEDS: dict[type, tuple[str, str, type]] = {
    interfaces.EpisodicEnvironment: (
        "an episodic environment",
        'docs/architecture.md, "Add an environment"',
        interfaces.EpisodicEnvironmentBase,
    ),
    interfaces.ContinuingEnvironment: (
        "a continuing environment",
        'docs/architecture.md, "Add an environment"',
        interfaces.EnvironmentBase,
    ),
    interfaces.Environment: (
        "an environment",
        'docs/architecture.md, "Add an environment"',
        interfaces.EnvironmentBase,
    ),
    interfaces.Preprocessor: ("a preprocessor", "ferl/interfaces.py, Preprocessor", interfaces.PreprocessorBase),
    interfaces.Predictor: (
        "a predictor",
        'docs/architecture.md, "Add a predictor (a memory)"',
        interfaces.PredictorBase,
    ),
    interfaces.Actor: ("an actor", 'docs/architecture.md, "Add an actor"', interfaces.ActorBase),
    exploration.Exploration: ("an exploration method", "ferl/exploration/__init__.py", exploration.ExplorationBase),
}


def class_name(part) -> str:
    """``module.Class`` of a built component, as a user's ``_target_`` would name it."""
    return f"{type(part).__module__}.{type(part).__qualname__}"


def constructor_arguments(node) -> set[str]:
    """The arguments the constructor a config node names takes by name (a factory that chooses
    its class from a key, ``predictor.<name>.memory``, the chosen class's)."""
    fn = target(node["_target_"])
    resolve = getattr(fn, "resolve", None)
    if resolve is not None:
        fn, _ = resolve({k: plain(v) for k, v in node.items() if k != "_target_"})
    return set(signature(fn)[0])


def facts_for(node, key: str, env) -> dict:
    """The environment's facts that the constructor of ``node`` (config key ``key``) takes, as
    keyword arguments for ``instantiate``; ConfigError when the node states one that disagrees."""
    takes, given = constructor_arguments(node), {}
    for fact in FACTS:
        value = fact.value(env) if fact.argument in takes else None
        if value is None:
            continue
        stated = node.get(fact.argument)
        if stated is not None and stated != value:
            raise ConfigError(
                f"{key}.{fact.argument}={stated} disagrees with the environment: env={class_name(env)} "
                f"{fact.words(env)}; leave it out"
            )
        given[fact.argument] = value
    return given


def check_conforms(part, protocol: type, key: str) -> None:
    """ConfigError naming everything ``part`` (config key ``key``) lacks of ``protocol``, and where
    the members are listed; nothing when it conforms."""
    missing = missing_members(part, protocol)
    if missing:
        what, where, base = NEEDS[protocol]
        hooks = [name for name in missing if name in dir(base)]
        defaults = f"; {base.__module__}.{base.__name__} gives the defaults of {', '.join(hooks)}" if hooks else ""
        raise ConfigError(
            f"{key}: {class_name(part)} lacks {', '.join(missing)} ({what} needs them: {where}{defaults})"
        )
