"""The actor's state at the probe visits (``probe.npz`` ``state``), rebuilt from each visit's
observation id and memories (``ActorEpisodes.visit_states``), against the state the episode itself
computed: a table shared by the runs (the digit maze's 784 pixels), one per run (the pixel
maze's processed observations), and the online trainer's episodes."""

import pytest
import torch
from hydra.utils import instantiate
from omegaconf import open_dict

from conftest import compose_config


def actor_phase(*overrides):
    """The actor phase of the composed config, eager, on its set-up job (untrained predictors:
    their memories are what they are, which is all the check needs)."""
    cfg = compose_config([*overrides, "n_runs=3", "compile=false"])
    with open_dict(cfg):
        del cfg["hydra"]
    trainer = instantiate(cfg.trainer)
    trainer.setup(cfg, torch.device("cpu"))
    return trainer.job, trainer.phases[-1]


@pytest.mark.parametrize(
    "experiment", ["table4_2_digit", "table5_1_pixel", "table4_1_matching trainer=online"], ids=lambda x: x.split()[0]
)
def test_rebuilt_visit_states_are_the_episodes_states(experiment):
    first, *others = experiment.split()
    job, phase = actor_phase(f"experiment={first}", *others)
    if first == "table5_1_pixel":  # the preprocessor's output: a processed table per run
        ids = job.env.observation_table.shape[0]
        width = job.preprocessor.output_size
        job.outputs.observations = torch.rand(job.R, ids, width, generator=torch.Generator().manual_seed(0))
    phase.prepare(job)
    phase.freeze(job)
    assert (phase.obs_offsets is not None) == (first == "table5_1_pixel")
    checked = 0
    for k in range(30):  # β = 0: random walks, most of which pass the junction
        played = phase.play_episode(job, k, job.actor.learning_rate(0.0), 0.0)
        visits = played["probes"]
        if visits is None:
            continue
        want = played["states"][visits["step"], visits["run"]].half()
        rebuilt = phase.visit_states(job, visits)
        assert "observation" not in rebuilt and list(rebuilt).index("state") == list(visits).index("observation")
        assert torch.equal(rebuilt["state"], want)
        assert phase.visit_states(job, rebuilt) is rebuilt  # visits that hold their states stay
        checked += len(want)
    assert checked >= 10
