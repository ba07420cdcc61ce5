"""Tensors as grey images: weights, pixel vectors and matrices for TensorBoard and the records.

Nothing here changes a tensor it is given or draws a random number.
"""

import math

import numpy as np
import torch

from ferl.data import IMAGE_PIXELS

IMAGE_SIDE = math.isqrt(IMAGE_PIXELS)  # MNIST images: 784 = 28 × 28 pixels


def unit_range(x: torch.Tensor, dims) -> torch.Tensor:
    """x scaled to [0, 1] over ``dims`` (each image or matrix on its own); non-finite entries
    (a diverged run) count as 0."""
    x = torch.where(torch.isfinite(x), x, torch.zeros_like(x))
    lo, hi = x.amin(dims, keepdim=True), x.amax(dims, keepdim=True)
    return (x - lo) / (hi - lo + 1e-12)


def weight_images(W: torch.Tensor) -> torch.Tensor:
    """Run 0's image→hidden weights W (R, 784, H) as H images (H, 1, 28, 28), each scaled to
    [0, 1] (Fig. 3.5)."""
    w = W[0].detach().float().cpu().T.reshape(-1, 1, IMAGE_SIDE, IMAGE_SIDE)
    return unit_range(w, (1, 2, 3))


def tile(images, n_cols: int | None = None, pad: int = 1) -> torch.Tensor:
    """Images (N, h, w) — or (rows, cols, h, w), one row each — in [0, 1] as one grey image
    (1, H, W) with ``pad`` white pixels between them."""
    x = (
        torch.as_tensor(np.asarray(images, dtype=np.float32))
        if not torch.is_tensor(images)
        else images.detach().float().cpu()
    )
    if x.dim() == 3:
        n_cols = n_cols or math.ceil(math.sqrt(x.shape[0]))
        n_rows = math.ceil(x.shape[0] / n_cols)
        x = torch.cat([x, torch.ones(n_rows * n_cols - x.shape[0], *x.shape[1:])]).view(n_rows, n_cols, *x.shape[1:])
    n_rows, n_cols, h, w = x.shape
    canvas = torch.ones(n_rows * (h + pad) + pad, n_cols * (w + pad) + pad)
    for r in range(n_rows):
        for c in range(n_cols):
            canvas[pad + r * (h + pad) : pad + r * (h + pad) + h, pad + c * (w + pad) : pad + c * (w + pad) + w] = x[
                r, c
            ]
    return canvas.unsqueeze(0)


def as_images(flat) -> torch.Tensor:
    """(…, 784) pixel vectors → (…, 28, 28) float32."""
    x = (
        torch.as_tensor(np.asarray(flat, dtype=np.float32))
        if not torch.is_tensor(flat)
        else flat.detach().float().cpu()
    )
    return x.reshape(*x.shape[:-1], IMAGE_SIDE, IMAGE_SIDE)


def matrix_image(M: torch.Tensor, min_side: int = 200) -> torch.Tensor:
    """A matrix (rows, cols) as a grey image (1, H, W) scaled to [0, 1], each entry a square of
    pixels so that small matrices stay visible."""
    m = unit_range(M.detach().float().cpu(), (0, 1))
    k = max(1, math.ceil(min_side / max(m.shape)))
    return m.repeat_interleave(k, 0).repeat_interleave(k, 1).unsqueeze(0)
