"""Fitted preprocessors kept on disk, so that only the first run of a setting pays for the fit.

A fit is a pure function of the preprocessor's constructor arguments (its ``hparams``: sizes,
n_runs and seed included: every run trains on its own stream from seed + r) and the training
images, so those two are the key. Files are written atomically: concurrent jobs filling the same
cache both train and the last rename wins, with identical contents.
"""
import hashlib
import json
import os
from pathlib import Path

import numpy as np
import torch


def tensor_digest(x: torch.Tensor) -> str:
    """sha256 of a tensor's shape, dtype and values."""
    digest = hashlib.sha256(f"{tuple(x.shape)} {x.dtype}".encode())
    digest.update(x.detach().cpu().contiguous().numpy().data)
    return digest.hexdigest()


def load_or_fit(preprocessor, images: torch.Tensor, cache_dir, writer=None) -> tuple[np.ndarray, bool]:
    """``preprocessor.train(images)`` (its own streams), or the state that the same hparams and
    images saved in ``cache_dir`` before (None: no cache). The file is
    ``<class>-<sha256[:16]>.pt``. Returns (the training errors (R, sweeps), whether cached)."""
    if cache_dir is None:
        return preprocessor.train(images, None, writer), False
    key = json.dumps({"hparams": preprocessor.hparams, "images": tensor_digest(images)}, sort_keys=True, default=str)
    name = type(preprocessor).__name__.lower()
    path = Path(cache_dir) / f"{name}-{hashlib.sha256(key.encode()).hexdigest()[:16]}.pt"
    if path.is_file():
        saved = torch.load(path, map_location=images.device)
        preprocessor.load_state_dict(saved["state_dict"])
        return saved["errors"].numpy(), True
    errors = preprocessor.train(images, None, writer)
    path.parent.mkdir(parents=True, exist_ok=True)
    tmp = path.with_name(f"{path.name}.{os.getpid()}.tmp")  # readers never see a half-written file
    torch.save({"state_dict": preprocessor.state_dict(), "errors": torch.from_numpy(errors), "key": key}, tmp)
    os.replace(tmp, path)
    return errors, False
