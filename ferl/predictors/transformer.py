"""A transformer memory (``memory: transformer``): a small causal GPT-style transformer over the
episode so far, batched over runs, trained by BPTT through autograd like the gated memories.

The memory reads the same inputs as the others, u_{t−1} = (c_y y_{t−1}, c_a a_{t−1}) (Eq. 4.3),
as tokens: token 0 is the zero input (the episode's start, Memory-RL's "zero-prepend"), token s ≥ 1
carries u_{s−1}. m_t is the output at token t, which attends to tokens 0 … t only (causal):

    x_s = W_in u_{s−1} + b_in + p_s                         (u_{−1} = 0; p_s sinusoidal)
    x ← x + W_o Attn(LN_1(x)) + b_o                         (per layer, causal multi-head attention)
    x ← x + W_2 GELU(W_1 LN_2(x) + b_1) + b_2
    m_t = tanh(LN_f(x_t))

The GPT-2 block (Radford et al. 2019): pre-LN, residual stream of width d_model = N^m, a feed-forward
layer of 4 N^m, a final LN, as Memory-RL's GPT memory (Ni et al. 2023, "When do transformers shine
in RL?", github.com/twni2016/Memory-RL, ``policies/seq_models/gpt2_vanilla.py``) uses. (POPGym's
attention memories, Morad et al. 2023, github.com/proroklab/popgym, ``popgym/baselines/models``,
are linear attention and fast-weight programmers, not this softmax block.) Choices, and why:

* ``layers`` = 1 and ``heads`` = 1 by default, as Memory-RL's ``configs/seq_models/gpt_default.py``:
  recalling one cue needs one attention hop; d_model = N^m, so that the actor's state keeps the
  size the other memories give it.
* Sinusoidal positions (Vaswani et al. 2017), Memory-RL's default: fixed, so that a position first
  reached late in a run (long episodes are rare while the agent explores) is not an untrained
  embedding, and defined at every t.
* Pre-LN (Xiong et al. 2020): trains without warm-up, which plain SGD (the predictors' optimiser,
  §4.3.1) does not have.
* No dropout: the memory is deterministic, so the acting step equals the training unroll.
* tanh on GPT-2's final LN: the actor's state then stays in (−1, 1), as with the gated memories'
  h_t; the LN's output alone (entries of ±3 and more) made the FERL actor's TD error diverge in
  its first episode (|δ| ≈ 1e20 in one of two runs on the regular maze, corridor 3).
* Weights Gaussian with std 1/√fan-in; the residual projections W_o, W_2 also × 1/√(2 · layers)
  (GPT-2's scaling of the residual branches); biases 0, LN gains 1.

``context`` is the number of past steps the memory attends to (tokens 1 … context besides the
start token); null takes the environment's T_max (``max_steps``, which the job passes,
``ferl.trainers.facts``), so that every step of every episode sees the whole episode, as
Memory-RL's context is its episode length. A context shorter than T_max is refused. The online
``step`` keeps the keys and values of every layer for the context + 1 tokens in its state (a cache
of fixed shape, (R, layers, 2, context + 1, N^m), beside [m_t, n] (R, N^m + 1)), so each step attends
over the cache instead of recomputing the episode and gives the same m_t as ``unroll``. A compiled
episode takes the cache's length as a symbol (``generic_state``): one graph serves every T_max. An episode never
outgrows the cache: the environment ends it after T_max ≤ context steps.
"""

import math
from collections import namedtuple
from typing import Annotated, NamedTuple

import torch
import torch.nn.functional as F
from torch import nn

from ferl.compiled import size_generic
from ferl.config.params import Allowed, ArgumentError, Positive, PositiveInt, checked
from ferl.predictors.heads import linear, scaled
from ferl.predictors.recurrent import RecurrentPredictor, autograd_bptt

# the memory's parameters in ``parameters()`` order; those of a layer are stacked (R, layers, …)
Weights = namedtuple("Weights", "W_in b_in ln1_g ln1_b W_qkv b_qkv W_o b_o ln2_g ln2_b W_1 b_1 W_2 b_2 lnf_g lnf_b")
FFN_RATIO = 4  # GPT-2's feed-forward width, 4 d_model

Layers = Annotated[int, Allowed(lambda x: 1 <= x <= 4, "in 1 … 4 (a small memory)")]


def per_run(p: torch.Tensor, x: torch.Tensor) -> torch.Tensor:
    """p (R, D) shaped to add to x (R, …, D)."""
    return p.view(p.shape[0], *(1,) * (x.dim() - 2), p.shape[-1])


def affine(x: torch.Tensor, W: torch.Tensor, b: torch.Tensor) -> torch.Tensor:
    """W x + b per run: x (R, …, I), W (R, O, I), b (R, O)."""
    return linear(x, W) + per_run(b, x)


def layer_norm(x: torch.Tensor, g: torch.Tensor, b: torch.Tensor) -> torch.Tensor:
    """LN(x) = g ⊙ (x − mean)/√(var + 1e−5) + b over the last axis (Ba et al. 2016), g, b (R, D)."""
    return F.layer_norm(x, x.shape[-1:]) * per_run(g, x) + per_run(b, x)


def positions(s: torch.Tensor, d: int) -> torch.Tensor:
    """Sinusoidal encodings p_s (…, d) of positions s (…) (Vaswani et al. 2017, §3.5):
    p_{s,2i} = sin(s / 10000^{2i/d}), p_{s,2i+1} = cos(s / 10000^{2i/d})."""
    freq = torch.exp(torch.arange(0, d, 2, dtype=torch.float64) * (-math.log(10000.0) / d)).to(s.device)
    angle = s.to(torch.float64).unsqueeze(-1) * freq
    return torch.stack([angle.sin(), angle.cos()], -1).flatten(-2)[..., :d]


class Attention(NamedTuple):
    """How a memory attends: ``heads`` heads, and their logits. ``qk_norm`` None: softmax(q kᵀ/√d_h)
    (Vaswani et al. 2017, Eq. 1). ``qk_norm`` g: QK-normalisation (Henry et al. 2020, "Query-key
    normalization for transformers"), softmax(g q̂ k̂ᵀ) with q̂, k̂ each head's query and key scaled
    to unit length, so that no logit passes ±g. Plain SGD on the summed replay losses grew W_qkv
    to norms of 23–237 and the logits to 10⁴–10⁷: attention froze one-hot on one token and the
    cue was never read again (docs/beyond.md, "The transformer memory"); g bounds that."""

    heads: int = 1
    qk_norm: float | None = None


def split_heads(x: torch.Tensor, heads: int) -> torch.Tensor:
    """(…, N, d) → (…, heads, N, d/heads)."""
    return x.unflatten(-1, (heads, -1)).transpose(-2, -3)


def attend(
    q: torch.Tensor, k: torch.Tensor, v: torch.Tensor, allowed: torch.Tensor, attention: Attention
) -> torch.Tensor:
    """softmax(q kᵀ/√d_h + mask) v per head (or QK-normalised, ``Attention``): q (…, Nq, d), k, v
    (…, Nk, d), ``allowed`` broadcast to (…, heads, Nq, Nk), True where a query may see a key
    (Vaswani et al. 2017, Eq. 1) → (…, Nq, d)."""
    q, k, v = (split_heads(z, attention.heads) for z in (q, k, v))
    if attention.qk_norm is None:
        scores = (q @ k.transpose(-1, -2)) / math.sqrt(q.shape[-1])
    else:  # ε keeps the all-zero query of an empty cache slot finite; masked keys are never seen
        q, k = (z / z.norm(dim=-1, keepdim=True).clamp(min=1e-6) for z in (q, k))
        scores = (q @ k.transpose(-1, -2)) * attention.qk_norm
    out = torch.softmax(scores.masked_fill(~allowed, float("-inf")), -1) @ v
    return out.transpose(-2, -3).flatten(-2)


def block(W: Weights, layer: int, x: torch.Tensor, self_attention) -> torch.Tensor:
    """One pre-LN block on x (R, …, d): ``self_attention(q, k, v)`` attends the queries to the keys
    the caller allows (all earlier tokens of a sequence, or the online step's cache)."""
    q, k, v = affine(layer_norm(x, W.ln1_g[:, layer], W.ln1_b[:, layer]), W.W_qkv[:, layer], W.b_qkv[:, layer]).chunk(
        3, -1
    )
    x = x + affine(self_attention(q, k, v), W.W_o[:, layer], W.b_o[:, layer])
    hidden = F.gelu(affine(layer_norm(x, W.ln2_g[:, layer], W.ln2_b[:, layer]), W.W_1[:, layer], W.b_1[:, layer]))
    return x + affine(hidden, W.W_2[:, layer], W.b_2[:, layer])


def initial_std(name: str, shape: tuple, layers: int) -> float:
    """The standard deviation a weight ``name`` (W_in, W_qkv, W_o, W_1, W_2; shape (…, O, I)) is
    drawn with: 1/√fan-in, the residual projections W_o, W_2 also × 1/√(2 · layers) (GPT-2's
    scaling of the residual branches). Biases start at 0, LN gains at 1."""
    return shape[-1] ** -0.5 * ((2 * layers) ** -0.5 if name in ("W_o", "W_2") else 1.0)


def weight_shapes(n_in: int, d_model: int, layers: int) -> dict[str, tuple]:
    """The shapes of ``Weights`` (without the run dimension), in its order, for inputs of ``n_in``
    values; a layer's are stacked (layers, …)."""
    L, M, H = layers, d_model, FFN_RATIO * d_model
    return dict(
        zip(
            Weights._fields,
            [(M, n_in), (M,), (L, M), (L, M), (L, 3 * M, M), (L, 3 * M), (L, M, M), (L, M)]
            + [(L, M), (L, M), (L, H, M), (L, H), (L, M, H), (L, M), (M,), (M,)],
        )
    )


def causal_stack(W: Weights, x: torch.Tensor, attention: Attention) -> torch.Tensor:
    """m = tanh(LN_f(x)) after every block of W on token embeddings x (R, …, N, d) (positions
    added), each token attending to itself and the earlier ones: (R, …, N, d)."""
    causal = torch.ones(x.shape[-2], x.shape[-2], dtype=torch.bool, device=x.device).tril()
    for layer in range(W.W_qkv.shape[1]):
        x = block(W, layer, x, lambda q, k, v: attend(q, k, v, causal, attention))
    return torch.tanh(layer_norm(x, W.lnf_g, W.lnf_b))


def cached_token(W: Weights, attention: Attention, state: tuple, x: torch.Tensor) -> tuple[torch.Tensor, torch.Tensor]:
    """The state after a token whose embedding (without position) is x (R, …, d), from ``state`` =
    (head, cache): head [m, n] (R, …, d + 1), the last output m and the tokens n seen so far; cache
    every layer's keys and values of tokens 0 … tokens − 1, (R, …, layers, 2, tokens, d), zero
    beyond n. The new token is token n: its keys and values are written at n and it attends to
    tokens 0 … n, so a sequence stepped token by token gives ``causal_stack``'s m. The cache's
    length is read from its shape: a compiled step whose cache is generic in it serves every length."""
    head, cache = state
    d, lead, tokens = x.shape[-1], x.shape[:-1], cache.shape[-2]
    n = head[..., d].long()  # (R, …)
    index = torch.arange(tokens, device=head.device)
    slot = (index == n.unsqueeze(-1)).view(*lead, 1, tokens, 1)
    seen = (index <= n.unsqueeze(-1)).view(*lead, 1, 1, tokens)
    x = (x + positions(n, d).to(x.dtype)).unsqueeze(-2)  # (R, …, 1, d)
    kept = []

    def cached_attention(q, k, v):
        kv = torch.where(slot, torch.stack([k, v], -3), cache[..., layer, :, :, :])  # (R, …, 2, tokens, d)
        kept.append(kv)
        return attend(q, kv[..., 0, :, :], kv[..., 1, :, :], seen, attention)

    for layer in range(W.W_qkv.shape[1]):
        x = block(W, layer, x, cached_attention)
    m = torch.tanh(layer_norm(x.squeeze(-2), W.lnf_g, W.lnf_b))
    return torch.cat([m, (n + 1).unsqueeze(-1).to(m.dtype)], -1), torch.stack(kept, -4)


class TransformerPredictor(RecurrentPredictor):
    """``memory: transformer`` (see the module docstring): ``context`` past steps (null: the
    environment's T_max, ``max_steps``), ``layers`` blocks of ``heads`` heads, d_model = n_memory,
    ``qk_norm`` the logits' bound g (``Attention``; null: none); the other arguments are
    ``RecurrentPredictor``'s."""

    kind = "transformer"
    W_in: torch.Tensor  # the memory's parameters (R, …), set by ``init_memory`` as ``weight_shapes`` names them
    b_in: torch.Tensor

    @checked
    def __init__(
        self,
        context: PositiveInt | None = None,
        layers: Layers = 1,
        heads: PositiveInt = 1,
        qk_norm: Positive | None = None,
        max_steps: PositiveInt | None = None,
        **kwargs,
    ):
        if context is None:
            if max_steps is None:
                raise ValueError("context is needed where no environment gives T_max (max_steps)")
            context = max_steps
        self.context: int = context
        self.layers, self.attention = layers, Attention(heads, qk_norm)
        super().__init__(**kwargs)

    @classmethod
    def check_config(cls, args: dict) -> None:
        super().check_config(args)
        if args["n_memory"] % args["heads"]:
            raise ArgumentError("heads", f"a divisor of n_memory={args['n_memory']} (d_model = n_memory)")
        if args["context"] is not None and args["max_steps"] is not None and args["context"] < args["max_steps"]:
            raise ArgumentError(
                "context",
                f"≥ {args['max_steps']}, the environment's T_max (env.max_steps): "
                "the memory attends to the whole episode",
            )

    def init_memory(self, gaussian, generators: list, n_obs: int, n_actions: int, n_memory: int) -> None:
        R, L = len(generators), self.layers
        for name, shape in weight_shapes(n_obs + n_actions, n_memory, L).items():
            if name.startswith("W_"):
                value = gaussian(*shape, std=initial_std(name, shape, L))
            else:  # LN gains 1, biases 0
                value = nn.Parameter((torch.ones if name.endswith("_g") else torch.zeros)(R, *shape))
            setattr(self, name, value)

    def memory_parameters(self) -> list:
        return [getattr(self, name) for name in Weights._fields]

    @property
    def gains(self) -> tuple:
        """(c_y, c_a, attention): what the memory takes besides its parameters (the attention: not in their shapes)."""
        return self.c_y, self.c_a, self.attention

    def describe(self) -> dict:
        return {**super().describe(), "context": self.context, "layers": self.layers, **self.attention._asdict()}

    def inputs(self, y: torch.Tensor, a: torch.Tensor) -> torch.Tensor:
        return torch.cat([scaled(y, self.c_y), scaled(a, self.c_a)], -1)

    # ---- sequences ----------------------------------------------------------------------------
    def unroll_with(self, params: list, y: torch.Tensor, a: torch.Tensor) -> torch.Tensor:
        """m_0 … m_T (R, B, T+1, M) of padded sequences y (R, B, T+1, Y), a (R, B, T, A) under memory
        parameters ``params``: every token at once, each attending to itself and the earlier ones.
        Padding after a sequence's end is never attended to by its steps."""
        T = a.shape[2]
        if T > self.context:
            raise ValueError(f"context={self.context} is shorter than the sequences' {T} steps")
        W = Weights(*params)
        u = F.pad(self.inputs(y[:, :, :-1], a), (0, 0, 1, 0))  # (R, B, T+1, Y+A): token 0 = the zero input
        x = affine(u, W.W_in, W.b_in) + positions(torch.arange(T + 1, device=y.device), self.memory_size).to(y.dtype)
        return causal_stack(W, x, self.attention)

    def unroll(self, y: torch.Tensor, a: torch.Tensor) -> torch.Tensor:
        return self.unroll_with(self.memory_parameters(), y, a)

    traceable_bptt = True  # autograd_bptt is tensor operations and torch.func: PredictorBatch.fuse compiles it
    bptt = staticmethod(autograd_bptt)

    # ---- online API: a cache of keys and values ---------------------------------------------------
    def token(self, state: tuple, x: torch.Tensor) -> tuple[torch.Tensor, torch.Tensor]:
        """The state after the token whose embedding (without position) is x (R, M): the state
        ([m_t, n], cache) holds m_t (R, M), the tokens n seen so far (R, 1) and every layer's keys
        and values of tokens 0 … context, (R, layers, 2, context + 1, M), zero beyond n
        (``cached_token``)."""
        return cached_token(Weights(*self.memory_parameters()), self.attention, state, x)

    @torch.no_grad()
    def initial_state(self) -> tuple[torch.Tensor, torch.Tensor]:
        """After token 0 (the zero input): [m_0, n = 1] and its keys and values."""
        R, M = self.W_in.shape[0], self.memory_size
        empty = self.W_in.new_zeros(R, M + 1), self.W_in.new_zeros(R, self.layers, 2, self.context + 1, M)
        return self.token(empty, self.b_in)

    def generic_state(self, state) -> tuple:
        """The cache's length, context + 1 (T_max + 1 by default), generic (``size_generic``)."""
        return state[0], size_generic(state[1], 3, 4)

    def memory(self, state: tuple) -> torch.Tensor:
        """m_t, (R, M): what the heads and the actor see."""
        return state[0][:, : self.memory_size]

    @torch.no_grad()
    def step(self, state: tuple, y_prev: torch.Tensor, a_prev: torch.Tensor) -> tuple:
        """The state after y_{t−1} (R, Y) and one-hot a_{t−1} (R, A): token t."""
        return self.token(state, affine(self.inputs(y_prev, a_prev), self.W_in, self.b_in))
