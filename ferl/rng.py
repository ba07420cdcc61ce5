"""The random streams of a batch of runs, and the seed offsets that keep them apart.

Run r of a batch started with ``seed`` is seed + r (``run_seeds``). A component draws run r's
initial parameters from a generator of its own seeded seed + offset + r (``run_generators``), so
that run r does not depend on how many runs share the batch; the offset (``SeedOffsets``) keeps
the actor's, each predictor's, the preprocessor's and the environment's streams apart. A component
that needs a further stream of its own after its weights (the RBM's shuffles and Gibbs samples,
DRQN's replay draws) seeds it with a number drawn from run r's generator (``child_seed``): not a
replay of the numbers that drew the weights, and still independent of n_runs. What the runs draw
while they train (action uniforms, observation noise) comes from one generator of the whole batch
seeded with ``seed`` (``generator``), which checkpoints save and resumes restore.

Every offset is named here. Changing one changes every number a run produces: the golden numbers
(tests/golden/reduced_scale.json) hold them.
"""

from collections.abc import Iterable
from dataclasses import dataclass
from typing import Literal, get_args

import torch


@dataclass(frozen=True)
class SeedOffsets:
    """What is added to the run's seed for each component's initial weights."""

    actor: int = 0
    predictors: int = 10_000  # predictor i: + i × this
    preprocessor: int = 200_000
    env: int = 300_000  # an environment that draws its own task per run (``seed`` in its constructor)
    exploration: int = 400_000  # a directed-exploration method's own draws (``ferl.exploration.counts``' hash)


# Online TD on a continuing task (the digit floor, ch. 3): the actor on seed + r, as the
# reproduction's numbers were measured.
CONTINUING = SeedOffsets()
# Algorithms 1–2 and the online trainer (ch. 4–5): the actor apart from the first predictor's seed + r.
EPISODIC = SeedOffsets(actor=100_000)
# The digit mazes' noisy image copies (§4.3.3): the maze generator's seed + this, so that every
# maze built for a job (the training one, the single-run views of ferl.envs.gym) draws the same.
# (Equal to ``SeedOffsets.env``: a digit maze takes no ``seed``, so the two never meet.)
IMAGE_NOISE = 300_000
# A preprocessor's sampled binary outputs (``RBMPreprocessor``, ``hidden: binary``): run r's
# training seed + this, so that every call draws the same samples.
BINARY_HIDDEN = 500_000
# what a trainer's config calls them (conf/trainer/*.yaml: seed_offsets)
OffsetsName = Literal["episodic", "continuing"]
NAMED_OFFSETS = dict(zip(get_args(OffsetsName), (EPISODIC, CONTINUING)))

SEED_BOUND = 2**62  # child seeds are drawn from [0, SEED_BOUND)


def run_seeds(seed: int, n_runs: int) -> list[int]:
    """The seeds of the batch's runs: seed + r for run r."""
    return [seed + r for r in range(n_runs)]


def generator(seed: int, device: torch.device | str = "cpu") -> torch.Generator:
    """A generator on ``device`` seeded with ``seed``."""
    return torch.Generator(device).manual_seed(seed)


def generators(seeds: Iterable[int], device: torch.device | str = "cpu") -> list[torch.Generator]:
    """One generator per seed, on ``device``."""
    return [generator(s, device) for s in seeds]


def run_generators(seed: int, n_runs: int, device: torch.device | str = "cpu") -> list[torch.Generator]:
    """One generator per run, seeded seed + r, so that run r's initial parameters do not depend
    on how many runs share the batch (``seed`` already holds the component's offset)."""
    return generators(run_seeds(seed, n_runs), device)


def child_seed(parent: torch.Generator) -> int:
    """A seed for a further stream, drawn from ``parent`` (module doc)."""
    return int(torch.randint(SEED_BOUND, (), generator=parent))
