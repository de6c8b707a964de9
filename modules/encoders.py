"""Encoders: an image observation (``uint8 [C, H, W]``, frames stacked on C) to a feature vector the heads read.

``make_image_encoder`` picks by size, as SB3 and CleanRL do: from 36 px up, the Nature DQN network's
convolutions (Mnih et al. 2015: 32 8x8/4, 64 4x4/2, 64 3x3/1); below, for small grids such as MinAtar's
10x10, one 16-channel 3x3 convolution (the MinAtar paper's network). The encoder ends at the flattened
feature maps: the head's first hidden layer reads them, so ``fc_layer_params: [512]`` on an 84x84 stack is the
Nature network (then one output per action) and ``[128]`` on MinAtar the MinAtar paper's. The pixels are
scaled to [0, 1] inside the encoder, so the replay buffer and the exported policy keep uint8.

A Dict observation with images among its entries arrives joined into one float vector
(``rlpipe.envs.observations.DictObservation``); ``DictEncoder`` cuts each image's span out, reads it through its
own image encoder and passes the vector entries on beside the features, as SB3's ``CombinedExtractor`` does.

An encoder is a plain ``nn.Module`` with ``out_features``: put it in front of any head
(``nn.Sequential(encoder, MLP(...))``), in a TorchRL ``TensorDictModule`` like any network.
"""

from __future__ import annotations

import torch
from torch import nn

__all__ = ["DictEncoder", "FEATURES_KEY", "ImageEncoder", "NATURE_MIN_SIZE", "make_image_encoder"]

FEATURES_KEY = "encoded_observation"
"""where an update puts the features of an encoder it runs itself, for the heads in its loss to read (an
encoder shared by actor and critics: ``share_encoder``); never stored, never collected"""

NATURE_MIN_SIZE = 36
"""the smallest side the Nature DQN network takes (its three convolutions leave a 1x1 map at 36 px)"""


class ImageEncoder(nn.Module):
    """``scale * image`` through ``convolutions``, flattened: ``[..., C, H, W] -> [..., out_features]``."""

    def __init__(self, convolutions: nn.Module, out_features: int, scale: float):
        super().__init__()
        self.convolutions = convolutions
        self.out_features = out_features
        self.scale = scale

    def forward(self, image: torch.Tensor) -> torch.Tensor:
        batch = image.shape[:-3]
        x = image.reshape(-1, *image.shape[-3:]).float() * self.scale
        return self.convolutions(x).reshape(*batch, self.out_features)


def make_image_encoder(shape: tuple[int, int, int], scale: float = 1 / 255) -> ImageEncoder:
    """The encoder for images of ``shape`` (C, H, W) whose unit is ``scale`` of full brightness."""
    channels, height, width = shape
    if min(height, width) >= NATURE_MIN_SIZE:
        convolutions = nn.Sequential(
            nn.Conv2d(channels, 32, 8, stride=4), nn.ReLU(),
            nn.Conv2d(32, 64, 4, stride=2), nn.ReLU(),
            nn.Conv2d(64, 64, 3, stride=1), nn.ReLU(),
        )
    else:
        convolutions = nn.Sequential(nn.Conv2d(channels, 16, 3, stride=1), nn.ReLU())
    with torch.no_grad():
        flat = convolutions(torch.zeros(1, channels, height, width)).numel()
    return ImageEncoder(convolutions, flat, scale)


class DictEncoder(nn.Module):
    """A Dict observation joined into one vector, read entry by entry: ``[..., D] -> [..., out_features]``.

    ``layout`` maps each entry to its ``(start, stop)`` in the vector (``DictObservation.layout``), ``images`` each
    image entry to its ``((C, H, W), scale)``. An image's span is reshaped to ``[C, H, W]`` and read by its own
    ``make_image_encoder``; a vector entry is passed on as it is. The features follow the entries' order.
    """

    def __init__(self, layout: dict[str, tuple[int, int]], images: dict[str, tuple[tuple[int, int, int], float]]):
        super().__init__()
        self.spans = [(start, stop) for start, stop in layout.values()]
        self.shapes = [images[key][0] if key in images else None for key in layout]
        # a list, not a ModuleDict: an env's entry names may hold dots, which module names may not
        self.encoders = nn.ModuleList(make_image_encoder(*images[key]) for key in layout if key in images)
        widths, encoders = [], iter(self.encoders)
        for (start, stop), shape in zip(self.spans, self.shapes):
            widths.append(next(encoders).out_features if shape is not None else stop - start)
        self.out_features = sum(widths)

    def forward(self, observation: torch.Tensor) -> torch.Tensor:
        batch = observation.shape[:-1]
        features, encoders = [], iter(self.encoders)
        for (start, stop), shape in zip(self.spans, self.shapes):
            part = observation[..., start:stop]
            features.append(part if shape is None else next(encoders)(part.reshape(*batch, *shape)))
        return torch.cat(features, -1)
