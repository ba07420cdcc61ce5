"""Digit matching T-maze with static digits (§4.3.3, Fig. 4.20, Table 4.2).

Every distinct observation of the (matching) T-maze is shown as one fixed binarized image of a
digit class: the ``image_index``-th training image of the class, pixels > ``binarize_threshold``
set to 1. Chapter 5's stochastic reservoir replaces the single instance by many.
"""
import torch

from ferl.data import MnistSplit
from ferl.envs.tmaze import TMaze, observation_names

__all__ = ["DigitTMaze", "observation_names"]


def class_images(data: MnistSplit, digit_classes: dict, image_index: int, threshold: float) -> dict:
    """Observation name → binarized 784-pixel image of its digit class."""
    images = {}
    for name, label in digit_classes.items():
        pool = data.train_images[data.train_labels == int(label)]
        if image_index >= len(pool):
            raise ValueError(f"env.image_index={image_index}: class {label} has {len(pool)} training images")
        images[name] = (pool[image_index] > threshold).float()
    return images


def DigitTMaze(n_runs: int, generator: torch.Generator, data: MnistSplit, digit_classes: dict,
               image_index: int = 0, binarize_threshold: float = 0.5, device="cpu", **maze) -> TMaze:
    """A T-maze whose observations are the digit images of ``digit_classes``."""
    images = class_images(data, dict(digit_classes), image_index, binarize_threshold)
    return TMaze(n_runs, generator, images={k: v.to(device) for k, v in images.items()}, device=device, **maze)
