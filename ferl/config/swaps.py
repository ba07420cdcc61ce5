"""An experiment's values under a group option the user chose in its place (docs/usage.md, "Swapping
a group after an experiment").

An experiment chooses group options (its ``defaults``) and sets values of the nodes they build. A
user who swaps one of those groups on the command line (``experiment=ch3_coding_cw trainer=online_td``)
keeps every value of the experiment that the new option's constructor takes (``trainer.steps``
here; ``actor.gamma`` of the card games holds for every actor) and loses those it does not take:
Hydra merges the experiment's values into whatever option is chosen, so without this a swap fails on
a key the user never typed (``trainer.n_sample is not allowed: no phase reads it``).

The rule, applied before the config is checked: in a group the user swapped, a key that its node's
constructor does not take is dropped unless the user typed it. Option files hold only keys their
constructor takes (tests/test_configs.py), so such a key is the experiment's — or the leftover of
an option's schedule under a schedule the experiment chose (``actor.lr.value`` of a constant rate
under ``large_action``'s exponential one). A key the user typed is never dropped: it fails the check
as it would without a swap. What still does not fit is refused in one line naming the pair
(``pair``): the environment a trainer steps (``fits``), or a key the swapped option brings along.
"""

import re

from hydra.core.hydra_config import HydraConfig
from omegaconf import DictConfig, OmegaConf, open_dict

from ferl.config.params import ArgumentError, ConfigError, plain, signature, target

GROUPS = ("env", "preprocessor", "predictor", "actor", "trainer", "data")


def hydra_node(cfg: DictConfig):
    """Hydra's own node: in the composed config (tests compose with it) or Hydra's singleton (train.py)."""
    if "hydra" in cfg:
        return cfg.hydra
    return HydraConfig.get() if HydraConfig.initialized() else None


def typed_keys(hydra) -> set[tuple]:
    """The key paths the user typed on the command line (``trainer=online`` → ``("trainer",)``)."""
    overrides = list(hydra.overrides.task) if hydra is not None else []
    keys = (o.lstrip("+~").partition("=")[0].partition("@")[0] for o in overrides)
    return {tuple(k.split(".")) for k in keys if k}


def typed_values(hydra) -> set[tuple]:
    """The key paths of values the user typed: group choices (``trainer=online``) left out."""
    return {k for k in typed_keys(hydra) if not (len(k) == 1 and k[0] in hydra.runtime.choices)}


def swapped_groups(hydra) -> list[str]:
    """The groups whose option the user chose on the command line, in GROUPS' order."""
    typed = typed_keys(hydra)
    return [g for g in GROUPS if (g,) in typed]


def chosen(group: str, fallback: str) -> str:
    """``group=option`` as the user chose it (Hydra's record of the choice), else ``fallback``
    (a component built from Python: its class); refusals name what the user chose."""
    choice = HydraConfig.get().runtime.choices.get(group) if HydraConfig.initialized() else None
    return f"{group}={choice}" if choice else fallback


def pair(hydra, groups) -> str:
    """``trainer=online does not fit experiment=ch3_floor``: the options at fault and what they were put with
    (the experiment, or the environment when there is none)."""
    choices = hydra.runtime.choices
    named = " ".join(f"{g}={choices.get(g)}" for g in groups)
    experiment = choices.get("experiment")
    base = f"experiment={experiment}" if experiment not in (None, "none") else f"env={choices.get('env')}"
    return f"{named} {'does' if len(groups) == 1 else 'do'} not fit {base}"


def drop_foreign_keys(cfg: DictConfig) -> None:
    """Drop, in every group the user swapped, the keys its constructor does not take that the user did not type."""
    hydra = hydra_node(cfg)
    if hydra is None:
        return
    typed = typed_values(hydra)
    for group in swapped_groups(hydra):
        node = cfg.get(group)
        if isinstance(node, DictConfig):
            with open_dict(node):
                prune(node, (group,), typed)


def prune(node: DictConfig, path: tuple, typed: set[tuple]) -> None:
    """One node: a component (``_target_``) keeps the keys its constructor takes; a map of components
    (``predictor``) keeps its entries that are components."""
    # typed, inside a typed node, or holding a typed key
    user = lambda p: any(t[: len(p)] == p or p[: len(t)] == t for t in typed)  # noqa: E731
    if "_target_" not in node:
        for key in list(node):
            child, where = node._get_node(key), (*path, key)  # unresolved: a ??? or ${…} is the check's to name
            if isinstance(child, DictConfig) and "_target_" not in child and not user(where):
                del node[key]  # an experiment's values for a component this option does not have
            elif isinstance(child, DictConfig):
                prune(child, where, typed)
        return
    takes = taken(node, ".".join(path))
    if takes is None:
        return  # no constructor to ask: the check names what is wrong
    for key in [k for k in node if k != "_target_"]:
        where = (*path, key)
        child = node._get_node(key)
        if key not in takes and not user(where):
            del node[key]
        elif isinstance(child, DictConfig) and "_target_" in child:
            prune(child, where, typed)


def taken(node: DictConfig, path: str) -> set[str] | None:
    """The keys a component node (at config path ``path``) takes: its constructor's, and if that takes
    ``**settings``, the settings that its sub-nodes read (``settings_read``; every key where they read
    none); None when the target cannot be imported or does not say which class it builds."""
    try:
        fn = target(node["_target_"])
        resolve = getattr(fn, "resolve", None)
        if resolve is not None:
            fn, _ = resolve({k: plain(v) for k, v in node.items() if k != "_target_"})
    except (ConfigError, ArgumentError, Exception):  # noqa: BLE001 — left to the check, which names it
        return None
    params, _, takes_any = signature(fn)
    if not takes_any:
        return set(params)
    return set(params) | settings_read(node, path) if settings_read(node, path) else set(node)


SETTING = re.compile(r"\$\{([\w.]+)\}")


def settings_read(node: DictConfig, path: str) -> set[str]:
    """The keys of the component node at config path ``path`` that its sub-nodes read by
    interpolation, ``${<path>.<key>}``: a trainer's settings (``${trainer.n_episodes}``), which a
    constructor taking ``**settings`` takes, and the names users override (``trainer.n_episodes=…``)."""

    def texts(value):
        if isinstance(value, dict):
            return [t for v in value.values() for t in texts(v)]
        if isinstance(value, list):
            return [t for v in value for t in texts(v)]
        return [value] if isinstance(value, str) else []

    container = OmegaConf.to_container(node, resolve=False)
    assert isinstance(container, dict)  # a component's node
    subtree = {k: v for k, v in container.items() if isinstance(v, (dict, list))}
    refs = {ref for text in texts(subtree) for ref in SETTING.findall(text)}
    return {ref[len(path) + 1 :] for ref in refs if ref.startswith(path + ".") and ref[len(path) + 1 :] in node}


def setting_named(error: ConfigError, cfg: DictConfig) -> ConfigError:
    """An error about a key whose value reads a setting (``trainer.phases.actor.n_episodes`` =
    ``${trainer.n_episodes}``) names the setting, the key the user sets."""
    match = re.match(r"[\w.]*", str(error))
    key = match.group(0) if match else ""
    parent, _, name = key.rpartition(".")
    try:
        node = OmegaConf.select(cfg, parent) if parent else None
        child = node._get_node(name) if isinstance(node, DictConfig) and name in node else None
        value = child._value() if child is not None else None
    except Exception:  # noqa: BLE001 — the error stands as it is
        return error
    read = SETTING.fullmatch(value) if isinstance(value, str) else None
    return ConfigError(read.group(1) + str(error)[len(key) :]) if read else error


def check_settings(cfg: DictConfig, key: str) -> None:
    """A component that takes ``**settings`` takes the keys its sub-nodes read (``settings_read``):
    one that none reads is refused (a misspelt ``trainer.n_episode``), naming what is allowed."""
    node = cfg.get(key)
    if not isinstance(node, DictConfig) or "_target_" not in node:
        return
    try:
        params, _, takes_any = signature(target(node["_target_"]))
    except ConfigError:
        return  # the check names the target
    read = settings_read(node, key)
    if not (takes_any and read):
        return
    for name in node:
        if name != "_target_" and name not in params and name not in read:
            raise ConfigError(
                f"{key}.{name!s} is not allowed: no phase reads it; {key} takes "
                f"{', '.join(sorted(read))} (its settings) and {', '.join(params)}"
            )


def continuing(env_class) -> bool:
    """A continuing task steps in chunks drawn ahead (``ContinuingEnvironment.step_with``)."""
    return callable(getattr(env_class, "step_with", None))


def check_fit(values: dict, hydra) -> None:
    """A trainer that declares the kind of task it steps (its ``environment``: episodic or
    continuing) against the environment's class: one line naming the pair, before any work."""
    env, trainer = values.get("env"), values.get("trainer")
    if not (isinstance(env, dict) and isinstance(trainer, dict) and "_target_" in env and "_target_" in trainer):
        return
    env_class = target(env["_target_"])
    wants = {"episodic": True, "continuing": False}.get(str(trainer.get("environment")))
    if wants is None or wants != continuing(env_class):
        return
    steps = "episodes" if wants else "a continuing task"
    is_ = "a continuing task" if continuing(env_class) else "episodic"
    env_name = (
        f"env={hydra.runtime.choices.get('env')} ({env_class.__name__})" if hydra is not None else env_class.__name__
    )
    reason = f"its phases train on {steps}, and {env_name} is {is_}"
    if hydra is None:
        raise ConfigError(f"trainer does not fit env: {reason}")
    at_fault = [g for g in swapped_groups(hydra) if g in ("env", "trainer")] or ["trainer"]
    raise ConfigError(f"{pair(hydra, at_fault)}: {reason}")
