"""Any Gymnasium environment with discrete actions as a ferl environment (``env=gymnasium``).

R runs are one ``gymnasium.vector`` environment (``SyncVectorEnv``; ``AsyncVectorEnv`` with
``vectorization=async``), run r seeded with seed + r at its first reset and never again, so every
later episode continues its own random stream. Each run's observations are encoded as bits
(``ferl.envs.encodings``) and given ids in order of first sight: the table of an episodic
environment (``EpisodicEnvironment``) that grows in place as observations are discovered
(``discovers_observations``), up to ``max_observations`` rows. Where the encoding's number of
distinct codes is known (``distinct_codes``: one-hot and thresholds), the table is sized to it
(``max_observations: null``) and a smaller ``max_observations`` is refused at set-up, since a run
could outgrow it (docs/beyond.md, "Outside POMDPs"); only a count too large for a table
(``TABLE_BYTES``), where ``max_observations`` is the user's bound, or an unknown one (MiniGrid's
view; 4096 rows unless set) can still overflow mid-run. ``encoding: real`` (a ``Box`` as real values
in [0, 1]) has no distinct codes: each step's observation gets a row of its own, in a table sized to
the episodes whose ids a phase keeps (``ferl.envs.observation_rows``, ``keep_episodes``).

Episodes follow ferl's lockstep (``ferl.trainers.actor_episodes``): every run starts episode k
together, and a run whose episode has ended waits, with reward 0, until all have. The vector
environment still steps it: Gymnasium's next-step auto-reset (its default) starts a new episode
there, which is played with action 0 and thrown away; the next ``reset`` resets every run. An
episode also ends, truncated, after ``max_steps`` actions (default: the id's own limit —
``max_episode_steps`` of its registration, POPGym's ``max_episode_length``, MiniGrid's
``max_steps``).

Rewards are the environment's, times ``reward_scale`` for the learners (POPGym scales every
episode's return into [−1, 1], so a step's reward can be ±1/50; the agents' step sizes are those
of rewards of order 1). The episode's undiscounted return, in the environment's own units, is the
outcome ``return`` (``final_return`` in summary.json); with ``success_threshold`` an episode whose
return exceeds it counts as a success (``final_success_rate``, MiniGrid's reward is positive only at the goal), and
with ``optimal_return`` (the environment's stated optimum) a run is ``solved`` when its final
return is ≥ 0.95 of it and every success rate ≥ 0.95.

A checkpoint holds every run's environment pickled (``ferl.envs.boundary.Guarded``: generators
included), so a resumed run steps the same episodes as an uninterrupted one.

Every run's environment is checked at the boundary (``ferl.envs.boundary``: every observation
against its space, every reward for finiteness, every exception caught). A run whose environment
fails is handed to ``on_fault`` — the training job's divergence guard, which freezes it like a
diverged run (``ferl.run.guard``) while the other runs go on — with the env id, run, episode and
step; its environment is never stepped again, in this process or a resumed one. Without
``on_fault`` (the class used directly) the fault raises ``EnvironmentFault``.
"""

import logging
from typing import Annotated, Literal, cast

import gymnasium
import numpy as np
import torch
from gymnasium import spaces

from ferl import rng
from ferl.config.params import ConfigError, Positive, PositiveInt, at_least, checked, plain
from ferl.envs.boundary import DETAIL, FAULT, Guarded
from ferl.envs.derived import Derived, derived_once, derives, unused_bits
from ferl.envs.encodings import (
    BadThresholds,
    BinaryObservation,
    Encoding,
    NoEncoding,
    RealObservation,
    distinct_codes,
    fixed_bits,
    real_box,
)
from ferl.envs.gymnasium_ids import action_sizes, default_max_steps, make
from ferl.envs.observation_rows import StepRows, table_rows
from ferl.interfaces import EpisodicEnvironmentBase
from ferl.messages import warn


class EnvironmentFault(RuntimeError):
    """An outside environment failed (``ferl.envs.boundary``) and nothing freezes its run."""


class GymnasiumEnv(EpisodicEnvironmentBase):
    """R runs of the Gymnasium environment ``id`` (module docstring). Arguments: ``kwargs`` for
    ``gymnasium.make``; ``encoding`` of the observations (``ferl.envs.encodings``) with its
    ``thresholds``; ``max_steps`` T_max (null: the id's own); ``vectorization``; ``max_observations``
    the table's rows (null: sized to the encoding's codes, module docstring); ``success_threshold``
    and ``optimal_return`` (null: none stated)."""

    task = "gymnasium"
    discovers_observations = True  # the observation table grows as observations are seen
    optimal_steps = float("nan")  # unknown in general
    reward_values = ()  # no reward bits: predictors take the scalar reward (reward_output=linear)

    @checked
    def __init__(
        self,
        n_runs: PositiveInt,
        generator: torch.Generator,
        seed: int,
        id: str,
        kwargs: dict | None = None,
        encoding: Encoding = "auto",
        thresholds: list | Literal["auto"] | None = None,
        bits_per_entry: PositiveInt = 8,
        sample_steps: Annotated[int, at_least(2, "a sample that can vary")] = 1000,
        max_steps: PositiveInt | None = None,
        vectorization: Literal["sync", "async"] = "sync",
        max_observations: PositiveInt | None = None,
        success_threshold: float | None = None,
        optimal_return: float | None = None,
        reward_scale: Positive = 1.0,
        device="cpu",
    ):
        del generator  # the environments draw from their own seeded generators
        self.n_runs, self.id, self.kwargs, self.device = n_runs, id, dict(kwargs or {}), torch.device(device)
        self.encoding, given = encoding, plain(thresholds)
        self.thresholds: list = [] if given == "auto" else list(given or ())  # plain lists: JSON, pickles
        self.derived: Derived | None = None  # the thresholds derived at set-up (ferl.envs.derived)
        probe = make(id, self.kwargs)
        try:
            self.sizes = action_sizes(probe.action_space, id)
            self.action_space = probe.action_space
            limit = max_steps or default_max_steps(probe)
            if limit is None:
                raise ConfigError(f"env.max_steps: {id!r} states no episode limit; set env.max_steps (T_max)")
            try:
                if encoding == "real":
                    real_box(probe.observation_space)  # before its sample is drawn
                if derives(probe.observation_space, encoding, given):
                    self.derived = derived_once(probe, [id, self.kwargs], bits_per_entry, sample_steps, limit)
                    self.thresholds = self.derived.thresholds
                elif encoding == "real":  # its values are standardised by the same sample's mean and s.d.
                    self.derived = derived_once(probe, [id, self.kwargs], bits_per_entry, sample_steps, limit)
                observation_size = self.encoded_size(probe, max_observations)
                codes = distinct_codes(probe.observation_space, encoding, self.thresholds)
                box = isinstance(probe.observation_space, spaces.Box) and self.thresholds
                fixed = fixed_bits(probe.observation_space, self.thresholds) if box else []
            except BadThresholds as e:
                raise ConfigError(f"env.thresholds: {e}") from None
            except NoEncoding as e:
                raise ConfigError(f"env.encoding: the observation space of {id!r}: {e}") from None
        finally:
            probe.close()
        # said at the first episode, once set-up has passed (a refusal stays one line)
        self.unused_bits = unused_bits(id, fixed, int(observation_size), self.derived)
        # derived thresholds stated at the first episode: the run's log (train.log); records/run.json has them too
        self.stated = ""
        if self.derived is not None:
            self.stated = self.derived.sample_stated(id) if encoding == "real" else self.derived.stated(id)
        self.max_steps, self.observation_size = limit, int(observation_size)
        self.distinct_codes = codes
        self.rows = StepRows(n_runs, limit, observation_size, self.device) if encoding == "real" else None
        if self.rows is None:
            max_observations = table_rows(id, codes, int(observation_size), max_observations)
        self.n_actions = int(np.prod(self.sizes))
        self.action_names = (
            [str(i) for i in range(self.n_actions)]
            if len(self.sizes) == 1
            else ["(" + ",".join(map(str, np.unravel_index(i, self.sizes))) + ")" for i in range(self.n_actions)]
        )
        self.success_threshold, self.optimal_return, self.vectorization = (
            success_threshold,
            optimal_return,
            vectorization,
        )
        self.reward_scale = reward_scale
        self.seeds: list[int | None] = list(rng.run_seeds(seed, n_runs))  # as vector.reset takes them
        vector = gymnasium.vector.AsyncVectorEnv if vectorization == "async" else gymnasium.vector.SyncVectorEnv
        self.vector = vector(
            [self.env_fn() for _ in range(n_runs)], autoreset_mode=gymnasium.vector.AutoresetMode.NEXT_STEP
        )
        self.observation_table = (
            self.rows.table
            if self.rows is not None
            else torch.zeros(cast(int, max_observations), self.observation_size, device=self.device)
        )
        self.ids: dict[bytes, int] = {}
        self.observation_names: list[str] = []
        self.seeded = False
        self.obs_id = torch.zeros(n_runs, dtype=torch.long, device=self.device)
        self.done = torch.ones(n_runs, dtype=torch.bool, device=self.device)
        self.t = torch.zeros(n_runs, dtype=torch.long, device=self.device)
        self.episode_return = torch.zeros(n_runs, device=self.device)
        self.episode = -1  # episodes begun (the reset count − 1): the reports' episode
        self.failed = [False] * n_runs  # runs whose environment failed (module docstring)
        self.on_fault = None  # on_fault(run, episode, reason, details), set by the training job

    def encoded_size(self, probe, max_observations: int | None) -> int:
        """The size of an encoded observation; ``real`` takes no thresholds and no table bound."""
        if self.encoding != "real":
            encoded = cast(
                spaces.MultiBinary, BinaryObservation(probe, self.encoding, self.thresholds).observation_space
            )
            return cast(int, encoded.n)  # MultiBinary(size): an int
        if self.thresholds:
            raise BadThresholds(f"are given, but env.encoding=real encodes {probe.observation_space} without them")
        if max_observations is not None:
            raise ConfigError(
                f"env.max_observations={max_observations}: env.encoding=real keeps a row per step of the "
                f"episodes kept, not a table of distinct observations; leave it null"
            )
        assert self.derived is not None  # the sample is drawn for real too
        return len(self.derived.mean)  # one value an entry (``RealObservation``)

    def env_fn(self):
        env_id, kwargs, encoding, thresholds = self.id, self.kwargs, self.encoding, self.thresholds
        if self.derived is not None and encoding == "real":
            mean, std = self.derived.mean, self.derived.std
            return lambda: RealObservation(Guarded(make(env_id, kwargs)), mean, std)
        return lambda: BinaryObservation(Guarded(make(env_id, kwargs)), encoding, thresholds)

    def keep_episodes(self, episodes: int, key: str) -> None:
        """Ids stay valid for the last ``episodes`` episodes (``EpisodicEnvironment``): a table of
        distinct codes keeps every id; rows per step (``real``) are sized to them."""
        if self.rows is not None:
            self.rows.keep(episodes, key, self.id)
            self.observation_table = self.rows.table

    # ---- observations -------------------------------------------------------------------------
    def observed_ids(self, observations: np.ndarray, runs: torch.Tensor) -> torch.Tensor:
        """Ids (R,) of the encoded observations (R, O) of the runs where ``runs`` is set: their rows
        per step (``real``) or their codes' (``identify``)."""
        if self.rows is not None:
            return torch.where(runs, self.rows.place(observations, self.episode, self.t, runs), self.obs_id)
        return torch.where(runs, self.identify(observations), self.obs_id)

    def identify(self, bits: np.ndarray) -> torch.Tensor:
        """Ids (R,) of the encoded observations (R, O), new ones added to the table."""
        ids = []
        for row in np.asarray(bits, np.uint8):
            key = row.tobytes()
            if key not in self.ids:
                i = len(self.ids)
                if i == self.observation_table.shape[0]:
                    raise RuntimeError(
                        f"env.max_observations: {self.id!r} showed more than {i} distinct observations; "
                        f"raise env.max_observations"
                    )
                self.ids[key] = i
                self.observation_names.append(f"obs{i}")
                self.observation_table[i] = torch.from_numpy(row.astype(np.float32)).to(self.device)
            ids.append(self.ids[key])
        return torch.tensor(ids, device=self.device)

    def observe(self) -> torch.Tensor:
        return self.observation_table.index_select(0, self.obs_id)

    # ---- episodes -----------------------------------------------------------------------------
    def reset(self) -> torch.Tensor:
        """Every run's next episode (run r seeded with seed + r at the first one)."""
        if self.stated:
            logging.getLogger(__name__).info(self.stated)
            self.stated = ""
        if self.unused_bits:
            warn(self.unused_bits)
            self.unused_bits = ""
        bits, info = self.vector.reset(seed=None if self.seeded else self.seeds)
        self.seeded = True
        self.episode += 1
        self.done = torch.zeros_like(self.done)
        self.t = torch.zeros_like(self.t)
        self.episode_return = torch.zeros_like(self.episode_return)
        self.report_faults(info, None)
        self.obs_id = self.observed_ids(bits, ~self.done)
        return self.observe()

    def env_actions(self, action: torch.Tensor) -> np.ndarray:
        """ferl's action indices (R,) as the space's actions; action 0 for runs that wait."""
        index = torch.where(self.done, 0, action).cpu().numpy()
        space = self.action_space
        if isinstance(space, spaces.Discrete):
            return index + int(space.start)
        digits = np.stack(np.unravel_index(index, self.sizes), -1).reshape(len(index), *space.nvec.shape)
        return digits + (space.start if getattr(space, "start", None) is not None else 0)

    def advance(self, action: torch.Tensor) -> tuple[torch.Tensor, torch.Tensor, torch.Tensor]:
        """One step of every run that has not ended: (rewards, terminated, truncated), each (R,)."""
        bits, reward, terminated_np, truncated_np, info = self.vector.step(self.env_actions(action))
        active = ~self.done
        as_tensor = lambda x, dtype: torch.as_tensor(np.asarray(x), dtype=dtype, device=self.device)  # noqa: E731
        raw = torch.where(active, as_tensor(reward, torch.float32), 0.0)
        self.t = self.t + active.long()
        self.report_faults(info, active)  # before the learner sees the step (a failed run's reward is 0)
        terminated = as_tensor(terminated_np, torch.bool) & active
        truncated = (as_tensor(truncated_np, torch.bool) | (self.t >= self.max_steps)) & active & ~terminated
        self.obs_id = self.observed_ids(bits, active)
        self.episode_return = self.episode_return + raw
        self.done = self.done | terminated | truncated
        return raw * self.reward_scale, terminated, truncated

    def report_faults(self, info: dict, active: torch.Tensor | None) -> None:
        """Hand every run whose environment failed at this reset (``active`` None) or step to
        ``on_fault`` (module docstring), once: the reason names the env id, episode and step."""
        if FAULT not in info:
            return
        for r in np.flatnonzero(info["_" + FAULT]).tolist():
            self.failed[r] = True
            step = int(self.t[r])
            where = (
                "its reset"
                if active is None
                else f"step {step}"
                if bool(active[r])
                else f"step {step} (after its episode ended, while it waited for the other runs)"
            )
            detail = info[DETAIL][r]
            reason = f"env {self.id!r} {info[FAULT][r]} at episode {self.episode}, {where}" + (
                f": {detail}" if detail else ""
            )
            if self.on_fault is None:
                raise EnvironmentFault(f"run {r} (seed {self.seeds[r]}): {reason}")
            self.on_fault(r, self.episode, reason, {"env_id": self.id, "step": step})

    def step(self, action: torch.Tensor):
        reward, terminated, truncated = self.advance(action)
        return self.observe(), reward, terminated, truncated

    def outcomes(self) -> dict:
        """The episode's undiscounted return, and whether it succeeded where a threshold is set."""
        facts = {"return": self.episode_return}
        if self.success_threshold is not None:
            facts["success"] = self.episode_return > self.success_threshold
        return facts

    def labels(self) -> dict:
        return {}

    @property
    def probe(self) -> torch.Tensor:
        return torch.zeros_like(self.done)  # no state of a third-party task is singled out

    def optimal(self, gamma: float) -> dict:
        """The stated optimum of the undiscounted return, if any (``solved`` needs one)."""
        return {} if self.optimal_return is None else {"return": self.optimal_return}

    def describe(self) -> dict:
        return {
            "kind": "gymnasium",
            "task": self.task,
            "episodic": True,
            "observation": "real" if self.rows is not None else "bits",
            "id": self.id,
            "kwargs": self.kwargs,
            "encoding": self.encoding,
            "thresholds": self.thresholds,
            **({"derived": self.derived.describe(self.rows is None)} if self.derived is not None else {}),
            "vectorization": self.vectorization,
            "observation_size": self.observation_size,
            "distinct_codes": self.distinct_codes,  # null: not known in advance
            "max_observations": self.observation_table.shape[0],
            "n_actions": self.n_actions,
            "action_names": self.action_names,
            "max_steps": self.max_steps,
            "optimal_return": self.optimal_return,
            "success_threshold": self.success_threshold,
            "reward_scale": self.reward_scale,
            "labels": [],
            "outcomes": list(self.outcomes()),
        }

    def state_dict(self) -> dict:
        n = len(self.ids) if self.rows is None else self.observation_table.shape[0]  # real: every row
        return {
            "envs": self.vector.get_attr("ferl_state"),
            "seeded": self.seeded,
            "table": self.observation_table[:n].cpu(),
            "obs_id": self.obs_id,
            "done": self.done,
            "t": self.t,
            "episode_return": self.episode_return,
            "episode": self.episode,
            "failed": list(self.failed),
        }

    def load_state_dict(self, state: dict) -> None:
        self.vector.set_attr("ferl_state", list(state["envs"]))
        self.failed = list(state.get("failed", [False] * self.n_runs))
        self.vector.set_attr("ferl_failed", self.failed)  # a failed environment stays dead, never stepped
        self.episode = state.get("episode", -1)
        self.seeded = state["seeded"]
        self.ids.clear()
        self.observation_names.clear()
        self.observation_table.zero_()
        if self.rows is not None:  # the rows of the episodes kept, as they were
            self.observation_table.copy_(state["table"])
            self.rows.placed = True
        else:
            self.identify(state["table"].numpy().astype(np.uint8))
        for key in ("obs_id", "done", "t", "episode_return"):
            setattr(self, key, state[key].to(self.device))

    def close(self) -> None:
        self.vector.close()
