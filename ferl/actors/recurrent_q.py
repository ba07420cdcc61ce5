"""The recurrent Q-learner (``actor=recurrent_q predictor=none``; docs/beyond.md): a recurrent core
(``actor.memory``: ``ferl.actors.recurrent_cores``) reads the (processed) observation and the
previous action, a value head (``actor.head``: ``ferl.actors.q_heads``) gives Q of every action:

    x_t = (s_t, onehot(a_{t−1})),   h_t = core(x_t, h_{t−1}), h_{−1} = 0,   Q(h_t, ·) = head(h_t)

With ``memory=gru head=linear`` it is DRQN (Hausknecht & Stone 2015, "Deep recurrent Q-learning
for partially observable MDPs"; ``actor=drqn``); with ``head=free_energy`` it is the dissertation's
RBM value Q = −F (Eqs. 2.21–2.22, 3.1) on a memory learnt for reward rather than by prediction.
It acts by the same softmax / β schedule (Eq. 3.11) as the FERL actor, stepping the core with
every ``act``. It learns from replayed whole episodes (the "bootstrapped sequential updates" of
§4 of the DRQN paper): after every episode, ``updates_per_episode`` Adam steps on
``batch_episodes`` episodes per run drawn from its last ``replay_episodes``, each unrolled from
the zero state by back-propagation through time (autograd, through head and core) on

    L = mean_t ℓ(Q(h_t, a_t) − y_t),   y_t = r_{t+1} + γ (1 − terminal) max_a Q⁻(h_{t+1}, a)

with ℓ the Huber loss (δ = 1, DRQN's) or, with ``td_loss: squared``, ℓ(e) = e²/2, the two equal
for |e| ≤ 1 (``TD_LOSSES``); Q⁻ a target network copied every ``target_every`` episodes (Mnih et al. 2015); the mean runs
over each run's valid steps, so padding after an episode's end changes nothing. Runs are
independent: the loss is summed over runs, Adam is elementwise, and each run replays its own
episodes, drawn for every run at once from the actor's generator, never from the trainer's (so
the lockstep episodes' pre-drawn streams stay as they are).
"""

import math
from collections.abc import Callable
from typing import Literal

import torch
from torch.nn import functional as nnf

from ferl import rng
from ferl.actors.q_heads import head as make_head
from ferl.actors.recurrent_cores import CORES
from ferl.actors.recurrent_q_fast import ADAM_BETAS, ADAM_EPS, adam_scalars, adam_update, replay_step
from ferl.actors.softmax import SoftmaxActor, TDRule
from ferl.compiled import compiled, first_call_compiles, in_chunks
from ferl.config.params import ArgumentError, NonNegative, NonNegativeInt, Positive, PositiveInt, checked
from ferl.interfaces import EndedEpisode
from ferl.predictors.transformer import Layers
from ferl.replay import draw_episodes, filled, new_replay, refilled, store_episode, stored_episodes

HeadName = Literal["linear", "free_energy", "scaled_free_energy", "expected_energy"]  # q_heads.head's names
MemoryName = Literal["gru", "lstm", "elman", "esn", "transformer"]  # recurrent_cores.CORES' names
ATTENTION_KEYS = {
    "context": None,
    "layers": 1,
    "heads": 1,
    "qk_norm": None,
}  # the transformer's keys and their defaults
TDLoss = Literal["huber", "squared"]
# ℓ(Q(h_t, a_t), y_t) elementwise. Huber's gradient is clipped at |e| = 1: with goal rewards of ±5
# its loss cannot tell Q = 4 from Q = −4 in the goal's direction, and action biases shared with
# the wall bumps' −1 drag Q(goal) down (docs/beyond.md, "The TD loss"); the squared loss's is e.
TD_LOSSES = {
    "huber": lambda q, y: nnf.huber_loss(q, y, reduction="none"),
    "squared": lambda q, y: 0.5 * (q - y).square(),
}


class RecurrentQActor(SoftmaxActor):
    """The recurrent Q-learner: a core over (observation, previous action) and a value head,
    acting by the FERL actor's softmax (Eq. 3.11) and learning from replayed whole episodes by
    BPTT on the TD loss (Huber or squared) with a target network (module docstring)."""

    learns_from_episodes = True  # nothing per step; its memory steps in place with every act
    # the core's trained weights (R, ·), then the head's (``names``); their Adam moments and target
    # copies are buffers named with _m, _v, _target, read through ``params``; the core's fixed
    # weights (an echo-state reservoir) are buffers of their own (``fixed_names``)
    h: torch.Tensor  # (R, 1, state size) the core's state
    a_prev: torch.Tensor  # (R, 1, nA) the previous action, one-hot
    replay: dict[str, torch.Tensor] | None

    @checked
    def __init__(
        self,
        *,
        n_hidden: PositiveInt,
        head: HeadName = "linear",
        memory: MemoryName = "gru",
        head_hidden: PositiveInt = 20,
        q_scale: Positive | None = None,
        replay_episodes: PositiveInt = 1000,
        batch_episodes: PositiveInt = 16,
        updates_per_episode: NonNegativeInt = 1,
        target_every: PositiveInt = 100,
        td_rule: TDRule = "q",
        init_std: NonNegative | None = None,
        head_init_std: NonNegative | None = None,
        td_loss: TDLoss = "huber",
        context: PositiveInt | None = None,
        layers: Layers = 1,
        heads: PositiveInt = 1,
        qk_norm: Positive | None = None,
        max_steps: PositiveInt | None = None,
        **softmax,
    ):
        """``softmax``: the sizes, γ, schedules and seed every softmax actor takes (``SoftmaxActor``);
        the TD rule is Q-learning's unless given. ``head_init_std``: the head's weights drawn
        N(0, std²) of their own, the RBM head's action offsets then exact (``EnergyHead.adjust``);
        ``td_loss``: ℓ of the module docstring. ``context``, ``layers``, ``heads``, ``qk_norm``: the transformer
        core's (``check_config``); ``max_steps``: the environment's T_max, which the job passes."""
        super().__init__(td_rule=td_rule, **softmax)
        n_runs, n_state, n_actions = self.sizes
        self.n_hidden, self.n_actions = n_hidden, n_actions
        self.replay_episodes, self.batch_episodes = replay_episodes, batch_episodes
        self.updates_per_episode, self.target_every = updates_per_episode, target_every
        self.td_loss = td_loss
        attention = {}
        if memory == "transformer":
            if context is None:
                if max_steps is None:
                    raise ValueError("context is needed where no environment gives T_max (max_steps)")
                context = max_steps + 1
            attention = {"context": context, "layers": layers, "heads": heads, "qk_norm": qk_norm}
        self.core = CORES[memory](n_state + n_actions, n_hidden, **attention)
        self.head = make_head(head, n_hidden, n_actions, head_hidden, q_scale)
        shapes = {**self.core.shapes(), **self.head.shapes()}
        self.names = tuple(shapes)
        # U(−1/√H, 1/√H) (PyTorch's recurrent-cell initialisation) unless init_std (the head's:
        # head_init_std) is given, per run from seed + r, parameter by parameter in the order of ``shapes``
        generators = self.run_generators()
        bound = 1 / math.sqrt(n_hidden)
        drawn = {}
        for name, shape in shapes.items():
            std = head_init_std if head_init_std is not None and name in self.head.shapes() else init_std
            draws = [
                torch.rand(shape, generator=g) * 2 * bound - bound
                if std is None
                else torch.randn(shape, generator=g) * std
                for g in generators
            ]
            drawn[name] = torch.stack(draws)
        self.core.adjust(drawn)
        self.head.adjust(drawn, exact=head_init_std is not None)
        fixed = self.core.fixed(generators)
        self.fixed_names = tuple(fixed)
        for name, value in {**drawn, **fixed}.items():
            self.register_buffer(name, value)
        for name in self.names:  # Adam's moments and the target network
            self.register_buffer(f"{name}_m", torch.zeros_like(getattr(self, name)))
            self.register_buffer(f"{name}_v", torch.zeros_like(getattr(self, name)))
            self.register_buffer(f"{name}_target", getattr(self, name).clone())
        self.register_buffer("h", torch.zeros(n_runs, 1, self.core.state_size))
        self.register_buffer("a_prev", torch.zeros(n_runs, 1, n_actions))
        # the replay's draws for every run at once, from a seed that run 0's stream gives
        self.generator = rng.generator(rng.child_seed(generators[0]))
        self.replay = None  # allocated by the first episode, whose length fixes T_max
        self.episodes = self.adam_steps = 0
        # the fast path (compile_updates): the compiled chunk of the core's unroll, the loss, the
        # Adam update; with fast_update None the replay steps are ``adam_step``'s
        self.chunk: Callable | None = None
        self.fast_update: Callable | None = None
        self.replay_loss = self.loss

    def compile_updates(self, device: torch.device) -> None:
        """On the fast path the replay steps (``replay_step``) run through graphs of a fixed size:
        a recurrent core's unroll in chunks (``unroll_chunk``), the transformer's whole loss (no
        loop over time), and the Adam update (``ferl.actors.recurrent_q_fast``)."""
        if self.core.parallel:
            self.replay_loss = compiled(self.loss, device, "the replay's TD loss")
        else:
            self.chunk = compiled(self.unroll_chunk, device, "a chunk of the replay's BPTT")
        adam = compiled(adam_update, device, "an Adam step")
        self.fast_update = first_call_compiles(
            lambda actor, index, step_size, root: replay_step(actor, index, step_size, root, adam)
        )

    @classmethod
    def check_config(cls, args: dict) -> None:
        """The transformer's keys: ``context`` ≥ T_max + 1 (every state s_0 … s_T_max of an episode
        is a token), ``heads`` dividing d_model = ``n_hidden``; refused with any other memory."""
        super().check_config(args)
        if args["memory"] != "transformer":
            for key, default in ATTENTION_KEYS.items():
                if args[key] != default:
                    raise ArgumentError(
                        key, f"only with memory=transformer (leave it out with memory={args['memory']})"
                    )
            return
        if args["n_hidden"] % args["heads"]:
            raise ArgumentError("heads", f"a divisor of n_hidden={args['n_hidden']} (d_model = n_hidden)")
        context, max_steps = args["context"], args["max_steps"]
        if context is not None and max_steps is not None and context < max_steps + 1:
            raise ArgumentError(
                "context",
                f"≥ {max_steps + 1}, the environment's T_max + 1 (env.max_steps + 1): "
                "the core attends to every state s_0 … s_T_max of an episode",
            )

    @property
    def n_runs(self) -> int:
        return self.a_prev.shape[0]

    def params(self, suffix: str = "") -> dict:
        """The trained parameters (their ``suffix`` copies: ``_target``) and the fixed weights."""
        return {
            **{name: getattr(self, name + suffix) for name in self.names},
            **{name: getattr(self, name) for name in self.fixed_names},
        }

    def describe(self) -> dict:
        """What the records keep; the kind is ``drqn`` for its GRU and linear head (``actor=drqn``)."""
        drqn = self.core.name == "gru" and self.head.name == "linear"
        return {
            "kind": "drqn" if drqn else "recurrent_q",
            "memory": self.core.name,
            **self.core.describe(),
            **self.head.describe(),
            "n_hidden": self.n_hidden,
            "gamma": self.gamma,
            "td_rule": self.td_rule,
            "replay_episodes": self.replay_episodes,
            "batch_episodes": self.batch_episodes,
            "updates_per_episode": self.updates_per_episode,
            "target_every": self.target_every,
            "td_loss": self.td_loss,
        }

    def state_weights(self) -> torch.Tensor:
        """The observation's weights into the core (R, S, G·H)."""
        W = self.core.input_weights(self.params())
        return W[:, : W.shape[1] - self.n_actions]

    def hidden(self, h: torch.Tensor) -> torch.Tensor:
        return self.core.hidden(h)

    def unroll(self, p: dict, states: torch.Tensor, prev_actions: torch.Tensor) -> torch.Tensor:
        """Q of every step of episodes: states (R, B, T+1, S), prev_actions one-hot (R, B, T+1, nA)
        (zeros at t = 0) → (R, B, T+1, nA), from the zero state."""
        return self.core.unroll(p, torch.cat([states, prev_actions], -1), lambda h: self.head.q(p, h))

    def unroll_pair(self, p: dict, p_target: dict, states: torch.Tensor, prev_actions: torch.Tensor):
        """``unroll`` under the online parameters p and, without gradient, under the target
        network's: (Q, Q⁻), each (R, B, T+1, nA). On the fast path both run in the same compiled
        chunks of steps (``unroll_chunk``), each carrying its own state."""
        if self.chunk is None:
            q = self.unroll(p, states, prev_actions)
            with torch.no_grad():
                return q, self.unroll(p_target, states, prev_actions)
        x = torch.cat([states, prev_actions], -1)
        zero = self.core.zero_state(x)
        # the later chunks' online states require grad: so does the first's, or it would be a second graph
        states_in = (zero.clone().requires_grad_(torch.is_grad_enabled()), zero)
        chunk = self.chunk
        return in_chunks(lambda x_chunk, state: chunk(p, p_target, x_chunk, state), x, states_in)

    def unroll_chunk(self, p: dict, p_target: dict, x: torch.Tensor, state: tuple) -> tuple[tuple, tuple]:
        """``unroll_pair``'s steps of inputs x (R, B, n, X) from the online and the target network's
        ``state`` (each (R, B, state size)): (Q, Q⁻) of every step and the two states after them, a
        fixed number of steps at a time on the fast path."""
        q, online = self.core.run(p, x, state[0], lambda h: self.head.q(p, h))
        with torch.no_grad():
            q_target, target = self.core.run(p_target, x, state[1], lambda h: self.head.q(p_target, h))
        return (q, q_target), (online, target)

    @torch.no_grad()
    def evaluate(self, s: torch.Tensor):
        """F = −Q (R, B, nA) at the present memory, stepped on s (R, B, S) by the previous
        action; the core's state broadcast over the actions as the cache. Only ``act`` moves
        the memory on."""
        p = self.params()
        x = torch.cat([s, self.a_prev.expand(-1, s.shape[1], -1)], -1)
        h = self.core.step(p, x, self.h.expand(-1, s.shape[1], -1))
        return -self.head.q(p, self.core.hidden(h)), h.unsqueeze(2).expand(-1, -1, self.n_actions, -1)

    def act(self, s: torch.Tensor, beta: float, generator: torch.Generator, uniform: torch.Tensor | None = None):
        """``SoftmaxActor.act`` at s (R, 1, S), then the memory steps: h ← core((s, a_{t−1}), h)
        and a_{t−1} ← the action drawn."""
        a, F_a, h, F_boot = super().act(s, beta, generator, uniform)
        self.h.copy_(h)
        self.a_prev.copy_(nnf.one_hot(a, self.n_actions).to(self.a_prev.dtype))
        return a, F_a, h, F_boot

    @torch.no_grad()
    def retake(self, a: torch.Tensor) -> tuple[torch.Tensor, torch.Tensor]:
        """The action taken at the last ``act`` was a (R, 1) (a directed exploration's,
        ``ferl.exploration.RetakesAction``): h_t does not depend on it, a_{t−1} of the next step
        does. Returns F(s_t, a) = −Q(h_t, a) (R, 1) and the cache h_t (R, 1, state size)."""
        self.a_prev.copy_(nnf.one_hot(a, self.n_actions).to(self.a_prev.dtype))
        F = -self.head.q(self.params(), self.core.hidden(self.h))  # (R, 1, nA)
        return F.gather(2, a.unsqueeze(2)).squeeze(2), self.h.clone()

    def end_episode(self, episode: EndedEpisode, lr: float) -> None:
        """Store every run's episode (``EndedEpisode.padded``: states (R, T_max+1, S), actions and
        rewards (R, T_max) padded after ``lengths`` (R,) actions, ``terminated`` (R,)), take the
        Adam steps on replayed episodes at step size ``lr``, and forget the episode: h = 0 and no
        previous action in every run. Nothing is learnt per step (``ActorBase.learn``)."""
        states, actions, rewards, lengths, terminated = episode.padded()
        stored = {
            "states": states,
            "actions": actions,
            "rewards": rewards,
            "lengths": lengths,
            "terminated": terminated,
        }
        if self.replay is None:
            self.replay = new_replay(stored, self.replay_episodes)
        store_episode(self.replay, self.episodes, stored)
        self.episodes += 1
        for _ in range(self.updates_per_episode):
            if self.fast_update is None:
                self.adam_step(self.sample(), lr)
            else:
                self.adam_steps += 1
                self.fast_update(self, self.draw(), *adam_scalars(lr, self.adam_steps, self.a_prev.device))
        if self.episodes % self.target_every == 0:
            for name in self.names:
                getattr(self, f"{name}_target").copy_(getattr(self, name))
        self.h.zero_()
        self.a_prev.zero_()

    def draw(self) -> torch.Tensor:
        """The slots (R, ``batch_episodes``) of the episodes a step replays: uniform with
        replacement over the stored ones, every run's in one draw."""
        assert self.replay is not None  # end_episode has stored one
        return draw_episodes(self.replay, self.episodes, self.batch_episodes, self.generator).to(self.a_prev.device)

    def sample(self) -> dict:
        """``batch_episodes`` stored episodes per run (``draw``), every field (R, B, …)."""
        assert self.replay is not None
        return stored_episodes(self.replay, self.draw())

    def loss(self, p: dict, batch: dict) -> torch.Tensor:
        """Σ over runs of the mean TD loss ℓ of the module docstring over the batch's steps."""
        states, actions, rewards = batch["states"], batch["actions"], batch["rewards"]
        T = actions.shape[-1]
        onehot = nnf.one_hot(actions, self.n_actions).to(states.dtype)  # (R, B, T, nA)
        prev = torch.cat([torch.zeros_like(onehot[:, :, :1]), onehot], 2)  # a_{t−1}, (R, B, T+1, nA)
        q, q_target = self.unroll_pair(p, self.params("_target"), states, prev)  # (R, B, T+1, nA) each
        with torch.no_grad():
            q_next = q_target[:, :, 1:].max(-1).values  # (R, B, T)
            t = torch.arange(T, device=states.device)
            valid = t < batch["lengths"].unsqueeze(-1)
            last = t == batch["lengths"].unsqueeze(-1) - 1
            bootstrap = ~(last & batch["terminated"].unsqueeze(-1))
            target = rewards + self.gamma * q_next * bootstrap
        q_sa = (q[:, :, :T] * onehot).sum(-1)
        errors = TD_LOSSES[self.td_loss](q_sa, target) * valid
        return (errors.sum((1, 2)) / valid.sum((1, 2)).clamp(min=1)).sum()

    def adam_step(self, batch: dict, lr: float) -> None:
        """One Adam step (Kingma & Ba 2015) of every run on its own loss. Written out rather than
        torch.optim.Adam, which would change the runs' numbers: it updates the first moment by
        ``lerp_`` (m + (1 − β1)(g − m), not β1 m + (1 − β1) g) and takes √(1 − β2^k) as a power,
        so parameters differ by ~1 ulp from the second step on (tests/test_baselines.py holds the
        two within 1e-5); the moments stay buffers of the module, checkpointed with it."""
        p = {name: value.detach().requires_grad_() for name, value in self.params().items()}
        trained = [p[name] for name in self.names]
        with torch.enable_grad():
            grads = torch.autograd.grad(self.loss(p, batch), trained)
        self.adam_steps += 1
        (b1, b2), k = ADAM_BETAS, self.adam_steps
        with torch.no_grad():
            for name, g in zip(self.names, grads):
                m, v = self.moments(name, g)
                denominator = (v.sqrt() / math.sqrt(1 - b2**k)).add_(ADAM_EPS)
                getattr(self, name).addcdiv_(m, denominator, value=-lr / (1 - b1**k))

    def moments(self, name: str, g: torch.Tensor) -> tuple[torch.Tensor, torch.Tensor]:
        """Adam's moments of parameter ``name`` moved on by its gradient g, in place:
        m ← β1 m + (1 − β1) g, v ← β2 v + (1 − β2) g²."""
        (b1, b2), m, v = ADAM_BETAS, getattr(self, f"{name}_m"), getattr(self, f"{name}_v")
        m.mul_(b1).add_(g, alpha=1 - b1)
        v.mul_(b2).addcmul_(g, g, value=1 - b2)
        return m, v

    def get_extra_state(self) -> dict:
        """What a checkpoint needs beyond the buffers: the replay, the counters, the generator."""
        return {
            "replay": None if self.replay is None else filled(self.replay, self.episodes),
            "episodes": self.episodes,
            "adam_steps": self.adam_steps,
            "generator": self.generator.get_state(),
        }

    def set_extra_state(self, state: dict) -> None:
        saved, self.episodes, self.adam_steps = state["replay"], state["episodes"], state["adam_steps"]
        self.replay = None if saved is None else refilled(saved, self.replay_episodes)
        self.generator.set_state(state["generator"])
