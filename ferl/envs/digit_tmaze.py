"""Digit matching T-mazes: static digits (§4.3.3, Fig. 4.20, Table 4.2) and a stochastic
reservoir of handwritten digits (§5.3.2, Fig. 5.14).

Every distinct observation of the (matching) T-maze is shown as an image of a digit class. Its
reservoir holds the ``image_index``-th … (``image_index`` + ``reservoir_size`` − 1)-th training
images of the class; a reservoir of one is the static digit of chapter 4, a reservoir of 100 the
noisy observations of chapter 5, drawn afresh at every visit, even within an episode. Pixels are
binarized (> ``binarize_threshold`` → 1, §4.3.3 "binarized") or, with a null threshold, kept as
intensities in [0, 1] for the mean-field visible units of the ch. 5 preprocessor.
"""
from typing import Annotated

import torch

from ferl.config.params import (Allowed, ArgumentError, NonNegativeInt, PositiveInt, UnitInterval, checked)
from ferl.data import MnistSplit
from ferl.envs.tmaze import TMaze, observation_names


def class_images(data: MnistSplit, digit_classes: dict, image_index: int, reservoir_size: int,
                 threshold: float | None) -> dict:
    """Observation name → (reservoir_size, 784) images of its digit class."""
    images = {}
    for name, label in digit_classes.items():
        pool = data.train_images[data.train_labels == int(label)]
        if image_index + reservoir_size > len(pool):
            raise ValueError(f"env.reservoir_size={reservoir_size} with env.image_index={image_index}: class {label} "
                             f"has {len(pool)} training images")
        reservoir = pool[image_index: image_index + reservoir_size]
        images[name] = reservoir if threshold is None else (reservoir > threshold).float()
    return images


class DigitTMaze(TMaze):
    """A (matching) T-maze whose observations are the digit images of ``digit_classes``; every
    other argument is the T-maze's."""

    @checked
    def __init__(self, n_runs: PositiveInt, generator: torch.Generator, data: MnistSplit,
                 digit_classes: dict[str, Annotated[int, Allowed(lambda c: 0 <= c <= 9, "a digit class 0–9")]],
                 image_index: NonNegativeInt = 0, reservoir_size: PositiveInt = 1,
                 binarize_threshold: UnitInterval | None = 0.5, device="cpu", **maze):
        self.digit_classes = {name: int(label) for name, label in dict(digit_classes).items()}
        images = class_images(data, self.digit_classes, image_index, reservoir_size, binarize_threshold)
        super().__init__(n_runs, generator, images={k: v.to(device) for k, v in images.items()}, device=device, **maze)

    def describe(self) -> dict:
        return {**super().describe(), "digit_classes": self.digit_classes}

    @classmethod
    def check_config(cls, args: dict) -> None:
        """Every observation of the maze has a digit class, and only those."""
        TMaze.check_config(args)
        names = observation_names(args["matching"])
        unknown = sorted(set(args["digit_classes"]) - set(names))
        if unknown:
            raise ArgumentError(f"digit_classes.{unknown[0]}", f"the maze's observations are {', '.join(names)}")
        missing = [n for n in names if n not in args["digit_classes"]]
        if missing:
            raise ArgumentError(f"digit_classes.{missing[0]}", "a class (every observation of the maze needs one)")
