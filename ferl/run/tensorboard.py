"""TensorBoard logging shared by the trainers; the tags are listed in docs/records.md
("TensorBoard tags").

Every tag is ``<phase>/<quantity>`` (``actor/discounted_return_ma200``, ``schedule/beta``);
histograms are ``<phase>/weights/<parameter>``. Nothing here draws a random number or changes a
tensor it is given, so logging never changes what a run computes; weights, images and
embeddings are run 0's, logged once per phase.
"""

import time

import numpy as np
import torch
from omegaconf import OmegaConf
from tensorboard.compat.proto import summary_pb2
from tensorboard.plugins.hparams import api_pb2, metadata, plugin_data_pb2
from tensorboard.plugins.hparams.summary_v2 import hparams_pb

from ferl.images import as_images
from ferl.run.jsonio import strict_dumps
from ferl.stats import flat_metrics, mean_sd


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
                flat[name] = strict_dumps(value)

    walk(OmegaConf.to_container(cfg, resolve=True), "")
    return flat


def summary_metrics(summary: dict) -> dict:
    """summary.json's headline figures as HParams metrics: ``hparam/<metric>`` for every flat
    metric name (``ferl.stats.flat_metrics``, the name ``optimized_metric`` uses), each the mean
    over the runs that have a value, plus the speed."""
    out = {}
    for name, values in flat_metrics(summary["metrics"]).items():
        mean, _, n = mean_sd(values)
        if n:
            out[f"hparam/{name}"] = mean
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
    end = plugin_data_pb2.HParamsPluginData(
        session_end_info=plugin_data_pb2.SessionEndInfo(status=api_pb2.STATUS_SUCCESS, end_time_secs=time.time())
    )
    file_writer.add_summary(start, step)
    for tag, value in metrics.items():
        writer.add_scalar(tag, value, step)
    file_writer.add_summary(_hparams_summary(metadata.SESSION_END_INFO_TAG, end), step)
    writer.flush()


# ---- weights --------------------------------------------------------------------------------
# TensorBoard's histogram buckets end at ±1e20 (``torch.utils.tensorboard.summary.default_bins``):
# values beyond them fall in none, and a histogram of only such values raises "The histogram is empty"
HISTOGRAM_RANGE = 1e20


def log_weights(writer, phase: str, module: torch.nn.Module, step: int, skip=("codes",)) -> None:
    """Histograms ``<phase>/weights/<name>`` of run 0's parameters and weight buffers; the
    non-finite entries of a diverged run, and finite ones beyond TensorBoard's buckets
    (``HISTOGRAM_RANGE``, a run on its way to diverging), are left out (none left: no histogram)."""
    for name, value in module.state_dict().items():
        if name not in skip and torch.is_tensor(value) and value.is_floating_point() and value.dim() > 1:
            values = value[0].detach().float().cpu()
            values = values[values.abs() < HISTOGRAM_RANGE]  # NaN compares false: left out too
            if values.numel():
                writer.add_histogram(f"{phase}/weights/{name}", values, step)


def log_embedding(writer, tag: str, points, columns: dict, step: int, images=None) -> None:
    """Points (N, D) for TensorBoard's projector, with one metadata column per entry of
    ``columns`` (each N values) and optional (N, 28, 28) thumbnails."""
    points = np.nan_to_num(np.asarray(points, dtype=np.float32), nan=0.0, posinf=0.0, neginf=0.0)
    header = list(columns)
    rows = [[str(columns[h][i]) for h in header] for i in range(len(points))]
    label_img = None if images is None else as_images(np.asarray(images).reshape(len(points), -1)).unsqueeze(1)
    writer.add_embedding(points, metadata=rows, metadata_header=header, label_img=label_img, global_step=step, tag=tag)
