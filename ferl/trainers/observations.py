"""What the agent observes in episodic tasks with finite observation sets (chapters 4–5): the
preprocessor's fit (Algorithm 2, §5.3.2) and the observations as TensorBoard images."""

import numpy as np
import torch

from ferl.config.params import ConfigError
from ferl.images import IMAGE_SIDE, as_images, matrix_image, tile
from ferl.interfaces import FitStopped
from ferl.run.tensorboard import log_weights
from ferl.trainers.phased import Phase


class FitPreprocessor(Phase):
    """Algorithm 2's first phase (§5.3.2): the preprocessor learns from the training images, then
    processes the table of every observation, per run: what the predictors and the actor see
    from now on (``job.outputs.observations``). Records ``preprocessor.npz``."""

    name = "preprocessor"

    def applies(self, job) -> bool:
        return job.preprocessor is not None

    def prepare(self, job) -> None:
        if job.env.discovers_observations:
            raise ConfigError(
                f"preprocessor: it processes the table of every observation once, and {job.env.task} "
                f"environments discover their observations as they run: use ~preprocessor"
            )

    def run(self, job, state) -> None:
        """The fit; where the preprocessor can stop between sweeps, a stop request checkpoints the
        fit so far (``{"fit": FitStopped.state}``), which ``resume`` continues exactly."""
        pre = job.preprocessor
        if pre.stoppable_fit:
            try:
                records = pre.fit(job.data, job.writer, stop=lambda: job.stop.requested, resume=state and state["fit"])
            except FitStopped as e:
                job.checkpoint(self.name, {"fit": e.state})  # a stop was requested: this exits
                raise
        else:
            records = pre.fit(job.data, job.writer)
        log_weights(job.writer, "preprocessor", pre, records["reconstruction_error"].shape[1])
        raw = job.env.observation_table
        with torch.no_grad():
            job.outputs.observations = processed = pre.transform(raw)
        job.run.save_records(
            "preprocessor",
            job.R,
            **records,
            raw_observations=raw.cpu().numpy().astype(np.float16),
            processed_observations=processed.cpu().numpy().astype(np.float16),
        )


def log_observations(job) -> None:
    """What the agent observes: up to 8 images of every observation's reservoir (one row per
    observation of the environment's table), or the table of bit codes itself."""
    if job.env.discovers_observations:
        return  # none seen yet
    table, names = job.env.observation_table.float().cpu(), job.env.observation_names
    if table.shape[1] == IMAGE_SIDE**2:
        per_name = table.view(len(names), -1, table.shape[1])
        job.writer.add_image("env/observations", tile(as_images(per_name[:, :8])), 0)
    else:
        job.writer.add_image("env/observations", matrix_image(table), 0)
