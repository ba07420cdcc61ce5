"""Observations of third-party Gymnasium environments as the binary vectors ferl's agents see.

The FERL actor's state nodes are binary (§3.2: the RBM's visible units), and the episodic phases
store observations as ids into a table of such vectors (``EpisodicEnvironment``), so every
observation space needs a declared encoding into {0, 1}^O:

* ``onehot``: a ``Discrete(n)`` value as n bits with one on; ``MultiDiscrete`` as one such group per
  entry; ``MultiBinary`` as its own bits; ``Tuple`` and ``Dict`` of these as their parts' groups
  in order (a ``Dict``'s keys sorted, as Gymnasium orders them).
* ``thresholds``: a ``Box`` value x as the bits [x_i > θ_ij] for every entry i (in C order) and
  threshold θ_ij of its list, a thermometer code: k_i increasing thresholds give k_i + 1 levels.
  ``thresholds`` is one list shared by every entry, ``[θ_1, …]``, or one list per entry,
  ``[[θ_11, …], [θ_21, …], …]``, so entries of different ranges each get thresholds of their own;
  entry i then takes k_i bits (an empty list: the entry is left out), and the code has
  Π_i (k_i + 1) distinct values. ``auto`` (or none given) derives one list per entry from the
  space's bounds or a random-policy sample (``ferl.envs.derived``), where the environment can be
  played: ``ferl.envs.gymnasium_vector`` derives them and hands the lists here.
* ``minigrid``: MiniGrid's symbolic view, a dict whose ``image`` is (7, 7, 3) (object, colour,
  state) indices per cell, as one one-hot group of each per cell (Chevalier-Boisvert et al. 2023,
  ``minigrid.core.constants``); the ``direction`` and ``mission`` entries are left out, as the
  egocentric view already turns with the agent and a task's mission is fixed.
* ``real``: a ``Box`` value x as one real number a entry, y_i = clip((x_i − μ_i) / (6 σ_i) + ½, 0, 1):
  the mean ± 3 standard deviations of a random-policy sample (``ferl.envs.derived``) mapped onto
  [0, 1], as the grey levels of chapter 5's pixels are (§5.2). The actor's state nodes and the
  predictors' inputs take the value itself; a predictor's observation head predicts it as it
  predicts a grey pixel, a Bernoulli mean (Eq. 4.4's sigmoid and cross-entropy with soft targets).
  An entry constant over the sample gives ½ throughout. No table of distinct codes can hold real
  values: ``ferl.envs.gymnasium_vector`` keeps each step's vector in a row of its own.
* ``auto``: ``minigrid`` for such a dict, ``onehot`` where every part is discrete, ``thresholds``
  for a ``Box``; anything else has no encoding and is refused naming the space.

Everything about an encoding is checked when it is built, before a run starts (docs/usage.md,
"Training"): thresholds that are not numbers, not increasing, a list per entry whose count is not
the Box's entries, thresholds given to an encoding that takes none (``BadThresholds``). The number
of distinct codes an encoding can give (``distinct_codes``) is known for ``onehot`` and
``thresholds`` (not for ``minigrid``), so the table of observations can be sized to it.

An encoding is a ``gymnasium.ObservationWrapper`` (``BinaryObservation``), so the same code serves
ferl's vector of environments and any outside learner given the wrapped environment.
"""

import math
from collections.abc import Callable, Iterable, Sequence
from typing import Literal, get_args

import gymnasium
import numpy as np
from gymnasium import spaces

Encoding = Literal["auto", "onehot", "thresholds", "minigrid", "real"]
ENCODINGS = get_args(Encoding)
REAL_SPREAD = 6.0  # real: the sample's μ ± REAL_SPREAD/2 σ spans [0, 1]
# MiniGrid's symbolic indices (minigrid.core.constants: OBJECT_TO_IDX, COLOR_TO_IDX, STATE_TO_IDX)
MINIGRID_SIZES = (11, 6, 3)

Encoder = Callable[[object], np.ndarray]  # one observation → uint8 bits (O,)


class NoEncoding(ValueError):
    """The observation space has no encoding of the kind asked for (the message names the space)."""


class BadThresholds(NoEncoding):
    """``thresholds`` cannot encode the observation space (the message says why): a fault of
    ``env.thresholds`` rather than of ``env.encoding``."""


def onehot_encoder(space) -> tuple[Encoder, int]:
    """(encoder, number of bits) of a space of discrete parts (module docstring: ``onehot``)."""
    if isinstance(space, spaces.Discrete):
        n, start = int(space.n), int(space.start)
        eye = np.eye(n, dtype=np.uint8)
        return (lambda x: eye[int(x) - start]), n
    if isinstance(space, spaces.MultiDiscrete):
        sizes = space.nvec.reshape(-1).astype(np.int64)
        offsets = np.concatenate([[0], np.cumsum(sizes)[:-1]])
        starts = np.asarray(space.start).reshape(-1) if getattr(space, "start", None) is not None else 0
        total = int(sizes.sum())

        def encode(x):
            bits = np.zeros(total, np.uint8)
            bits[offsets + np.asarray(x).reshape(-1) - starts] = 1
            return bits

        return encode, total
    if isinstance(space, spaces.MultiBinary):
        return (lambda x: np.asarray(x, np.uint8).reshape(-1)), int(np.prod(space.shape))
    if isinstance(space, (spaces.Tuple, spaces.Dict)):
        named: Iterable[tuple[str | int, spaces.Space]] = (
            space.spaces.items() if isinstance(space, spaces.Dict) else enumerate(space.spaces)
        )
        subspaces = dict(named)
        keys = list(subspaces)
        parts = [onehot_encoder(subspaces[k]) for k in keys]
        return (lambda x: np.concatenate([enc(x[k]) for k, (enc, _) in zip(keys, parts)])), sum(n for _, n in parts)
    raise NoEncoding(
        f"{space} has no one-hot encoding (only Discrete, MultiDiscrete, MultiBinary and Tuple/Dict of them)"
    )


def threshold_lists(space, thresholds) -> list[np.ndarray]:
    """The increasing thresholds of every entry of the ``Box`` (C order): the shared list
    repeated, or the lists given one per entry (module docstring); BadThresholds otherwise."""
    if not isinstance(space, spaces.Box):
        raise NoEncoding(f"{space} is not a Box: env.encoding=thresholds encodes Box observations")
    entries = int(np.prod(space.shape))
    if not thresholds:
        raise BadThresholds(
            f"{space} needs thresholds for env.encoding=thresholds: [θ_1, …] shared by its "
            f"{entries} entries, or one such list per entry"
        )
    nested = [isinstance(t, Sequence) and not isinstance(t, str) for t in thresholds]
    if any(nested) and not all(nested):
        raise BadThresholds("mixes numbers and lists: give one list of numbers, or one list per entry")
    lists = [list(t) for t in thresholds] if all(nested) else [list(thresholds)] * entries
    if len(lists) != entries:
        raise BadThresholds(
            f"gives {len(lists)} lists, one per entry, but {space} has {entries} entries (shape {space.shape})"
        )
    if not any(lists):  # an empty list leaves its entry out; all empty would leave no bits
        raise BadThresholds("are all empty lists: at least one entry needs a threshold")
    out = []
    for i, theta in enumerate(lists):
        where = f"entry {i}'s list {theta}" if all(nested) else f"{theta}"
        if (not theta and not all(nested)) or not all(
            isinstance(t, (int, float)) and not isinstance(t, bool) for t in theta
        ):
            raise BadThresholds(f"{where} is not a list of numbers")
        values = np.asarray(theta, np.float64)
        if not np.isfinite(values).all() or (np.diff(values) <= 0).any():
            raise BadThresholds(f"{where} is not finite and increasing (a thermometer code: θ_1 < θ_2 < …)")
        out.append(values)
    return out


def thresholds_encoder(space, thresholds) -> tuple[Encoder, int]:
    """(encoder, bits) of a ``Box``: [x_i > θ_ij] for every entry i, threshold j (module docstring)."""
    lists = threshold_lists(space, thresholds)
    entry = np.repeat(np.arange(len(lists)), [len(theta) for theta in lists])  # the entry of every bit
    theta = np.concatenate(lists)
    return (lambda x: (np.asarray(x, np.float64).reshape(-1)[entry] > theta).astype(np.uint8)), len(theta)


def fixed_bits(space, thresholds) -> list[tuple[int, float]]:
    """(entry, θ) of every threshold outside its entry's bounds [low_i, high_i): a bit that never
    changes (θ ≥ high_i: always 0; θ < low_i: always 1), what a list shared by entries of different
    ranges gives."""
    low, high = np.asarray(space.low, np.float64).reshape(-1), np.asarray(space.high, np.float64).reshape(-1)
    return [
        (i, float(t))
        for i, theta in enumerate(threshold_lists(space, thresholds))
        for t in theta
        if t >= high[i] or t < low[i]
    ]


def distinct_codes(space, encoding: str, thresholds=()) -> int | None:
    """How many distinct codes ``encoding`` can give for ``space`` (None: not known in advance,
    MiniGrid's view): a bound on the distinct observations a run can meet."""
    encoding = resolved(space, encoding, thresholds)
    if encoding == "real":
        return None  # real values: no finite set of codes
    if encoding == "thresholds":
        return math.prod(len(theta) + 1 for theta in threshold_lists(space, thresholds))
    if encoding == "minigrid":
        return None
    if isinstance(space, spaces.Discrete):
        return int(space.n)
    if isinstance(space, spaces.MultiDiscrete):
        return math.prod(int(n) for n in space.nvec.reshape(-1))
    if isinstance(space, spaces.MultiBinary):
        return 2 ** int(np.prod(space.shape))
    if isinstance(space, (spaces.Tuple, spaces.Dict)):
        parts = space.spaces.values() if isinstance(space, spaces.Dict) else space.spaces
        counts = [distinct_codes(part, "onehot") for part in parts]
        return None if None in counts else math.prod(c for c in counts if c is not None)
    return None


def is_minigrid(space) -> bool:
    image = space.spaces.get("image") if isinstance(space, spaces.Dict) else None
    return isinstance(image, spaces.Box) and image.shape[-1:] == (3,) and len(image.shape) == 3


def minigrid_encoder(space) -> tuple[Encoder, int]:
    """(encoder, bits) of MiniGrid's symbolic view: object, colour, state one-hot per cell."""
    if not is_minigrid(space):
        raise NoEncoding(f"{space} is not MiniGrid's symbolic view (a Dict with an (H, W, 3) 'image')")
    cells = int(np.prod(space.spaces["image"].shape[:2]))
    offsets = np.concatenate([[0], np.cumsum(MINIGRID_SIZES)[:-1]])
    width = sum(MINIGRID_SIZES)

    def encode(x):
        bits = np.zeros((cells, width), np.uint8)
        bits[np.arange(cells)[:, None], offsets + x["image"].reshape(cells, 3)] = 1
        return bits.reshape(-1)

    return encode, cells * width


def resolved(space, encoding: str, thresholds=()) -> str:
    """The encoding that ``encoding`` names for ``space`` (``auto``: the module docstring's choice)."""
    if encoding != "auto":
        return encoding
    return (
        "minigrid" if is_minigrid(space) else "thresholds" if isinstance(space, spaces.Box) and thresholds else "onehot"
    )


def encoder_for(space, encoding: str, thresholds=()) -> tuple[Encoder, int]:
    """The encoder of ``space`` that ``encoding`` names (``auto``: the module docstring's choice);
    thresholds given to an encoding that takes none are refused."""
    chosen = resolved(space, encoding, thresholds)
    if chosen == "real":  # values, not bits: RealObservation, with the sample's statistics
        raise NoEncoding(f"{space}: env.encoding=real gives real values, not bits (``real_encoder``)")
    if chosen == "thresholds":
        return thresholds_encoder(space, thresholds)
    if chosen == "minigrid":
        made = minigrid_encoder(space)
    else:
        try:
            made = onehot_encoder(space)
        except NoEncoding:
            if encoding != "auto":
                raise
            raise NoEncoding(
                f"{space} has no automatic encoding: a Box needs thresholds (env.thresholds=auto "
                f"derives them, or [...]: one list, or one per entry); other spaces are not supported"
            ) from None
    if thresholds:
        raise BadThresholds(
            f"are given, but env.encoding={encoding} encodes {space} without them; "
            f"thresholds encode a Box (env.encoding=thresholds or auto)"
        )
    return made


def real_box(space) -> None:
    """NoEncoding unless ``space`` is a ``Box``, the one space ``real`` encodes."""
    if not isinstance(space, spaces.Box):
        raise NoEncoding(f"{space} is not a Box: env.encoding=real encodes Box observations")


def real_encoder(space, mean: Sequence[float], std: Sequence[float]) -> tuple[Encoder, int]:
    """(encoder, entries) of a ``Box`` as real values in [0, 1] from the sample's per-entry ``mean``
    and ``std`` (module docstring: ``real``); float32 values, each entry in C order."""
    real_box(space)
    mu, sigma = np.asarray(mean, np.float64), np.asarray(std, np.float64)
    width = np.where(sigma > 0, REAL_SPREAD * sigma, np.inf)  # a constant entry: ½ throughout

    def encode(x):
        z = (np.asarray(x, np.float64).reshape(-1) - mu) / width + 0.5
        return np.clip(z, 0.0, 1.0).astype(np.float32)

    return encode, int(np.prod(space.shape))


class RealObservation(gymnasium.ObservationWrapper):
    """An environment whose ``Box`` observations are real values in [0, 1] (``real_encoder``)."""

    def __init__(self, env, mean: Sequence[float], std: Sequence[float]):
        super().__init__(env)
        self.encode, size = real_encoder(env.observation_space, mean, std)
        self.observation_space = spaces.Box(0.0, 1.0, (size,), np.float32)

    def observation(self, observation):
        return self.encode(observation)


class BinaryObservation(gymnasium.ObservationWrapper):
    """An environment whose observations are the bits of ``encoding`` (``MultiBinary(O)``)."""

    def __init__(self, env, encoding: str = "auto", thresholds=()):
        super().__init__(env)
        self.encode, size = encoder_for(env.observation_space, encoding, thresholds)
        self.observation_space = spaces.MultiBinary(size)

    def observation(self, observation):
        return self.encode(observation)
