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
