"""Config checks run before any work (CONTRACT §6): one line naming the key and what is allowed.

Rules are data: (key, test, what is allowed). A rule applies when its key is in the
composed config, so each task's groups bring only their own keys; a ``*`` in a key stands for
every entry of a mapping (``predictor.*.lr``: the learning rate of each named predictor).
"""
from numbers import Integral, Real

import torch
from omegaconf import DictConfig, ListConfig, OmegaConf
from omegaconf.errors import MissingMandatoryValue

from ferl.actor import ACTION_CODES, ACTION_SELECTIONS, LR_NORMS, TD_RULES
from ferl.data import DataError
from ferl.envs.digit_floor import REWARD_CONDITIONS
from ferl.preprocessor import RULES as PREPROCESSOR_RULES


class ConfigError(ValueError):
    """A config that cannot work; str(e) is the one line shown to the user."""


def _int(x):
    return isinstance(x, Integral) and not isinstance(x, bool)


def _num(x):
    return isinstance(x, Real) and not isinstance(x, bool)


def positive_int(x):
    return _int(x) and x > 0


def non_negative_int(x):
    return _int(x) and x >= 0


def unit_interval(x):
    return _num(x) and 0.0 <= x <= 1.0


def discount(x):
    return _num(x) and 0.0 <= x < 1.0


def non_negative(x):
    return _num(x) and x >= 0


def positive(x):
    return _num(x) and x > 0


def one_of(*allowed):
    return lambda x: x in allowed


def noise_levels(x):
    return isinstance(x, list) and len(x) > 0 and all(unit_interval(v) for v in x)


def arrangement(x):
    labels = [str(c) for row in x for c in row] if isinstance(x, list) and all(isinstance(r, list) for r in x) else []
    return len(x) == 3 and all(len(r) == 3 for r in x) and len(set(labels)) == 9 and \
        all(c in {str(d) for d in range(10)} for c in labels)


RULES = [
    ("seed", non_negative_int, "an integer ≥ 0"),
    ("n_runs", positive_int, "an integer ≥ 1"),
    ("device", one_of("auto", "cpu", "cuda"), "auto, cpu or cuda"),
    ("resume", one_of(True, False), "true or false"),
    ("compile", one_of(True, False), "true or false"),
    ("optimized_metric", lambda x: x is None or (isinstance(x, str) and x != ""), "null or a summary.json metric name"),
    ("cpu_threads", positive_int, "an integer ≥ 1"),
    ("task", one_of("digit_floor", "tmaze"), "digit_floor or tmaze"),
    ("env.noise", unit_interval, "a fraction of pixels in [0, 1]"),
    ("env.reward_condition", one_of(*REWARD_CONDITIONS), "cw, ccw or none (§3.5.3)"),
    ("env.patches", positive_int, "an integer ≥ 1 (patches per side of the torus)"),
    ("env.arrangement", arrangement, "a 3×3 list of 9 distinct digit classes 0–9"),
    ("env.noise_tile", lambda x: x is None or str(x) in {str(d) for d in range(10)}, "null or a digit class of the arrangement"),
    ("env.corridor_length", lambda x: _int(x) and x >= 2, "an integer ≥ 2 (T_min: start, corridor cells, junction)"),
    ("env.max_steps", positive_int, "an integer ≥ 1 (T_max)"),
    ("env.matching", one_of(True, False), "true or false"),
    ("env.digit_classes", lambda x: isinstance(x, dict) and all(_int(v) and 0 <= v <= 9 for v in x.values()),
     "a map observation name → digit class 0–9"),
    ("env.image_index", non_negative_int, "an integer ≥ 0"),
    ("env.binarize_threshold", lambda x: x is None or unit_interval(x), "null (grey levels) or a threshold in [0, 1]"),
    ("env.reservoir_size", positive_int, "an integer ≥ 1 (images per observation)"),
    ("predictor.*.n_memory", positive_int, "an integer ≥ 1"),
    ("predictor.*.reward_output", one_of("bits", "linear", "none"), "bits, linear or none"),
    ("predictor.*.predict_obs", one_of(True, False), "true or false"),
    ("predictor.*.time_average", one_of(True, False), "true or false"),
    ("predictor.*.batch_size", positive_int, "an integer ≥ 1 (1: pattern mode, one SGD step per sequence)"),
    ("predictor.*.lr", positive, "a learning rate > 0"),
    ("predictor.*.init_std", non_negative, "a standard deviation ≥ 0"),
    *[(f"predictor.*.{k}", non_negative, "a number ≥ 0") for k in ("c_y", "c_a", "rho_y", "rho_r")],
    *[(f"predictor.*.{k}", positive, "a gain > 0") for k in ("beta_m", "beta_y", "beta_r")],
    *[rule for rule in PREPROCESSOR_RULES if rule[0].startswith("preprocessor.")],
    ("actor.n_hidden", positive_int, "an integer ≥ 1"),
    ("actor.td_rule", one_of(*TD_RULES), ", ".join(TD_RULES)),
    ("actor.lr_norm", one_of(*LR_NORMS), ", ".join(LR_NORMS)),
    ("actor.gamma", discount, "a discount factor in [0, 1)"),
    ("actor.init_std", non_negative, "a standard deviation ≥ 0"),
    ("actor.bias_init_std", non_negative, "a standard deviation ≥ 0"),
    ("actor.action_code", one_of(*ACTION_CODES), ", ".join(ACTION_CODES)),
    ("actor.action_selection", one_of(*ACTION_SELECTIONS), ", ".join(ACTION_SELECTIONS)),
    ("actor.gibbs_sweeps", positive_int, "an integer ≥ 1"),
    ("actor.lr.value", positive, "a learning rate > 0"),
    ("actor.lr.start", positive, "a learning rate > 0"),
    ("actor.lr.end", positive, "a learning rate > 0"),
    ("actor.beta.start", non_negative, "an inverse temperature ≥ 0"),
    ("actor.beta.end", non_negative, "an inverse temperature ≥ 0"),
    ("trainer.steps", positive_int, "an integer ≥ 1"),
    ("trainer.log_every", positive_int, "an integer ≥ 1"),
    ("trainer.checkpoint_every", positive_int, "an integer ≥ 1"),
    ("trainer.checkpoint_every_epochs", positive_int, "an integer ≥ 1"),
    ("trainer.divergence_limit", positive, "a number > 0"),
    ("trainer.checkpoint_minutes", non_negative, "minutes ≥ 0 (0: checkpoints by count only)"),
    ("trainer.compile_group_runs", positive_int, "an integer ≥ 1 (runs per compiled group on a CPU)"),
    ("trainer.prefetch", non_negative_int, "an integer ≥ 0 (chunks of random numbers drawn ahead)"),
    ("trainer.test_per_class", positive_int, "an integer ≥ 1"),
    ("trainer.test_noise_levels", noise_levels, "a non-empty list of noise levels in [0, 1]"),
    ("trainer.n_sample", positive_int, "an integer ≥ 1 (N_sample episodes)"),
    ("trainer.collect_batch", positive_int, "an integer ≥ 1"),
    ("trainer.train_fraction", lambda x: _num(x) and 0 < x < 1, "a fraction in (0, 1)"),
    ("trainer.l_training", positive_int, "an integer ≥ 1 (L_training)"),
    ("trainer.n_epoch", non_negative_int, "an integer ≥ 0 (N_epoch)"),
    ("trainer.error_every", positive_int, "an integer ≥ 1"),
    ("trainer.n_episodes", positive_int, "an integer ≥ 1 (N episodes)"),
    ("trainer.actor_obs_scale", positive, "a scale > 0 (1: the dissertation)"),
    ("trainer.td_sample_every", positive_int, "an integer ≥ 1"),
    ("trainer.final_window", positive_int, "an integer ≥ 1"),
    ("data.test_per_class", lambda x: _int(x) and 1 <= x <= 499, "an integer in [1, 499] (500 images per class)"),
]

# summary.json metrics per task (CONTRACT §2; ferl/trainers/*.py write them), by the names that
# `optimized_metric` uses: a per-test-level metric is ``<name>/<level>`` (``greedy_accuracy/0.125``).
TASK_METRICS = {
    "tmaze": ("final_discounted_return", "final_steps_to_goal", "final_correct_goal_rate", "solved"),
    "digit_floor": ("reward_per_step_last10pct",),
}
LEVEL_METRICS = {"digit_floor": ("greedy_accuracy", "greedy_accuracy_before")}

_ABSENT = object()


def expand(cfg: DictConfig, key: str) -> list[str]:
    """The concrete keys a rule key names: ``a.*.b`` → ``a.x.b`` for every entry x of ``a``."""
    if "*" not in key:
        return [key]
    head, _, tail = key.partition(".*.")
    node = OmegaConf.select(cfg, head, default=None)
    return [f"{head}.{name}.{tail}" for name in node] if isinstance(node, DictConfig) else []


def validate(cfg: DictConfig) -> None:
    """Raise ConfigError for the first rule the config breaks, then check cross-key facts."""
    for key, test, allowed in ((k, t, a) for rule_key, t, a in RULES for k in expand(cfg, rule_key)):
        try:
            value = OmegaConf.select(cfg, key, default=_ABSENT, throw_on_missing=True)
        except MissingMandatoryValue:
            raise ConfigError(f"{key} is required: {allowed}") from None
        if value is _ABSENT:
            continue
        plain = OmegaConf.to_container(value, resolve=True) if isinstance(value, (DictConfig, ListConfig)) else value
        if not test(plain):
            raise ConfigError(f"{key}={plain!r} is not allowed: expected {allowed}")
    if cfg.device == "cuda" and not torch.cuda.is_available():
        raise ConfigError("device=cuda but no CUDA device is available: use device=auto or device=cpu")
    check_cross_keys(cfg)
    check_data(cfg)


def check_cross_keys(cfg) -> None:
    env = cfg.get("env", {})
    if env.get("noise_tile") is not None:
        labels = {str(c) for row in env.arrangement for c in row}
        if str(env.noise_tile) not in labels:
            raise ConfigError(f"env.noise_tile={env.noise_tile!r} is not allowed: expected a class of env.arrangement {sorted(labels)}")
        if str(env.noise_tile) == str(env.arrangement[1][1]):
            raise ConfigError("env.noise_tile is not allowed to be the goal (the centre of env.arrangement)")
    if "corridor_length" in env and env.max_steps < env.corridor_length:
        raise ConfigError(f"env.max_steps={env.max_steps} is not allowed: T_max must be ≥ "
                          f"env.corridor_length={env.corridor_length} (T_min)")
    if "digit_classes" in env:
        from ferl.envs.digit_tmaze import observation_names

        names = observation_names(env.matching)
        unknown = sorted(set(env.digit_classes) - set(names))
        if unknown:
            raise ConfigError(f"env.digit_classes.{unknown[0]} is not allowed: observations are {', '.join(names)}")
        missing = [n for n in names if n not in env.digit_classes]
        if missing:
            raise ConfigError(f"env.digit_classes.{missing[0]} is required: every observation needs a digit class")
    if cfg.compile and cfg.get("actor", {}).get("action_selection") == "gibbs":
        raise ConfigError("compile=true is not allowed with actor.action_selection=gibbs: its chain draws "
                          "from the generator step by step; use compile=false")
    check_preprocessor(cfg)
    check_optimized_metric(cfg)
    trainer, data = cfg.get("trainer", {}), cfg.get("data", {})
    if "test_per_class" in trainer and "test_per_class" in data and trainer.test_per_class > data.test_per_class:
        raise ConfigError(f"trainer.test_per_class={trainer.test_per_class} is not allowed: at most "
                          f"data.test_per_class={data.test_per_class} held-out images per class exist")


def check_optimized_metric(cfg) -> None:
    """``optimized_metric`` names a metric that this task's summary.json will hold."""
    metric, task = cfg.get("optimized_metric"), cfg.get("task")
    if metric is None or task not in TASK_METRICS:
        return
    names, allowed = list(TASK_METRICS[task]), ", ".join(TASK_METRICS[task])
    if LEVEL_METRICS.get(task):
        levels = [f"{x:g}" for x in cfg.get("trainer", {}).get("test_noise_levels", [])]
        names += [f"{m}/{lvl}" for m in LEVEL_METRICS[task] for lvl in levels]
        allowed += ", " + ", ".join(f"{m}/L" for m in LEVEL_METRICS[task]) + \
            f" with L a test noise level of trainer.test_noise_levels ({', '.join(levels)})"
    if metric not in names:
        raise ConfigError(f"optimized_metric={metric!r} is not allowed: expected null or a summary.json "
                          f"metric of task={task}: {allowed}")


def check_preprocessor(cfg) -> None:
    """The RBM preprocessor reads 784-pixel images: the digit T-mazes (§5.3.2), not bit codes."""
    pre = cfg.get("preprocessor")
    if pre is None:
        return
    if cfg.get("task") != "tmaze" or "digit_classes" not in cfg.get("env", {}):
        raise ConfigError("preprocessor is not allowed here: it processes the images of env=digit_tmaze "
                          "(use preprocessor=null for bit observations)")
    if pre.n_visible != 784:
        raise ConfigError(f"preprocessor.n_visible={pre.n_visible} is not allowed: the digit images have 784 pixels")


def check_data(cfg) -> None:
    data = cfg.get("data")
    if data is None or "root" not in data.keys():
        return
    if OmegaConf.is_missing(data, "root"):
        raise ConfigError("data.root is required with data=mnist_idx: a folder holding the MNIST IDX files")
    from ferl.data import MnistIDX

    try:
        MnistIDX(data.root).check()
    except DataError as e:
        raise ConfigError(str(e)) from None
