"""What every recurrent predictor shares, whatever its memory (§2.4, §4.2, §5.2, §5.4).

A predictor is a memory — Elman (the dissertation), LSTM, GRU or an echo-state reservoir (§5.4's
"memories that last") — with the output heads of ``ferl.predictors.heads`` on top. The config
chooses the memory by name (``predictor.<name>.memory``); ``predictor`` builds the class whose
``kind`` it is, or the class a dotted path names, so a new memory is one module with a
``RecurrentPredictor`` subclass and no list to extend.

All parameters carry the run dimension first. A subclass draws its memory's parameters in
``init_memory`` (before the heads, from the same per-run generators), and provides ``unroll``
(the memories of padded sequences), ``step`` (one online step), ``initial_state``, ``memory``
and the staticmethod ``bptt`` that ``PredictorBatch`` calls for the gradients of a batch.
"""

import importlib
import pkgutil
from typing import Literal

import torch
from torch import nn

from ferl import rng
from ferl.config.params import ArgumentError, NonNegative, NonNegativeInt, Positive, PositiveInt, checked
from ferl.predictors.heads import OutputHeads, RewardOutput, clean, members_heads, valid_steps
from ferl.predictors.popart import RewardStatistics
from ferl.predictors.training import PredictorBatch


def lookup_step(predictor, table: torch.Tensor, n_actions: int):
    """A step on observation ids with the predictor's current weights: the observation rows of
    ``table`` (ids, Y) or (R, ids, Y), the one-hot action, then ``predictor.step``."""
    eye = torch.eye(n_actions, device=table.device)
    runs = torch.arange(table.shape[0], device=table.device) if table.dim() == 3 else None

    @torch.no_grad()
    def step(state, obs_id: torch.Tensor, action: torch.Tensor):
        return predictor.step(state, table[obs_id] if runs is None else table[runs, obs_id], eye[action])

    return step


class RecurrentPredictor(OutputHeads):
    """A memory of ``n_memory`` units and the output heads (``reward_output``: "bits", "linear",
    "none"; ``predict_obs``); ``n_reward`` reward bits, one per reward value of the environment,
    which the job passes (``ferl.trainers.facts``). c_y, c_a scale the previous observation and action into the memory
    (§4.3.3); β_y, β_r the heads' gains and ρ_y, ρ_r their error weights (Eq. 4.6); ``lr`` is α of
    plain SGD on J(T) (``time_average``) or Σ_t E_t, one step per ``batch_size`` sequences;
    ``init_std`` the spread of the Gaussian initial weights (§4.3.1); ``reward_norm`` popart: the
    linear reward head learns each run's standardised reward (``ferl.predictors.popart``)."""

    kind = ""
    uses_beta_m = False  # β_m is the gain of the Elman memory's sigmoid (Eq. 4.3); others keep it 1
    traceable_bptt = False  # True where ``bptt`` is tensor operations only: PredictorBatch.fuse compiles it
    # True where ``sequence_start`` and ``run_steps`` split the memory's unroll into a start and
    # steps that carry a state: then BPTT runs in compiled chunks of a fixed number of steps
    # (``ferl.predictors.training.chunked_bptt``)
    time_chunks = False

    def sequence_start(self, params: list, y: torch.Tensor, a: torch.Tensor) -> tuple:
        """What the memory's steps start from, for padded sequences y (R, B, T+1, Y), a (R, B, T, A)
        under memory parameters ``params``: every step's input (R, B, T, ·), computed at once, the
        state before the first step (R, B, S) and the memory m_0 (R, B, M). Where ``time_chunks``."""
        raise NotImplementedError

    def run_steps(self, params: list, x: torch.Tensor, state: torch.Tensor) -> tuple:
        """The memories after each of the steps of inputs x (R, B, n, ·) from ``state`` (R, B, n, M),
        and the state after the last. Where ``time_chunks``."""
        raise NotImplementedError

    @staticmethod
    def bptt(members: list, memory: list, y, a, rs: list, steps, reward_steps) -> list:
        """The gradients of a batch of predictors of this class (``PredictorBatch``): the memory's
        parameters of every member, then their heads'; the subclass's."""
        raise NotImplementedError

    @checked
    def __init__(
        self,
        n_runs: PositiveInt,
        n_obs: PositiveInt,
        n_actions: PositiveInt,
        n_memory: PositiveInt = 20,
        n_reward: PositiveInt | None = None,
        reward_output: RewardOutput = "bits",
        c_y: NonNegative = 1.0,
        c_a: NonNegative = 1.0,
        beta_m: Positive = 1.0,
        beta_y: Positive = 1.0,
        beta_r: Positive = 1.0,
        rho_y: NonNegative = 1.0,
        rho_r: NonNegative = 1.0,
        lr: Positive = 0.05,
        init_std: NonNegative = 1.0,
        predict_obs: bool = True,
        time_average: bool = False,
        batch_size: PositiveInt = 1,
        seed: NonNegativeInt = 0,
        reward_norm: Literal["none", "popart"] = "none",
    ):
        super().__init__()
        self.c_y, self.c_a, self.beta_m = c_y, c_a, beta_m
        self.lr, self.time_average, self.batch_size = lr, time_average, batch_size
        self.memory_size = n_memory
        # Each run is initialised from its own seed, so run r does not depend on n_runs (§4.3.1:
        # weights and biases from a spherical Gaussian of variance init_std²), memory then heads.
        gens = rng.run_generators(seed, n_runs)

        def gaussian(*shape, std=init_std):
            return nn.Parameter(torch.stack([torch.randn(*shape, generator=g) for g in gens]) * std)

        self.init_memory(gaussian, gens, n_obs, n_actions, n_memory)
        self.init_heads(
            gaussian, n_obs, n_memory, n_reward, reward_output, predict_obs, (beta_y, beta_r), (rho_y, rho_r)
        )
        if reward_norm == "popart":
            self.reward_stats = RewardStatistics(n_runs)

    @classmethod
    def check_config(cls, args: dict) -> None:
        if not args["predict_obs"] and args["reward_output"] == "none":
            raise ArgumentError(
                "reward_output", "bits or linear when predict_obs is false (a predictor needs an output)"
            )
        if not cls.uses_beta_m and args["beta_m"] != 1:
            raise ArgumentError("beta_m", f"1 with memory={cls.kind} (β_m is the gain of the Elman memory's sigmoid)")
        if args["reward_norm"] != "none" and args["reward_output"] != "linear":
            raise ArgumentError("reward_norm", "none unless reward_output=linear (it standardises a scalar reward)")

    def init_memory(self, gaussian, generators: list, n_obs: int, n_actions: int, n_memory: int) -> None:
        """Draw the memory's parameters: ``gaussian(*shape, std=…)`` (R, *shape) per run."""
        raise NotImplementedError

    def describe(self) -> dict:
        return {"kind": self.kind, "memory_size": self.memory_size, **self.describe_heads()}

    def memory_parameters(self) -> list:
        """The memory's trained parameters, in ``parameters()`` order (heads after them)."""
        raise NotImplementedError

    @property
    def gains(self) -> tuple:
        """The memory's scalars besides its parameters (c_y, c_a, …)."""
        return self.c_y, self.c_a

    @property
    def batch_key(self) -> tuple:
        """Predictors with equal keys train as one ``PredictorBatch``: one kind and form of
        memory (sizes, gains) and the same α, objective and batch size."""
        return (
            self.kind,
            self.memory_size,
            tuple(q.shape for q in self.memory_parameters()),
            self.gains,
            self.lr,
            self.time_average,
            self.batch_size,
        )

    @classmethod
    def training_batch(
        cls, members: list, y, a, rs: list, lengths, batch_size: int | None = None, summed: bool = False
    ) -> PredictorBatch:
        return PredictorBatch(members, y, a, rs, lengths, batch_size, summed)

    def frozen_step(self, table: torch.Tensor, n_actions: int):
        return lookup_step(self, table, n_actions)

    def loss(self, y, a, r, lengths) -> torch.Tensor:
        """Σ_t E_t, or J(T) = Σ_t E_t / (T + 1) with ``time_average``, per (run, sequence), (R, B):
        what BPTT differentiates (Eqs. 4.6, 5.1, 5.2). Padded steps are masked."""
        y, a, r = clean(y, a, r, lengths)
        E = self.step_errors(self.unroll(y, a), y, r, lengths)
        return E.sum(-1) / (lengths + 1) if self.time_average else E.sum(-1)

    @torch.no_grad()
    def gradients(self, y, a, r, lengths, weight: torch.Tensor) -> list:
        """∂/∂θ of Σ_b weight_b · Σ_t E_t(b) for every trained parameter (``parameters()`` order),
        as training computes them (the class's ``bptt``). Inputs cleaned; weight (R, B)."""
        steps = valid_steps(lengths, y.shape[2]) * weight.unsqueeze(-1)
        return type(self).bptt(
            [self], self.memory_parameters(), y, a, [r], steps, steps * (torch.arange(y.shape[2], device=y.device) > 0)
        )

    def memory_gradients(self, y, a, dm) -> list:
        """∂/∂θ of Σ dm · m for the memory's parameters θ (``memory_parameters()`` order): the
        memory's part of BPTT from an error dm (R, B, T+1, M) on the memories m_0 … m_T of cleaned
        sequences y (R, B, T+1, Y), a (R, B, T, A) — the chain from what the actor reads to the
        memory's parameters. Through autograd on ``unroll_with(params, y, a)``; a memory whose BPTT
        is written out (Elman) overrides it; one without trained parameters (the echo-state
        reservoir) has none."""
        memory = self.memory_parameters()
        if not memory:
            return []
        with torch.enable_grad():
            leaves = [q.detach().requires_grad_() for q in memory]
            m = self.unroll_with(leaves, y, a)  # type: ignore[operator]  # every memory with trained parameters has one
            return list(torch.autograd.grad((m * dm).sum(), leaves))

    @torch.no_grad()
    def descend_memory(self, y, a, dm) -> None:
        """θ_m ← θ_m − α ∂(Σ dm · m)/∂θ_m (``memory_gradients``), α the predictor's ``lr``."""
        torch._foreach_add_(self.memory_parameters(), self.memory_gradients(y, a, dm), alpha=-self.lr)

    def train_epoch(self, y, a, r, lengths, order: torch.Tensor) -> None:
        """One epoch of pattern-mode SGD (§4.3.1) on this predictor alone (``PredictorBatch``)."""
        PredictorBatch([self], y, a, [r], lengths).train_epoch([order])


def autograd_bptt(members: list, memory: list, y, a, rs: list, steps, reward_steps) -> list:
    """The gradients ``PredictorBatch`` asks for, for a memory whose BPTT is not written out (LSTM,
    GRU, the transformer): members stacked along the run axis (P·R, …) share ``memory`` (their
    memory parameters, concatenated); the loss is Σ steps · E_t of every member's heads. The heads'
    part is written out (``OutputHeads.head_gradients``, Eqs. 2.57–2.62), which also gives ∂J/∂m_t;
    the memory's is the vector-Jacobian product of its ``unroll_with`` with that error
    (``torch.func.vjp``: autograd's chain rule, in a form dynamo traces, so ``PredictorBatch.fuse``
    can compile it). Tests check it against finite differences."""
    lead = members[0]
    m, pull = torch.func.vjp(lambda *params: lead.unroll_with(list(params), y, a), *memory)[:2]  # outer no_grad ignored
    heads, dm = members_heads(members, m, y, rs, steps, reward_steps)
    return list(pull(dm)) + heads


def memory_class(name: str):
    """The predictor class of a memory: the ``RecurrentPredictor`` subclass whose ``kind`` is
    ``name`` (every module of ``ferl.predictors`` is imported to find it), or the class a dotted
    path names (a user's own memory)."""
    if "." in name:
        from ferl.config.params import target

        return target(name)
    import ferl.predictors as package

    for module in pkgutil.iter_modules(package.__path__):
        importlib.import_module(f"{package.__name__}.{module.name}")
    kinds = {}
    stack = list(RecurrentPredictor.__subclasses__())
    while stack:
        cls = stack.pop()
        kinds[cls.kind] = cls
        stack += cls.__subclasses__()
    if name not in kinds:
        raise ArgumentError("memory", f"one of {', '.join(sorted(k for k in kinds if k))} or a class's dotted path")
    return kinds[name]


def predictor(memory: str = "elman", **kwargs) -> RecurrentPredictor:
    """The predictor whose memory is ``memory`` (``predictor.<name>.memory``, docs/architecture.md)."""
    return memory_class(memory)(**kwargs)


# ``check_arguments`` checks the other keys against the chosen class's signature (a function's
# attribute, which ferl.config.params reads)
predictor.resolve = lambda values: (  # type: ignore[attr-defined]
    memory_class(values.get("memory", "elman")),
    {k: v for k, v in values.items() if k != "memory"},
)
