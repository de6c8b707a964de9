"""A point on a camera image to be driven to the centre: SAC from pixels, for measuring."""
import gymnasium
import numpy as np
from gymnasium import spaces


class PixReach(gymnasium.Env):
    """48x48x3 uint8 image of a point (a bright 5x5 square) in [-1, 1]^2; action: velocity (2,), 0.1 a step;
    reward: minus its distance to the centre; 50 steps."""

    SIZE = 48

    def __init__(self):
        self.observation_space = spaces.Box(0, 255, (self.SIZE, self.SIZE, 3), np.uint8)
        self.action_space = spaces.Box(-1.0, 1.0, (2,), np.float32)

    def _obs(self):
        image = np.zeros((self.SIZE, self.SIZE, 3), np.uint8)
        i, j = ((self.pos + 1) / 2 * (self.SIZE - 5)).round().astype(int)
        image[i:i + 5, j:j + 5] = 255
        image[self.SIZE // 2, self.SIZE // 2, 1] = 128  # the centre, dim
        return image

    def reset(self, seed=None, options=None):
        super().reset(seed=seed)
        self.pos = self.np_random.uniform(-1, 1, 2)
        self.t = 0
        return self._obs(), {}

    def step(self, action):
        self.pos = np.clip(self.pos + 0.1 * np.clip(action, -1, 1), -1, 1)
        self.t += 1
        return self._obs(), -float(np.linalg.norm(self.pos)), False, self.t >= 50, {}
