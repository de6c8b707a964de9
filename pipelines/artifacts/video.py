"""Videos of a policy acting, as the tutorials make them: frames from ``render()`` into an mp4.

The env is stepped through gymnasium directly (no TorchRL wrapper is needed to render), with the
same float32 observations the policy was trained on.
"""

from __future__ import annotations

from collections.abc import Callable, Mapping
from pathlib import Path

import gymnasium
import imageio.v2 as imageio
import numpy as np
import torch

from rlpipe.envs import MINITAUR_ID, EnvError, observed, resolve_env_id
from rlpipe.envs.observations import is_atari
from rlpipe.envs.user import check_kwargs
from rlpipe.pipelines.artifacts.files import atomic_path

__all__ = ["record_video"]

# Minitaur's TinyRenderer takes ~0.27 s for a 960x720 frame; a smaller frame keeps a video to seconds.
_RENDER_KWARGS = {MINITAUR_ID: {"render_width": 480, "render_height": 360}}


def record_video(
    env_id: str,
    policy: Callable[[torch.Tensor], torch.Tensor] | None,
    path: Path,
    episodes: int = 3,
    seed: int = 0,
    max_steps: int = 1000,
    frame_skip: int = 1,
    env_kwargs: Mapping | None = None,
    observation_options: Mapping | None = None,
) -> Path:
    """Write an mp4 of ``episodes`` episodes of ``policy`` (random actions if ``None``) to ``path``, the env made
    with ``env_kwargs`` (a run's own), its observations read as ``observation_options`` (``make_env``'s
    ``observation_keys`` and ``frame_stack``) say."""
    gym_id = resolve_env_id(env_id)
    kwargs = {**_RENDER_KWARGS.get(gym_id, {}), **(env_kwargs or {})}
    if is_atari(gym_id):
        kwargs.setdefault("frameskip", 1)
    check_kwargs(gym_id, kwargs, env_id, EnvError)
    no_frames = (f"env {env_id!r} does not render frames: expected an env that takes render_mode='rgb_array' and "
                 "returns frames from render()")
    try:
        check_kwargs(gym_id, {**kwargs, "render_mode": "rgb_array"}, env_id, EnvError)
    except EnvError:
        raise EnvError(f"{no_frames} (its constructor takes no render_mode)") from None
    env = observed(gymnasium.make(gym_id, render_mode="rgb_array", **kwargs), env_id, **(observation_options or {}))
    if env.render_mode != "rgb_array":
        env.close()
        raise EnvError(f"{no_frames} (its render_mode is {env.render_mode!r} when asked for 'rgb_array')")
    env.action_space.seed(seed)
    fps = max(1, int(env.metadata.get("render_fps", 30)) // frame_skip)
    path = Path(path)
    path.parent.mkdir(parents=True, exist_ok=True)
    try:
        with (
            atomic_path(path, suffix=".mp4") as tmp,
            imageio.get_writer(tmp, fps=fps, codec="libx264", macro_block_size=8) as writer,
        ):
            for episode in range(episodes):
                obs, _ = env.reset(seed=seed + episode)
                writer.append_data(env.render())
                for t in range(max_steps):
                    if policy is None:
                        action = env.action_space.sample()
                    else:
                        with torch.no_grad():
                            obs = torch.as_tensor(np.asarray(obs))
                            out = policy(obs if obs.dtype == torch.uint8 else obs.float())
                        action = out.numpy()
                        if isinstance(env.action_space, gymnasium.spaces.Discrete):
                            action = int(action)
                    obs, _, terminated, truncated, _ = env.step(action)
                    if t % frame_skip == 0:
                        writer.append_data(env.render())
                    if terminated or truncated:
                        break
    finally:
        env.close()
    return path
