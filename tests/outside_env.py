"""A Gymnasium environment that is not ferl's (issue 5/8): importing this module registers it, so
``env=gymnasium env.id=outside_env:CueRecall-v0`` trains on it with no edit in ferl.

CueRecall: the first observation shows a cue c ∈ {0, 1}; then ``delay`` steps show a blank, each
rewarded −0.1 whatever the action (with ``random_delay``, a delay drawn from 1 … ``delay`` per
episode, so that runs' episodes end at different steps); at the last step the action must repeat the cue: +1 if it
does, −1 otherwise, and the episode terminates. The observation is a Tuple (symbol: cue 0, cue 1
or blank; whether the choice is now), so its one-hot encoding has 3 + 2 bits. With
``grid_actions`` the action is MultiDiscrete([2, 3]), whose first entry is the choice.
"""

import gymnasium
import numpy as np
from gymnasium import spaces

BLANK = 2


class CueRecall(gymnasium.Env):
    def __init__(self, delay: int = 2, grid_actions: bool = False, random_delay: bool = False):
        self.max_delay, self.random_delay = delay, random_delay
        self.observation_space = spaces.Tuple((spaces.Discrete(3), spaces.Discrete(2)))
        self.action_space = spaces.MultiDiscrete([2, 3]) if grid_actions else spaces.Discrete(2)
        self.cue, self.t, self.delay = 0, 0, delay

    def observe(self):
        symbol = self.cue if self.t == 0 else BLANK
        return (symbol, int(self.t == self.delay))

    def reset(self, *, seed=None, options=None):
        super().reset(seed=seed)
        self.cue, self.t = int(self.np_random.integers(2)), 0
        self.delay = int(self.np_random.integers(1, self.max_delay + 1)) if self.random_delay else self.max_delay
        return self.observe(), {}

    def step(self, action):
        choice = int(np.asarray(action).reshape(-1)[0])
        if self.t < self.delay:
            self.t += 1
            return self.observe(), -0.1, False, False, {}
        return self.observe(), 1.0 if choice == self.cue else -1.0, True, False, {}


gymnasium.register("CueRecall-v0", entry_point=CueRecall, max_episode_steps=10)


class Faulty(CueRecall):
    """CueRecall with a MultiDiscrete([3, 2]) observation (symbol, whether the choice is now) whose
    environment seeded ``bad_seed`` misbehaves from its ``at``-th step since that seeding (episodes
    included), as ``fault`` says: ``raise`` (ValueError), ``shape`` (an observation of 3 entries),
    ``range`` ([3, 1]: outside the space), ``nan_reward`` or ``inf_reward``. The step count is the
    environment's state, so a resumed run's environment would misbehave again if it were stepped."""

    FAULTS = ("raise", "shape", "range", "nan_reward", "inf_reward")

    def __init__(self, fault: str = "raise", at: int = 50, bad_seed: int = -1, delay: int = 2):
        super().__init__(delay=delay)
        assert fault in self.FAULTS, fault
        self.fault, self.at, self.bad_seed, self.bad, self.steps = fault, at, bad_seed, False, 0
        self.observation_space = spaces.MultiDiscrete([3, 2])

    def observe(self):
        return np.array(super().observe(), dtype=np.int64)

    def reset(self, *, seed=None, options=None):
        if seed is not None:
            self.bad, self.steps = seed == self.bad_seed, 0
        return super().reset(seed=seed, options=options)

    def step(self, action):
        observation, reward, terminated, truncated, info = super().step(action)
        self.steps += 1
        if not (self.bad and self.steps >= self.at):
            return observation, reward, terminated, truncated, info
        if self.fault == "raise":
            raise ValueError(f"operands could not be broadcast together with shapes (3,) (2,)\n(at step {self.steps})")
        if self.fault == "shape":
            return np.zeros(3, np.int64), reward, terminated, truncated, info
        if self.fault == "range":
            return np.array([3, 1]), reward, terminated, truncated, info
        return observation, float(self.fault.split("_")[0]), terminated, truncated, info


gymnasium.register("Faulty-v0", entry_point=Faulty, max_episode_steps=10)
