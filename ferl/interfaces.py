"""The interfaces the components of ferl meet through (docs/architecture.md).

Data flows one way: environment → preprocessor → predictors → actor. Trainers and analysis talk
to these protocols only, so a new component is one module with one YAML file whose ``_target_``
names it. Every component is batched over R independent runs (parameters and states carry the
run dimension first; one call advances or updates every run) and says what it is (``describe``,
kept in ``records/run.json``, from which analysis decides which figures and claims apply).

A protocol declares every member that ferl calls, its hooks too, each with a default on the small
base class beside it (``EnvironmentBase`` … ``ActorBase``, as acme's ``core.py``): a component
that subclasses the base names only the hooks it changes, and ferl calls every member directly. A
component is checked against its protocol when it is built (``ferl.conformance.missing_members``).

Constructors receive their YAML keys plus what the trainer supplies (``n_runs``, sizes, ``seed``,
``generator``, ``device``, ``data`` where the constructor names it); the types and ranges of the
YAML keys are the constructor's annotations (``ferl.config.params``), checked before any work.
"""

from collections.abc import Callable, Hashable, Sequence
from typing import Protocol, runtime_checkable

import torch
from torch import Tensor

from ferl.ended_episode import EndedEpisode  # what Actor.end_episode takes

State = Tensor | tuple[Tensor, ...]  # a predictor's recurrent state: (R, ·), or an LSTM's (h, c)


class Checkpointed(Protocol):
    """What a checkpoint keeps of a component: its parameters, its episode in progress."""

    def state_dict(self) -> dict: ...

    def load_state_dict(self, state: dict) -> None: ...


@runtime_checkable
class Environment(Checkpointed, Protocol):
    """R environments stepped together with one action per run (R,) of ``n_actions`` discrete actions;
    ``describe()`` holds at least ``task`` (the summary's task: which metrics a run reports), ``kind``,
    ``episodic``, ``observation`` ("bits", "image" or "vector"), ``observation_size`` and ``n_actions``."""

    n_runs: int
    n_actions: int
    action_names: Sequence[str]
    observation_size: int
    task: str
    device: torch.device
    # set by the training job: on_fault(run, episode, reason, details) freezes a run whose environment
    # failed (ferl.envs.boundary); an environment that cannot fail never calls it (default None)
    on_fault: Callable | None

    def reset(self) -> Tensor:
        """Start every run afresh; the observations (R, observation_size)."""

    def step(self, action: Tensor) -> tuple[Tensor, Tensor, Tensor, Tensor]:
        """Act in every run: (observations (R, O), rewards (R,), terminated (R,), truncated (R,))."""

    def optimal(self, gamma: float) -> dict[str, float]:
        """The optimum a run is measured against (``summary.json``'s ``optimal``)."""

    def describe(self) -> dict: ...


@runtime_checkable
class ContinuingEnvironment(Environment, Protocol):
    """A continuing task stepped by the online TD phase (the digit floor, §3.4): a step's random
    numbers can be drawn ahead, so that a chunk of steps is one call (and can be compiled)."""

    def step_inputs(self, steps: int) -> tuple:
        """The random numbers of the next ``steps`` steps, each (steps, R, …)."""

    def step_with(self, action: Tensor, *inputs) -> tuple[Tensor, Tensor]:
        """``step`` on one step's slice of ``step_inputs``: (observations, rewards)."""

    def slice_runs(self, index: slice) -> "ContinuingEnvironment":
        """A view of a slice of the runs whose steps land in this batch."""


class EnvironmentBase:
    """The default of ``Environment``'s hook: nothing to report a fault to until the job sets it."""

    on_fault: Callable | None = None


@runtime_checkable
class EpisodicEnvironment(Environment, Protocol):
    """An environment of episodes with a finite set of observations (the T-mazes), as the phased
    algorithms of chapters 4–5 need it: observations are ids into ``observation_table``, so that
    episodes are stored as ids and a frozen predictor's step is a table lookup.

    A run's episode ends when it terminates or after ``max_steps`` actions; ``done`` runs stay put
    (reward 0) until ``reset``. What the records keep besides returns and lengths is declared here,
    not known to the trainer: ``outcomes`` (facts of an ended episode, e.g. ``correct_goal``;
    boolean ones become ``final_<name>_rate`` metrics and count towards ``solved``), ``labels``
    (what the episode's probes are labelled with, e.g. the maze's condition) and ``probe`` (the
    runs whose present state is one whose activations the records keep, e.g. the T-junction).
    Four hooks (defaults on ``EpisodicEnvironmentBase``) say how its episodes may be run and
    compiled, and how long its ids stay valid."""

    max_steps: int
    optimal_steps: int
    reward_values: tuple[float, ...]
    observation_names: Sequence[str]
    observation_table: Tensor  # (ids, O): with a reservoir, several ids per name
    obs_id: Tensor  # (R,) the id of every run's present observation
    done: Tensor  # (R,) bool
    t: Tensor  # (R,) actions taken in the episode
    # True when ``advance`` is tensor operations only (no branch on a tensor's value, no NumPy): an
    # episode can then be one compiled graph (``ActorEpisodes.episode``)
    traceable_steps: bool
    # True when the observations are not known in advance (a third-party environment,
    # ``ferl.envs.gymnasium_vector``): rows of the table are filled in place as they are met, so
    # the phases index the table live and compute nothing from it ahead of the episodes
    discovers_observations: bool

    def keep_episodes(self, episodes: int, key: str) -> None:
        """A phase that keeps observation ids of its last ``episodes`` episodes (the one being
        played included) says so before the first episode: the ids must stay valid that long.
        A table of fixed or distinct observations keeps every id (the default does nothing); one
        that reuses rows (``env.encoding=real``) is sized to them, and a ConfigError naming ``key``
        says where it cannot be."""

    def tables_generic(self, generic: Callable[[Tensor], Tensor]) -> None:
        """Before its episodes are compiled, a tensor environment (``traceable_steps``) replaces the
        tables whose sizes follow its configuration (the maze's corridor), not the runs, by
        ``generic(table)``: one compiled graph then serves every such size. The numbers its steps
        read from the configuration must be tensors for the same reason. The default has none."""

    def advance(self, action: Tensor) -> tuple[Tensor, Tensor, Tensor]:
        """``step`` without building the observations: (rewards, terminated, truncated)."""

    def outcomes(self) -> dict[str, Tensor]:
        """Per-run facts of the episode (valid once ``done``), each (R,)."""

    def labels(self) -> dict[str, Tensor]:
        """Per-run labels of the present episode, each (R,)."""

    @property
    def probe(self) -> Tensor:
        """(R,) bool: runs whose present state the records keep activations of."""


class EpisodicEnvironmentBase(EnvironmentBase):
    """The defaults of ``EpisodicEnvironment``'s hooks: eager episodes, a table known from the start."""

    traceable_steps: bool = False
    discovers_observations: bool = False

    def keep_episodes(self, episodes: int, key: str) -> None:
        """Every id stays valid: nothing to size."""

    def tables_generic(self, generic: Callable[[Tensor], Tensor]) -> None:
        """No table sized by the configuration: nothing to replace."""


@runtime_checkable
class Preprocessor(Checkpointed, Protocol):
    """Maps raw observations (…, input_size) to processed ones (R, …, output_size), run by run
    (chapter 5's RBM, §5.2). ``fit`` learns from the data's training images before the agent acts."""

    input_size: int
    output_size: int
    # True when ``fit`` takes ``stop`` and ``resume`` (``fit(data, writer, stop, resume)``): ``stop()``
    # is asked between steps of the fit; True raises ``FitStopped``, and ``resume=`` its state (the
    # weights restored from the checkpoint) continues the fit. False: a stop waits for the fit's end
    stoppable_fit: bool

    def fit(self, data, writer) -> dict:
        """Learn from ``data`` (train_images, test_images, test_labels, e.g. an ``MnistSplit``),
        logging to the TensorBoard ``writer``; returns the records of the fit (e.g. error curves)."""

    def transform(self, observations: Tensor) -> Tensor:
        """(B, input_size) shared by all runs, or (R, B, input_size) → (R, B, output_size)."""

    def describe(self) -> dict: ...


class PreprocessorBase:
    """The default of ``Preprocessor``'s hook: a fit that runs to its end."""

    stoppable_fit: bool = False


class FitStopped(Exception):
    """A preprocessor's fit stopped by a stop request; ``state`` continues it (``Preprocessor``)."""

    def __init__(self, state: dict):
        super().__init__(f"the fit stopped after sweep {state.get('sweep')}")
        self.state = state


@runtime_checkable
class TrainingBatch(Protocol):
    """Predictors that train together on the same sequences (``Predictor.training_batch``)."""

    def train_epoch(self, orders: Sequence[Tensor]) -> None:
        """One epoch, member k taking the sequences in its order orders[k] (R, N)."""

    def fuse(self, device: torch.device, unroll_to: int | None = None) -> None:
        """Run the next epochs compiled where it can (compile=true), unrolled to ``unroll_to`` if given."""


class TrainingBatchBase:
    """The default of ``TrainingBatch``'s hook: epochs stay eager."""

    def fuse(self, device: torch.device, unroll_to: int | None = None) -> None: ...


@runtime_checkable
class Predictor(Checkpointed, Protocol):
    """A recurrent model of the history (§2.4, §4.2, §5.2) whose memory the actor sees.

    Sequences are padded batches: y (R, B, T+1, Y) observations, a (R, B, T, A) one-hot actions,
    r (R, B, T+1, ·) reward targets (``reward_targets``), lengths (R, B) the actions of each.
    """

    memory_size: int  # what ``memory`` hands the actor per run
    batch_key: Hashable  # predictors with equal keys train as one ``training_batch``

    def initial_state(self) -> State:
        """The state before the first observation, m_0 (Eq. 4.1)."""

    def memory(self, state: State) -> Tensor:
        """What the actor sees of a state: (R, memory_size)."""

    def generic_state(self, state: State) -> State:
        """The state, its sizes set by the configuration (a transformer's T_max + 1 cached tokens) generic."""

    def step(self, state: State, y_prev: Tensor, a_prev: Tensor) -> State:
        """One step from y_{t−1} (R, Y) and one-hot a_{t−1} (R, A) (Eq. 4.3)."""

    def frozen_step(self, table: Tensor, n_actions: int):
        """The frozen predictor's step on observation ids, (state, obs_id_prev (R,), action_prev (R,))
        → state, ``table`` (ids, Y) or (R, ids, Y) the (processed) observation of every id; it may
        precompute what does not depend on the state (the Elman predictor's drive table)."""

    def reward_targets(self, reward_values: Sequence[float], rewards: Tensor) -> Tensor | None:
        """Targets (R, B, T+1, ·) of rewards r_1 … r_T (R, B, T), or None without a reward output."""

    @classmethod
    def training_batch(
        cls,
        members: list,
        y: Tensor,
        a: Tensor,
        rs: list,
        lengths: Tensor,
        batch_size: int | None = None,
        summed: bool = False,
    ) -> TrainingBatch:
        """Members with one ``batch_key`` and their training sequences, ready to train; one SGD
        step per ``batch_size`` sequences (the members' own when None) on their mean loss, or
        their summed loss when ``summed``."""

    def prediction_errors(self, y: Tensor, a: Tensor, r: Tensor | None, lengths: Tensor) -> Tensor:
        """Prediction error of every step (R, B, T+1), NaN where there is none (Eq. 4.8)."""

    def observation_error(self, state: State, y: Tensor) -> Tensor | None:
        """ρ_y Σ_i |y_i − ŷ_i| (R,): how far the observation that ``state`` predicts is from y (R, Y)
        (the online trainer's curiosity, §5.4); None for a predictor without an observation head."""

    def observe_rewards(self, rewards: Tensor, lengths: Tensor) -> None:
        """Take in the rewards of new episodes (R, B, T_max) with lengths (R, B), once each (a
        normalised reward head's statistics, ``ferl.predictors.popart``)."""

    def describe(self) -> dict: ...


class PredictorBase:
    """The defaults of ``Predictor``'s hooks: no observation head, reward statistics or generic sizes."""

    def generic_state(self, state: State) -> State:
        return state

    def observation_error(self, state: State, y: Tensor) -> Tensor | None:
        return None

    def observe_rewards(self, rewards: Tensor, lengths: Tensor) -> None: ...


@runtime_checkable
class Actor(Checkpointed, Protocol):
    """Chooses actions from a state (R, B, S) (§3.2) and learns, as acme's actors observe and update:
    after every step from its TD error (``learn``) and after every episode from the whole episode
    (``end_episode``). A TD actor (the FERL actor, Eq. 3.10) learns in ``learn``; a recurrent
    Q-learner that replays whole episodes (``ferl.actors.drqn``) in ``end_episode``.

    ``evaluate`` gives every action's value as an energy F (lower is better: Q = −F) and a cache
    of what ``learn`` reuses; ``ferl.actors.td.td_step`` is the one online step that every trainer
    takes with any actor. The fast path's members (``uniforms_per_action``, ``slice_runs``,
    ``prepare_for_compile``, ``compile_updates``) say how it may be compiled; the hooks have
    defaults on ``ActorBase``. What the records show of it is the optional ``ActorViews``.
    """

    n_runs: int
    gamma: float  # the discount of its TD errors (and of the returns the optimum is measured in)
    # True when it learns only at ``end_episode`` (replayed episodes): a continuing task cannot train it
    learns_from_episodes: bool

    def learning_rate(self, progress: float) -> float: ...

    def inverse_temperature(self, progress: float) -> float: ...

    def evaluate(self, s: Tensor) -> tuple[Tensor, Tensor]:
        """F (R, B, nA) of every action and the per-action cache (R, B, nA, ·) (greedy tests)."""

    def act(
        self, s: Tensor, beta: float, generator: torch.Generator, uniform: Tensor | None = None
    ) -> tuple[Tensor, Tensor, Tensor, Tensor]:
        """At states s (R, 1, S): an action (R, 1), its F (R, 1) and cache (R, 1, ·), and the F a TD
        error bootstraps from at s (by the actor's TD rule); ``uniform`` (R, 1, uniforms_per_action)."""

    def learn(self, s, a, cache_sa, delta, lr, s_next, a_next, F_next, cache_next) -> tuple[Tensor, Tensor]:
        """After a step: update on (s, a) with TD errors delta (R, B); returns F and the cache of
        (s', a') for the next TD error (at the updated parameters where the actor's reading says so)."""

    def end_episode(self, episode: EndedEpisode, lr: float) -> None:
        """After every run's episode has ended: learn from it at step size ``lr``, and forget it (a
        memory the actor carries starts afresh with the next ``act``)."""

    @property
    def uniforms_per_action(self) -> int:
        """U(0, 1) numbers one choice takes (``act``'s ``uniform``): 1, or a Gibbs chain's every draw;
        0 where ``act`` draws from the generator itself (then nothing is drawn ahead or compiled)."""

    def slice_runs(self, index: slice) -> "Actor":
        """A view of a slice of the runs whose updates land in this actor (the fast path's groups
        of runs, ``ferl.trainers.chunks``)."""

    def prepare_for_compile(self) -> None:
        """Lay the parameters out for a compiled step (their values unchanged)."""

    def compile_updates(self, device: torch.device) -> None: ...  # compile what end_episode learns
    def describe(self) -> dict: ...


class ActorBase:
    """The defaults of ``Actor``'s hooks: nothing learnt after a step or an episode (an actor
    overrides the one it learns in), no random number drawn inside a step, no layout to prepare."""

    learns_from_episodes: bool = False

    @property
    def uniforms_per_action(self) -> int:
        return 1

    def learn(self, s, a, cache_sa, delta, lr, s_next, a_next, F_next, cache_next) -> tuple[Tensor, Tensor]:
        return F_next, cache_next

    def end_episode(self, episode: EndedEpisode, lr: float) -> None:
        """Nothing."""

    def prepare_for_compile(self) -> None:
        """Nothing to lay out: the parameters' default layout serves a compiled step."""

    def compile_updates(self, device: torch.device) -> None: ...  # nothing learnt after an episode


@runtime_checkable
class ActorViews(Protocol):
    """What the records and TensorBoard show of an actor, where it has them (optional: an actor
    without them trains the same, without those records): Figs. 3.5, 4.14–4.19."""

    def hidden(self, cache: Tensor) -> Tensor:
        """The actor's hidden activations from a cache entry (R, B, ·), for the records."""

    def state_weights(self) -> Tensor:
        """Weights from the state nodes (R, S, ·), for images of what the actor attends to."""


class Trainer(Protocol):
    """A training procedure: built from ``conf/trainer/*.yaml`` (``_target_``), then ``setup``
    builds the components from the composed config and ``fit`` trains them into a run directory."""

    def setup(self, cfg, device: torch.device) -> None: ...

    def metric_names(self) -> list[str]:
        """The flat names (``ferl.stats.flat_metrics``) of the summary.json metrics ``fit`` writes."""

    def fit(self, run, resume: bool) -> dict:
        """Train; returns the summary.json dict (docs/records.md)."""

    def starting_state(self) -> list:
        """What ``fit`` allocates as it starts beyond ``setup`` (its phases' ``fresh_state``: records
        of every step or episode), for the memory estimate (``ferl.run.footprint``)."""

    def run_bytes(self) -> int:
        """The peak bytes ``fit`` allocates later (collected episodes, training batches), for it too."""


class TrainerBase:
    """The defaults of ``Trainer``'s hooks: nothing allocated beyond what ``setup`` built."""

    def starting_state(self) -> list:
        return []

    def run_bytes(self) -> int:
        return 0
