"""Digit matching T-mazes: static digits (§4.3.3, Fig. 4.20, Table 4.2) and a stochastic
reservoir of handwritten digits (§5.3.2, Fig. 5.14).

Every distinct observation of the (matching) T-maze is shown as an image of a digit class. Its
reservoir holds the ``image_index``-th … (``image_index`` + ``reservoir_size`` − 1)-th training
images of the class; a reservoir of one is the static digit of chapter 4, a reservoir of 100 the
noisy observations of chapter 5, drawn afresh at every visit, even within an episode. Pixels are
binarized (> ``binarize_threshold`` → 1, §4.3.3 "binarized") or, with a null threshold, kept as
intensities in [0, 1] for the mean-field visible units of the ch. 5 preprocessor.

Continuous observations (§5.4 "Fifth", for the Gaussian RBM): with ``pixel_noise_std`` σ > 0 the
grey-level images carry Gaussian pixel noise, x + ε, ε ~ N(0, σ² I), not clipped to [0, 1]. The
maze's observations are ids into a finite ``observation_table`` that the preprocessor processes
once (Algorithm 2) and the episodes store, so the noise cannot be drawn at every visit: every
reservoir image gets ``noise_copies`` noisy copies, drawn once when the maze is built, and the
reservoir of an observation is its K images × C copies (id n·K·C + c·K + k: copy c of image k),
from which every visit draws one afresh as before. The copies come from a stream of their own,
seeded from the maze generator's seed (``ferl.rng.IMAGE_NOISE``): every maze built for a job (the
trainer builds more for its random episodes) has the same table, and the noise shifts no other
random number. Observations of one digit class share their noisy copies, as they share images.
"""

from typing import Annotated

import torch

from ferl import rng
from ferl.config.params import Allowed, ArgumentError, NonNegative, NonNegativeInt, PositiveInt, UnitInterval, checked
from ferl.data import MnistSplit
from ferl.envs.tmaze import TMaze, observation_names


def class_images(
    data: MnistSplit, digit_classes: dict, image_index: int, reservoir_size: int, threshold: float | None
) -> dict:
    """Observation name → (reservoir_size, 784) images of its digit class."""
    images = {}
    for name, label in digit_classes.items():
        pool = data.train_images[data.train_labels == int(label)]
        if image_index + reservoir_size > len(pool):
            raise ValueError(
                f"env.reservoir_size={reservoir_size} with env.image_index={image_index}: class {label} "
                f"has {len(pool)} training images"
            )
        reservoir = pool[image_index : image_index + reservoir_size]
        images[name] = reservoir if threshold is None else (reservoir > threshold).float()
    return images


def noisy_copies(images: dict, digit_classes: dict, std: float, copies: int, generator: torch.Generator) -> dict:
    """Observation name → its reservoir (K, V) repeated ``copies`` times, (copies·K, V), plus
    N(0, std²) per pixel; one draw per digit class (in class order), shared by its observations."""
    noisy = {}
    for label in sorted(set(digit_classes.values())):
        names = [name for name, c in digit_classes.items() if c == label]
        clean = images[names[0]].repeat(copies, 1)
        drawn = clean + std * torch.randn(clean.shape, generator=generator, dtype=clean.dtype)
        noisy.update({name: drawn for name in names})
    return noisy


class DigitTMaze(TMaze):
    """A (matching) T-maze whose observations are the digit images of ``digit_classes``, with
    Gaussian pixel noise of s.d. ``pixel_noise_std`` in ``noise_copies`` copies of every image
    (grey levels only; ignored without noise); every other argument is the T-maze's."""

    @checked
    def __init__(
        self,
        n_runs: PositiveInt,
        generator: torch.Generator,
        data: MnistSplit,
        digit_classes: dict[str, Annotated[int, Allowed(lambda c: 0 <= c <= 9, "a digit class 0–9")]],
        image_index: NonNegativeInt = 0,
        reservoir_size: PositiveInt = 1,
        binarize_threshold: UnitInterval | None = 0.5,
        pixel_noise_std: NonNegative = 0.0,
        noise_copies: PositiveInt = 10,
        device="cpu",
        **maze,
    ):
        self.digit_classes = {name: int(label) for name, label in dict(digit_classes).items()}
        self.pixel_noise_std, self.noise_copies = pixel_noise_std, noise_copies
        images = class_images(data, self.digit_classes, image_index, reservoir_size, binarize_threshold)
        if pixel_noise_std > 0:
            stream = rng.generator(generator.initial_seed() + rng.IMAGE_NOISE)
            images = noisy_copies(images, self.digit_classes, pixel_noise_std, noise_copies, stream)
        super().__init__(n_runs, generator, images={k: v.to(device) for k, v in images.items()}, device=device, **maze)

    def describe(self) -> dict:
        return {
            **super().describe(),
            "digit_classes": self.digit_classes,
            "pixel_noise_std": self.pixel_noise_std,
            "noise_copies": self.noise_copies if self.pixel_noise_std > 0 else 1,
        }

    @classmethod
    def check_config(cls, args: dict) -> None:
        """Every observation of the maze has a digit class, and only those; pixel noise only on grey levels."""
        TMaze.check_config(args)
        names = observation_names(args["matching"])
        unknown = sorted(set(args["digit_classes"]) - set(names))
        if unknown:
            raise ArgumentError(f"digit_classes.{unknown[0]}", f"the maze's observations are {', '.join(names)}")
        missing = [n for n in names if n not in args["digit_classes"]]
        if missing:
            raise ArgumentError(f"digit_classes.{missing[0]}", "a class (every observation of the maze needs one)")
        if args["pixel_noise_std"] > 0 and args["binarize_threshold"] is not None:
            raise ArgumentError(
                "pixel_noise_std",
                "0 unless binarize_threshold is null (the noise is added to "
                f"grey levels; binarize_threshold={args['binarize_threshold']})",
            )
