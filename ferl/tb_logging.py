"""TensorBoard logging shared by the trainers; the tags are listed in docs/records.md
("TensorBoard tags").

Every tag is ``<phase>/<quantity>`` (``actor/discounted_return_ma200``, ``schedule/beta``);
histograms are ``<phase>/weights/<parameter>``. Nothing here draws a random number or changes a
tensor it is given, so logging never changes what a run computes; weights, images and
embeddings are run 0's, logged once per phase.
"""
import json
import math
import time

import numpy as np
import torch
from omegaconf import OmegaConf
from tensorboard.compat.proto import summary_pb2
from tensorboard.plugins.hparams import api_pb2, metadata, plugin_data_pb2
from tensorboard.plugins.hparams.summary_v2 import hparams_pb

IMAGE_SIDE = 28  # MNIST images: 784 = 28 × 28 pixels


# ---- hparams --------------------------------------------------------------------------------
def flat_config(cfg) -> dict:
    """The resolved config as ``{"actor.n_hidden": 20, ...}``: nested keys joined by dots, lists
    (e.g. ``trainer.test_noise_levels``) as their JSON text, null as ``"null"``; TensorBoard's
    HParams tab takes only bool, number and string values."""
    flat = {}

    def walk(node, prefix):
        for key, value in node.items():
            name = f"{prefix}{key}"
            if isinstance(value, dict):
                walk(value, name + ".")
            elif isinstance(value, (bool, int, float, str)):
                flat[name] = value
            else:
                flat[name] = json.dumps(value)

    walk(OmegaConf.to_container(cfg, resolve=True), "")
    return flat


def summary_metrics(summary: dict) -> dict:
    """summary.json's headline figures as HParams metrics: ``hparam/<metric>`` (a per-level metric
    as ``hparam/<metric>/<level>``, the name ``optimized_metric`` uses), each the mean over the
    runs of the batch (null values, e.g. no optimal action to score, left out), plus the speed."""
    out = {}

    def add(name, values):
        finite = [v for v in values if v is not None and not math.isnan(v)]
        if finite:
            out[f"hparam/{name}"] = float(np.mean(finite))

    for name, value in summary["metrics"].items():
        if isinstance(value, dict):
            for level, values in value.items():
                add(f"{name}/{level}", values)
        else:
            add(name, value)
    for name in ("agent_steps_per_s", "wall_time_s"):
        out[f"hparam/{name}"] = float(summary[name])
    return out


def _hparams_summary(tag: str, data: plugin_data_pb2.HParamsPluginData) -> summary_pb2.Summary:
    summary = summary_pb2.Summary()
    summary.value.add(tag=tag, metadata=metadata.create_summary_metadata(data), tensor=metadata.NULL_TENSOR)
    return summary


def log_hparams(writer, cfg, summary: dict, step: int) -> None:
    """One HParams session per run, written into the run's own log (``tb/``, what
    ``add_hparams(..., run_name=".")`` does), so that TensorBoard on a sweep directory shows one
    row per Hydra job: the flattened config and the ``hparam/*`` metrics (scalars at ``step``).

    Unlike ``SummaryWriter.add_hparams`` this writes no experiment summary: TensorBoard takes
    the first experiment summary it finds as the whole table's columns, so a sweep over several
    experiments would lose the other jobs' keys and metrics. Without one it builds the columns
    from every job's session (the union of config keys; every scalar tag is a metric column)."""
    metrics = summary_metrics(summary)
    file_writer = writer._get_file_writer()
    start = hparams_pb(flat_config(cfg), start_time_secs=time.time() - summary["wall_time_s"])
    end = plugin_data_pb2.HParamsPluginData(session_end_info=plugin_data_pb2.SessionEndInfo(
        status=api_pb2.STATUS_SUCCESS, end_time_secs=time.time()))
    file_writer.add_summary(start, step)
    for tag, value in metrics.items():
        writer.add_scalar(tag, value, step)
    file_writer.add_summary(_hparams_summary(metadata.SESSION_END_INFO_TAG, end), step)
    writer.flush()


# ---- weights --------------------------------------------------------------------------------
def log_weights(writer, phase: str, module: torch.nn.Module, step: int, skip=("codes",)) -> None:
    """Histograms ``<phase>/weights/<name>`` of run 0's parameters and weight buffers; the
    non-finite entries of a diverged run are left out (none left: no histogram)."""
    for name, value in module.state_dict().items():
        if name not in skip and torch.is_tensor(value) and value.is_floating_point() and value.dim() > 1:
            values = value[0].detach().float().cpu()
            values = values[torch.isfinite(values)]
            if values.numel():
                writer.add_histogram(f"{phase}/weights/{name}", values, step)


# ---- images ---------------------------------------------------------------------------------
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
    x = torch.as_tensor(np.asarray(images, dtype=np.float32)) if not torch.is_tensor(images) \
        else images.detach().float().cpu()
    if x.dim() == 3:
        n_cols = n_cols or math.ceil(math.sqrt(x.shape[0]))
        n_rows = math.ceil(x.shape[0] / n_cols)
        x = torch.cat([x, torch.ones(n_rows * n_cols - x.shape[0], *x.shape[1:])]).view(n_rows, n_cols, *x.shape[1:])
    n_rows, n_cols, h, w = x.shape
    canvas = torch.ones(n_rows * (h + pad) + pad, n_cols * (w + pad) + pad)
    for r in range(n_rows):
        for c in range(n_cols):
            canvas[pad + r * (h + pad):pad + r * (h + pad) + h, pad + c * (w + pad):pad + c * (w + pad) + w] = x[r, c]
    return canvas.unsqueeze(0)


def as_images(flat) -> torch.Tensor:
    """(…, 784) pixel vectors → (…, 28, 28) float32."""
    x = torch.as_tensor(np.asarray(flat, dtype=np.float32)) if not torch.is_tensor(flat) else flat.detach().float().cpu()
    return x.reshape(*x.shape[:-1], IMAGE_SIDE, IMAGE_SIDE)


def matrix_image(M: torch.Tensor, min_side: int = 200) -> torch.Tensor:
    """A matrix (rows, cols) as a grey image (1, H, W) scaled to [0, 1], each entry a square of
    pixels so that small matrices stay visible."""
    m = unit_range(M.detach().float().cpu(), (0, 1))
    k = max(1, math.ceil(min_side / max(m.shape)))
    return m.repeat_interleave(k, 0).repeat_interleave(k, 1).unsqueeze(0)


def log_embedding(writer, tag: str, points, columns: dict, step: int, images=None) -> None:
    """Points (N, D) for TensorBoard's projector, with one metadata column per entry of
    ``columns`` (each N values) and optional (N, 28, 28) thumbnails."""
    points = np.nan_to_num(np.asarray(points, dtype=np.float32), nan=0.0, posinf=0.0, neginf=0.0)
    header = list(columns)
    rows = [[str(columns[h][i]) for h in header] for i in range(len(points))]
    label_img = None if images is None else as_images(np.asarray(images).reshape(len(points), -1)).unsqueeze(1)
    writer.add_embedding(points, metadata=rows, metadata_header=header, label_img=label_img,
                         global_step=step, tag=tag)
