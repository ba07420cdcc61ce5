"""Stateless CartPole, as issue 61's user wrote it outside ferl: importing this module registers
``StatelessCartPole-v0``, so ``env=gymnasium env.id=stateless_cartpole:StatelessCartPole-v0``
trains on it (docs/beyond.md, "Box observations", gives the same code as a recipe).

CartPole-v1 showing only [x, θ], the cart's position and the pole's angle: the velocities ẋ and θ̇
must come from memory. The Box keeps CartPole's bounds for those entries (x ±4.8, θ ±0.418 rad,
twice the ±2.4 and ±0.21 at which an episode ends) and episodes end after 200 steps.
"""

import gymnasium
import numpy as np
from gymnasium import spaces

KEPT = [0, 2]  # CartPole's observation: x, ẋ, θ, θ̇


class StatelessCartPole(gymnasium.ObservationWrapper):
    def __init__(self, env):
        super().__init__(env)
        box = env.observation_space
        self.observation_space = spaces.Box(box.low[KEPT], box.high[KEPT], dtype=np.float32)

    def observation(self, observation):
        return observation[KEPT]


def make_stateless(**kwargs):
    return StatelessCartPole(gymnasium.make("CartPole-v1", **kwargs).unwrapped)


gymnasium.register("StatelessCartPole-v0", entry_point=make_stateless, max_episode_steps=200)
