"""Observations of third-party Gymnasium environments as the binary vectors ferl's agents see.

The FERL actor's state nodes are binary (§3.2: the RBM's visible units), and the episodic phases
store observations as ids into a table of such vectors (``EpisodicEnvironment``), so every
observation space needs a declared encoding into {0, 1}^O:

* ``onehot``: a ``Discrete(n)`` value as n bits with one on; ``MultiDiscrete`` as one such group per
  entry; ``MultiBinary`` as its own bits; ``Tuple`` and ``Dict`` of these as their parts' groups
  in order (a ``Dict``'s keys sorted, as Gymnasium orders them).
* ``thresholds``: a ``Box`` value x as the bits [x_i > θ_j] for every entry i and threshold θ_j of
  ``thresholds`` (a thermometer code: k thresholds give k + 1 levels per entry).
* ``minigrid``: MiniGrid's symbolic view, a dict whose ``image`` is (7, 7, 3) (object, colour,
  state) indices per cell, as one one-hot group of each per cell (Chevalier-Boisvert et al. 2023,
  ``minigrid.core.constants``); the ``direction`` and ``mission`` entries are left out, as the
  egocentric view already turns with the agent and a task's mission is fixed.
* ``auto``: ``minigrid`` for such a dict, ``onehot`` where every part is discrete; anything else
  has no encoding and is refused naming the space.

An encoding is a ``gymnasium.ObservationWrapper`` (``BinaryObservation``), so the same code serves
ferl's vector of environments and any outside learner given the wrapped environment.
"""

from collections.abc import Callable, Iterable
from typing import Literal, get_args

import gymnasium
import numpy as np
from gymnasium import spaces

Encoding = Literal["auto", "onehot", "thresholds", "minigrid"]
ENCODINGS = get_args(Encoding)
# MiniGrid's symbolic indices (minigrid.core.constants: OBJECT_TO_IDX, COLOR_TO_IDX, STATE_TO_IDX)
MINIGRID_SIZES = (11, 6, 3)

Encoder = Callable[[object], np.ndarray]  # one observation → uint8 bits (O,)


class NoEncoding(ValueError):
    """The observation space has no encoding of the kind asked for (the message names the space)."""


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


def thresholds_encoder(space, thresholds) -> tuple[Encoder, int]:
    """(encoder, bits) of a ``Box``: [x_i > θ_j] for every entry i, threshold j (module docstring)."""
    if not isinstance(space, spaces.Box):
        raise NoEncoding(f"{space} is not a Box: env.encoding=thresholds encodes Box observations")
    if not thresholds:
        raise NoEncoding(f"{space} needs env.thresholds (a list of numbers) for env.encoding=thresholds")
    theta = np.asarray(thresholds, np.float64)
    return (lambda x: (np.asarray(x, np.float64).reshape(-1, 1) > theta).astype(np.uint8).reshape(-1)), int(
        np.prod(space.shape)
    ) * len(theta)


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


def encoder_for(space, encoding: str, thresholds=()) -> tuple[Encoder, int]:
    """The encoder of ``space`` that ``encoding`` names (``auto``: the module docstring's choice)."""
    if encoding == "auto":
        if is_minigrid(space):
            return minigrid_encoder(space)
        try:
            return onehot_encoder(space)
        except NoEncoding:
            raise NoEncoding(
                f"{space} has no automatic encoding: a Box needs env.encoding=thresholds with "
                f"env.thresholds=[...]; other spaces are not supported"
            ) from None
    if encoding == "onehot":
        return onehot_encoder(space)
    if encoding == "thresholds":
        return thresholds_encoder(space, thresholds)
    return minigrid_encoder(space)


class BinaryObservation(gymnasium.ObservationWrapper):
    """An environment whose observations are the bits of ``encoding`` (``MultiBinary(O)``)."""

    def __init__(self, env, encoding: str = "auto", thresholds=()):
        super().__init__(env)
        self.encode, size = encoder_for(env.observation_space, encoding, thresholds)
        self.observation_space = spaces.MultiBinary(size)

    def observation(self, observation):
        return self.encode(observation)
