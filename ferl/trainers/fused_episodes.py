"""The actor phase's episodes on the fast path (``ferl.compiled``; docs/performance.md, "Graphs of
fixed size"): ``ActorEpisodes.episode``'s steps in compiled graphs of a few steps.

An episode is the first action (eager: one step an episode, ``ActorEpisodes.first``) and
n = ⌈T_max / K⌉ calls of one graph of ⌈T_max / n⌉ ≤ K steps (K = ``EPISODE_CHUNK_STEPS``)
(``ActorEpisodes.steps``), the ``Carry`` handed from call to call; what the environment and the
actor keep in place (positions, the recurrent Q-learner's memory, the weights the TD steps move) is
written back by each graph as it returns. The graph's size does not grow with T_max, so neither
does its compile time. Every call plays all its steps, the runs whose episode has ended masked
(δ = 0, their parameters kept), as the eager reference does once every run has ended; the steps
past T_max, which the last call pads with (every run has ended by then), are dropped. The eager ``ActorEpisodes.episode`` is the reference
(tests/test_fast_path.py: the same actions, values within float32 rounding, at T_max of 11, 51
and 201).
"""

import torch

from ferl import compiled as fast
from ferl.compiled import chunk_count, compiled, size_generic
from ferl.trainers.episodes import Step, played


class FusedEpisodes:
    """The compiled chunk of steps of ``phase`` (an ``ActorEpisodes``) for ``job``'s episodes of
    T_max steps, and the discounts and draws padded to whole chunks."""

    def __init__(self, phase, job):
        T_max = job.env.max_steps
        # chunks of EPISODE_CHUNK_STEPS steps whatever T_max (T_max = 9 plays 3 × 4 steps, the
        # last 3 padded): the graph is then the same for every T_max, and with the environment's
        # tables generic in their sizes (``tables_generic``), for every corridor of a maze
        self.T_max, self.chunk = T_max, min(T_max, fast.EPISODE_CHUNK_STEPS)
        self.n_chunks = chunk_count(T_max, self.chunk)
        self.pad = self.n_chunks * self.chunk - T_max
        job.env.tables_generic(lambda table: size_generic(table, 0))
        # each chunk's discounts γ^t, the same in every episode: sliced once, each its own tensor
        # (storage offset 0, as every call's inputs are)
        discounts = torch.cat([phase.discount_table, phase.discount_table.new_zeros(self.pad)])
        self.discounts = [part.clone() for part in discounts.split(self.chunk)]
        what = f"a chunk of {self.chunk} steps of an episode"
        self.steps = compiled(phase.steps, job.device, what, generic=as_marked)

    def play(self, phase, job, lr: float, beta, uniform: torch.Tensor) -> dict:
        """``phase.episode(job, lr, beta, uniform, False)`` in chunks: α and β as tensors, so that
        one graph serves every episode; ``uniform`` (T_max + 1, R, 1, ·) padded with zeros for the
        steps past T_max (the draws of runs that have ended choose nothing that is kept)."""
        lr_t = torch.tensor(lr, device=job.device)
        beta_t = as_beta(beta, job.device)
        draws = torch.cat([uniform[1:], uniform.new_zeros(self.pad, *uniform.shape[1:])])
        obs = [job.env.obs_id.unsqueeze(0)]
        carry = phase.first(job, beta_t, uniform[0])  # once an episode: eager (a graph would cost its compiling)
        predictors = list(job.predictors.values())
        parts = []
        for c, discounts in enumerate(self.discounts):
            at = slice(c * self.chunk, (c + 1) * self.chunk)
            # states sized by the configuration (a transformer's cache), generic at every call:
            # dynamo keys a graph on whether an input's sizes were marked
            carry = carry._replace(m=[p.generic_state(x) for p, x in zip(predictors, carry.m)])
            carry, steps, after = self.steps(job, carry, lr_t, beta_t, draws[at].clone(), discounts, False)
            parts.append(steps)
            obs.append(after)
        ep = joined(parts, self.T_max)
        return played(job.env, carry, ep, torch.cat(obs)[: self.T_max + 1])


def joined(parts: list[Step], steps: int) -> Step:
    """The chunks' ``Step``s (n, R, …) as one of their first ``steps`` steps."""
    return Step._make(
        tuple(torch.cat(m)[:steps] for m in zip(*field)) if isinstance(field[0], tuple) else torch.cat(field)[:steps]
        for field in zip(*parts)
    )


def as_beta(beta, device: torch.device) -> torch.Tensor:
    """β (a number, or per run (R, 1, 1)) as a float32 tensor: the form in which one compiled graph serves every episode."""
    return torch.as_tensor(beta, dtype=torch.float32, device=device)


def as_marked(args: tuple) -> tuple:
    """The chunk's arguments as they are: what is generic in them (the environment's tables) was
    marked once (``tables_generic``); every other size stays a constant of the graph."""
    return args
