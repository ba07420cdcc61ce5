"""What a Gymnasium id states, as ``ferl.envs.gymnasium_vector`` reads it at set-up: how it is made
(``make``: ``module:Id`` imports the module that registers it), its discrete actions
(``action_sizes``) and its own episode limit (``default_max_steps``). Each failure is one
ConfigError line naming the env key."""

import gymnasium
import numpy as np
from gymnasium import spaces

from ferl.config.params import ConfigError


def make(env_id: str, kwargs: dict):
    """``gymnasium.make`` (``module:Id`` imports the module that registers the id); a failure is
    one ConfigError line naming env.id."""
    try:
        return gymnasium.make(env_id, **kwargs)
    except gymnasium.error.Error as e:
        raise ConfigError(
            f"env.id: {env_id!r} is not a registered Gymnasium id ({str(e).splitlines()[0]}); "
            f"use a registered id or 'module:Id' with a module that registers it"
        ) from None
    except (ModuleNotFoundError, ImportError) as e:
        raise ConfigError(f"env.id: {env_id!r}: its module cannot be imported ({e})") from None
    except TypeError as e:
        raise ConfigError(f"env.kwargs: {env_id!r} does not take them ({e})") from None


def action_sizes(space, env_id: str) -> np.ndarray:
    """The sizes of the discrete action's parts: (n,) for ``Discrete(n)``, the entries of a
    ``MultiDiscrete`` (its actions are enumerated: action i is the mixed-radix digits of i)."""
    if isinstance(space, spaces.Discrete):
        return np.array([int(space.n)])
    if isinstance(space, spaces.MultiDiscrete):
        return space.nvec.reshape(-1).astype(np.int64)
    raise ConfigError(
        f"env.id: {env_id!r} has the action space {space}; ferl's agents choose among discrete "
        f"actions (Discrete or MultiDiscrete)"
    )


def default_max_steps(env) -> int | None:
    """An id's own episode limit (module docstring), or None if it states none."""
    spec_limit = env.spec.max_episode_steps if env.spec is not None else None
    inner = env.unwrapped
    for limit in (spec_limit, getattr(inner, "max_episode_length", None), getattr(inner, "max_steps", None)):
        if isinstance(limit, (int, np.integer)) and limit > 0:
            return int(limit)
    return None
