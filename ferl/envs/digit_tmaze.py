"""Digit matching T-mazes: static digits (§4.3.3, Fig. 4.20, Table 4.2) and a stochastic
reservoir of handwritten digits (§5.3.2, Fig. 5.14).

Every distinct observation of the (matching) T-maze is shown as an image of a digit class. Its
reservoir holds the ``image_index``-th … (``image_index`` + ``reservoir_size`` − 1)-th training
images of the class; a reservoir of one is the static digit of chapter 4, a reservoir of 100 the
noisy observations of chapter 5, drawn afresh at every visit, even within an episode. Pixels are
binarized (> ``binarize_threshold`` → 1, §4.3.3 "binarized") or, with a null threshold, kept as
intensities in [0, 1] for the mean-field visible units of the ch. 5 preprocessor.
"""
import torch

from ferl.data import MnistSplit
from ferl.envs.tmaze import TMaze, observation_names

__all__ = ["DigitTMaze", "observation_names"]


def class_images(data: MnistSplit, digit_classes: dict, image_index: int, reservoir_size: int,
                 threshold: float | None) -> dict:
    """Observation name → (reservoir_size, 784) images of its digit class."""
    if reservoir_size < 1:
        raise ValueError(f"env.reservoir_size must be an integer ≥ 1, got {reservoir_size}")
    images = {}
    for name, label in digit_classes.items():
        pool = data.train_images[data.train_labels == int(label)]
        if image_index + reservoir_size > len(pool):
            raise ValueError(f"env.reservoir_size={reservoir_size} with env.image_index={image_index}: class {label} "
                             f"has {len(pool)} training images")
        reservoir = pool[image_index: image_index + reservoir_size]
        images[name] = reservoir if threshold is None else (reservoir > threshold).float()
    return images


def DigitTMaze(n_runs: int, generator: torch.Generator, data: MnistSplit, digit_classes: dict,
               image_index: int = 0, reservoir_size: int = 1, binarize_threshold: float | None = 0.5,
               device="cpu", **maze) -> TMaze:
    """A T-maze whose observations are the digit images of ``digit_classes``."""
    images = class_images(data, dict(digit_classes), image_index, reservoir_size, binarize_threshold)
    return TMaze(n_runs, generator, images={k: v.to(device) for k, v in images.items()}, device=device, **maze)
