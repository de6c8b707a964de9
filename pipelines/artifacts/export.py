"""The exported policy: TF-Agents' saved policy, as ONNX (data only) and as a ``torch.export`` program.

Each export writes, in ``RUN/policy``::

    policy.onnx          ONNX: a graph and its weights, data only (nothing in it runs as code):
                         safe to load from anyone; ONNX Runtime and robots' stacks run it
    policy.pt2           a torch.export archive: ``torch.export.load`` unpickles parts of it, so a
                         crafted file runs code: load it only from a source you trust
    step_NNNNNNN.onnx    the same two files of each export (the tutorials' ``policy_checkpoint_N``);
    step_NNNNNNN.pt2     the newest ``policy_keep`` are kept (0: all); ``policy.*`` is the latest
    policy.json          what goes in and out, how to make the env, which files exist

Both map a batch of observations ``[B, D]`` (float32) to actions ``[B, ...]``, without grad; with
ONNX Runtime alone::

    import numpy as np, onnxruntime
    policy = onnxruntime.InferenceSession("RUN/policy/policy.onnx")
    actions = policy.run(None, {"observation": np.asarray(observations, dtype=np.float32)})[0]

``load_policy`` is rlpipe's loader (``rlpipe eval`` and ``rlpipe video`` use it): ONNX by default,
a ``.pt2`` only when the caller says it trusts the file; what it returns takes one observation ``[D]``
as well as a batch, numpy (gives numpy) or torch (gives torch).

A module ONNX cannot express (an operator without an ONNX equivalent in a user's plug-in actor) is
exported as ``policy.pt2`` only, with a warning; ``load_policy`` then needs ``trust=True``.
"""

from __future__ import annotations

import copy
import io
import json
import logging
import math
import re
import warnings
from collections.abc import Mapping
from pathlib import Path
from typing import Any

import numpy as np
import torch
from torch import nn

from rlpipe.pipelines.artifacts.files import write_bytes_atomic, write_json_atomic
from rlpipe.pipelines.compat.torch import stderr_kept_on_success
from rlpipe.pipelines.errors import InputError

__all__ = ["ExportedPolicy", "OnnxExportWarning", "OnnxPolicy", "TorchExportPolicy", "available_steps", "export_policy",
           "load_policy"]

ONNX_OPSET = 17
"""ONNX Runtime 1.14 and later run it: old enough for the runtimes robots ship"""

_STEP_FILE = re.compile(r"step_(\d+)\.(onnx|pt2)")

FILES = {
    "policy.onnx": "ONNX (onnxruntime.InferenceSession): data only, nothing in it runs as code; safe to load from "
                   "anyone. Observations float32 [B, D] -> actions [B, ...]",
    "policy.pt2": "torch.export archive (torch.export.load(...).module()): loading it unpickles parts of it, which "
                  "can run code; load it only from a source you trust. Observations float32 [B, D] -> actions [B, ...]",
    "step_NNNNNNN.onnx, step_NNNNNNN.pt2": "the same two formats, one pair per export at that iteration",
}


class OnnxExportWarning(UserWarning):
    """A policy could not be exported as ONNX; only the ``.pt2`` (trusted sources only) was written."""


def step_name(step: int, suffix: str) -> str:
    return f"step_{step:07d}{suffix}"


def available_steps(folder: Path) -> list[int]:
    """The iterations at which the exports kept in ``folder`` were made, oldest first."""
    folder = Path(folder)
    if not folder.is_dir():
        return []
    return sorted({int(m.group(1)) for p in folder.iterdir() if (m := _STEP_FILE.fullmatch(p.name))})


# --- writing -----------------------------------------------------------------------------------------


ImageInputs = dict[str, tuple[tuple[int, ...], bool]]
"""the images among a Dict env's entries: each one's shape as the env gives it, and whether its channels come last"""

DiscreteInputs = dict[str, tuple[tuple[int, ...], list[int], list[int]]]
"""the discrete entries (Discrete, MultiDiscrete) among a Dict env's: each one's shape as the env gives it (() for a
Discrete), and the sizes and starts of its values, flattened (``envs.observations.discrete_entries``)"""

ImageFrame = tuple[tuple[int, ...], bool]
"""an image observation's frame as the env gives it (HxW, HxWxC or CxHxW), and whether its channels come last"""


class OneHot(nn.Module):
    """A discrete entry's integers ``[B, *shape]`` to the one-hot vector ``[B, sum(nvec)]`` the networks read, as
    ``gymnasium.spaces.flatten`` makes it: each value less its start, one-hot in its own span."""

    def __init__(self, nvec: list[int], start: list[int]):
        super().__init__()
        offsets = torch.tensor([0, *nvec[:-1]]).cumsum(0)
        self.register_buffer("shift", offsets - torch.tensor(start), persistent=False)
        self.register_buffer("slots", torch.arange(sum(nvec)), persistent=False)

    def forward(self, entry: torch.Tensor) -> torch.Tensor:
        index = entry.reshape(entry.shape[0], -1).to(torch.int64) + self.shift
        return (index.unsqueeze(-1) == self.slots).to(torch.float32).sum(1)


class NamedEntries(nn.Module):
    """``module`` on a Dict env's entries given one by one, by name: ``forward(*entries)`` joins them in the env's
    order (``DictObservation``'s) into the vector ``module`` reads. A vector entry is a float32 ``[B, size]``; an
    image entry (``images``) a uint8 ``[B, *shape]`` as the env gives it, put channels first and flattened; a
    discrete entry (``discrete``) its int64 values ``[B, *shape]``, made one-hot."""

    def __init__(self, module: nn.Module, sizes: dict[str, int], images: ImageInputs | None = None,
                 discrete: DiscreteInputs | None = None):
        super().__init__()
        self.module, self.sizes = module, dict(sizes)
        images, discrete = dict(images or {}), dict(discrete or {})
        self.inputs = {name: (tuple(images[name][0]), torch.uint8) if name in images
                       else (tuple(discrete[name][0]), torch.int64) if name in discrete
                       else ((size,), torch.float32) for name, size in self.sizes.items()}
        self._channels_last = [name in images and images[name][1] for name in self.sizes]
        # entry names are the env's (a Dict may call one "keys"): the one-hot maps go by position
        self.one_hot = nn.ModuleList(OneHot(*discrete[name][1:]) for name in self.sizes if name in discrete)
        slots = iter(range(len(self.one_hot)))
        self._one_hot_of = [next(slots) if name in discrete else None for name in self.sizes]

    def forward(self, *entries: torch.Tensor) -> torch.Tensor:
        joined = [self.one_hot[slot](entry) if slot is not None
                  else (entry.permute(0, 3, 1, 2) if last else entry).flatten(1).to(torch.float32)
                  for entry, last, slot in zip(entries, self._channels_last, self._one_hot_of)]
        return self.module(torch.cat(joined, -1))


class OnEnvFrames(nn.Module):
    """``module`` (on rlpipe's image stacks, ``uint8 [B, C, H, W]``) on the env's own frames, ``uint8 [B, *shape]``
    as the env gives them: one frame (``frame_stack=1``), put channels first as ``ImageObservation`` does."""

    def __init__(self, module: nn.Module, frame: ImageFrame):
        super().__init__()
        self.module, self.shape, self.channels_last = module, tuple(frame[0]), frame[1]

    def forward(self, frames: torch.Tensor) -> torch.Tensor:
        if len(self.shape) == 2:
            return self.module(frames.unsqueeze(1))
        return self.module(frames.permute(0, 3, 1, 2) if self.channels_last else frames)


def export_policy(module: nn.Module, observation_dim: int | tuple[int, ...], folder: Path, info: dict, *,
                  step: int | None = None, keep: int = 0, dtype: torch.dtype = torch.float32,
                  entries: dict[str, tuple[int, int]] | None = None, images: ImageInputs | None = None,
                  discrete: DiscreteInputs | None = None, frame: ImageFrame | None = None) -> Path:
    """Export ``module`` (observations ``[B, observation_dim]``, or ``[B, *shape]`` of ``dtype`` for a tuple:
    an image stack ``uint8 [B, C, H, W]`` -> actions ``[B, ...]``) to ``folder``. ``entries``: a Dict env's
    entries and where each lies in the observation vector: the exported programs then take them as inputs of
    those names (``NamedEntries``), the env's own observation; ``images``: the images among them, taken as uint8
    in the env's own shape; ``discrete``: its discrete entries, taken as their integers. ``frame``: an image
    observation of one frame (no stack), taken as the env gives it (``OnEnvFrames``) rather than channels first.

    Writes ``policy.onnx`` (unless ONNX cannot express the module: then a warning), ``policy.pt2``
    and ``policy.json``, each atomically; with ``step``, also ``step_NNNNNNN.onnx/.pt2``, keeping the
    newest ``keep`` steps (0: all). Returns the path of the latest policy, ``.onnx`` where written.
    """
    folder = Path(folder)
    folder.mkdir(parents=True, exist_ok=True)
    # A copy: the caller's module keeps training; here its parameters stop asking for grad, so
    # the exported programs give actions without grad (the .pt2 keeps each parameter's flag).
    module = copy.deepcopy(module).eval()
    for parameter in module.parameters():
        parameter.requires_grad_(False)
    shape = (observation_dim,) if isinstance(observation_dim, int) else tuple(observation_dim)
    stack = shape
    if entries:
        module = NamedEntries(module, {name: stop - start for name, (start, stop) in entries.items()}, images, discrete)
        inputs = module.inputs
    elif frame is not None:
        module, shape = OnEnvFrames(module, frame), tuple(frame[0])
        inputs = {"observation": (shape, dtype)}
    else:
        inputs = {"observation": (shape, dtype)}
    examples = tuple(torch.zeros(2, *size, dtype=kind) for size, kind in inputs.values())
    batch = torch.export.Dim("batch", min=1, max=1 << 20)
    dynamic = tuple({0: batch} for _ in examples)
    # NamedEntries.forward(*entries): one parameter, whose shapes are the tuple of its entries'
    program = torch.export.export(module, examples, dynamic_shapes=(dynamic,) if entries else dynamic, strict=False)
    pt2 = io.BytesIO()
    torch.export.save(program, pt2)
    files = {".pt2": pt2.getvalue(), ".onnx": _onnx_model(module, inputs)}
    for suffix, data in files.items():
        if data is not None:
            if step is not None:
                write_bytes_atomic(folder / step_name(step, suffix), data)
            write_bytes_atomic(folder / f"policy{suffix}", data)
    onnx_model = files[".onnx"]
    if onnx_model is None:  # an older export's ONNX is not this policy
        (folder / "policy.onnx").unlink(missing_ok=True)
    if step is not None and keep > 0:
        for old in available_steps(folder)[:-keep]:
            for suffix in (".onnx", ".pt2"):
                (folder / step_name(old, suffix)).unlink(missing_ok=True)
    steps = available_steps(folder)
    write_json_atomic(folder / "policy.json", {
        "observation_dim": shape[0] if len(shape) == 1 else None, "observation_shape": list(shape),
        "observation_dtype": str(dtype).removeprefix("torch."),
        "inputs": {name: list(size) for name, (size, _) in inputs.items()},
        **({"image_inputs": {name: {"shape": list(size), "channels_last": last} for name, (size, last) in images.items()}}
           if entries and images else {}),
        **({"discrete_inputs": {name: {"shape": list(size), "nvec": list(nvec), "start": list(start)}
                                for name, (size, nvec, start) in discrete.items()}} if entries and discrete else {}),
        **({"image_input": {"shape": list(shape), "channels_last": frame[1], "stack_shape": list(stack)}}
           if frame is not None and not entries else {}),
        **info, "step": step, "steps": steps,
        "env_recipe": _env_recipe(info.get("env"), info.get("env_kwargs") or {},
                                  _observations_said(inputs, shape, info, frame if not entries else None)),
        "files": {name: text for name, text in FILES.items() if (folder / name).exists() or name.startswith("step_") and steps},
    })
    return folder / ("policy.pt2" if onnx_model is None else "policy.onnx")


def _observations_said(inputs: dict[str, tuple[tuple[int, ...], torch.dtype]], shape: tuple[int, ...],
                       info: dict, frame: ImageFrame | None = None) -> str:
    """What the exported policy takes, in words, for ``policy.json``."""
    dtype = inputs[next(iter(inputs))][1]
    if len(inputs) > 1:
        images = [name for name, (_, kind) in inputs.items() if kind == torch.uint8]
        counts = [name for name, (_, kind) in inputs.items() if kind == torch.int64]
        return (f"the env's own Dict observation: its entries {', '.join(inputs)} as inputs of those names, float32"
                + (f" (the image{'s' if len(images) > 1 else ''} {', '.join(images)} uint8, as the env gives "
                   f"{'them' if len(images) > 1 else 'it'})" if images else "")
                + (f" (the discrete {', '.join(counts)} int64, the env's own values)" if counts else "")
                + " (rlpipe's loader also takes them joined in that order, as the networks read them)")
    if frame is not None:
        return (f"the env's own image, one frame as the env gives it: uint8 {list(shape)}"
                + (", channels last" if frame[1] else "") + " (bool frames as 0/1)")
    if len(shape) == 3:
        stack = info.get("frame_stack", 1)
        return (f"the env's image as {str(dtype).removeprefix('torch.')} [C, H, W] = {list(shape)}, channels first"
                + (f", its last {stack} frames stacked on C (oldest first)" if stack > 1 else ""))
    return "the env's own, as float32 (no normalisation)"


def _env_recipe(env: str | None, kwargs: dict[str, Any], observations: str = "the env's own, as float32 "
                "(no normalisation)") -> dict[str, Any]:
    """How a person makes the env the policy acts in, with gymnasium alone (and rlpipe for Minitaur), or with
    the trainer's own module for an env named ``module:Target``."""
    from rlpipe.envs import EnvError, resolve_env_id
    from rlpipe.envs.user import NAMESPACE, is_user_env

    try:
        gym_id = resolve_env_id(env) if env else None
    except EnvError:
        gym_id = None
    if gym_id is None:
        return {"gymnasium_id": None, "imports": [], "make": None,
                "note": f"{env!r} is not a gymnasium id: the env came from the trainer's own code"}
    args = ", ".join(f"{k}={v!r}" for k, v in kwargs.items())
    if is_user_env(env):
        module, _, name = env.partition(":")
        if gym_id.startswith(f"{NAMESPACE}/"):  # a class or function of the trainer's module: called as rlpipe did
            return {"gymnasium_id": None, "imports": [module], "make": f"from {module} import {name}; env = {name}({args})",
                    "observations": observations}
        gym_id = env  # gymnasium's own module:id form imports the module itself
    imports = ["rlpipe.envs"] if gym_id.startswith("rlpipe/") else []  # registers rlpipe's envs with gymnasium
    make = "".join(f"import {m}; " for m in imports) + f"import gymnasium; env = gymnasium.make({gym_id!r}{', ' + args if args else ''})"
    return {"gymnasium_id": gym_id, "imports": imports, "make": make, "observations": observations}


def _onnx_model(module: nn.Module, inputs: dict[str, tuple[tuple[int, ...], torch.dtype]]) -> bytes | None:
    """``module`` as an ONNX model (``observation [batch, D] -> action [batch, ...]``, or each of a Dict env's
    ``inputs`` by name), checked against the module; None with a warning if ONNX cannot express it.

    torch 2.13's TorchScript-based exporter (``dynamo=False``) is used on purpose: it is still
    supported there, exports our policies in ~0.02 s (the dynamo exporter takes ~1.3 s per export
    and needs onnxscript), and traces the TensorDict policies of plug-in actors as well.
    """
    import onnx

    buffer = io.BytesIO()
    try:
        with warnings.catch_warnings(), stderr_kept_on_success():  # compat: torch 2.13 logs the graph
            warnings.simplefilter("ignore")  # its DeprecationWarning, and tracer notes on TensorDict code
            examples = tuple(torch.zeros(2, *size, dtype=kind) for size, kind in inputs.values())
            names = list(inputs)
            torch.onnx.export(module, examples, buffer, dynamo=False, opset_version=ONNX_OPSET, input_names=names,
                              output_names=["action"],
                              dynamic_axes={**{n: {0: "batch"} for n in names}, "action": {0: "batch"}})
        data = buffer.getvalue()
        onnx.checker.check_model(onnx.load_from_string(data), full_check=True)
        _check_same_actions(module, data, inputs)
    except Exception as exc:  # an operator ONNX lacks, a graph the tracer cannot follow, different actions
        message = str(exc).strip().splitlines()[0] if str(exc).strip() else ""
        warnings.warn(f"the policy could not be exported as ONNX ({type(exc).__name__}: {message[:200]}); "
                      "only policy.pt2 is written, which rlpipe eval/video load only with --trust",
                      OnnxExportWarning, stacklevel=3)
        return None
    return data


def _check_same_actions(module: nn.Module, onnx_model: bytes,
                        inputs: dict[str, tuple[tuple[int, ...], torch.dtype]]) -> None:
    """Raise if ONNX Runtime's actions differ from the module's (a tracer can miss Python control flow)."""
    generator = torch.Generator().manual_seed(0)
    observations = [torch.randn(8, *shape, generator=generator) * 3 if dtype.is_floating_point
                    else torch.randint(0, 256, (8, *shape), generator=generator).to(dtype)
                    for shape, dtype in inputs.values()]
    with torch.no_grad():
        expected = module(*observations)
    got = OnnxPolicy(onnx_model).act_entries(observations)
    if got.dtype.is_floating_point:
        torch.testing.assert_close(got, expected, rtol=1e-4, atol=1e-5, check_dtype=False)
    elif not torch.equal(got, expected):
        raise ValueError("ONNX Runtime's actions differ from the module's")


# --- loading -----------------------------------------------------------------------------------------


def _trailing(shape: tuple[int, ...], size: int) -> tuple[int, ...]:
    """The trailing axes of a vector entry's ``shape`` that hold its ``size`` values (a matrix Box's two, a vector's
    one); what comes before them is the batch."""
    held, axes = 1, 0
    while axes < len(shape) and (held < size or axes == 0):
        axes += 1
        held *= shape[-axes]
    return tuple(shape[len(shape) - axes:])


class ExportedPolicy(nn.Module):
    """An exported policy as a module: observations ``[D]`` or ``[..., D]`` -> actions, without grad.

    Takes a torch tensor (gives one back) or anything numpy takes (gives a numpy array); ``path``
    is the file it came from.
    """

    path: Path
    entry_sizes: dict[str, int] | None = None
    """a Dict env's entries the policy takes by name, in the env's order, and each one's length in the joined
    vector (None: one observation input)"""
    entry_images: ImageInputs = {}
    """the images among those entries: each one's shape as the env gives it, and whether its channels come last"""
    entry_discrete: DiscreteInputs = {}
    """the discrete entries among them: each one's shape, and the sizes and starts of its values"""
    observation_ndim: int = 1
    """dimensions of one observation: 1 for a vector, 3 for an image stack [C, H, W]"""
    observation_shape: tuple[int, ...] | None = None
    """one observation's shape, where ``policy.json`` says it"""
    observation_dtype: torch.dtype = torch.float32
    frame: tuple[tuple[int, ...], bool, tuple[int, ...]] | None = None
    """an image policy on the env's own frames: their shape, whether channels come last, and the shape of the
    channels-first stack rlpipe's env gives (taken as well)"""

    def forward(self, observation):
        """Actions for ``observation``: one observation or a batch, the env's own (a Dict env's as a mapping of its
        entries, or as the joined vector the networks read), torch (gives torch) or numpy (gives numpy)."""
        if isinstance(observation, Mapping):
            return self._on_entries(observation)
        as_numpy = not isinstance(observation, torch.Tensor)
        obs = torch.as_tensor(np.asarray(observation) if as_numpy else observation, dtype=self.observation_dtype)
        if self.frame is not None:
            obs = self._as_frames(obs)
        ndim = self.observation_ndim
        self._check_shape("an observation", obs.shape, self.observation_shape)
        with torch.no_grad():
            batch = obs.reshape(-1, *obs.shape[obs.ndim - ndim:])
            action = self.act(batch.cpu())
        action = action.reshape((*obs.shape[:obs.ndim - ndim], *action.shape[1:])).to(obs.device)
        return action.numpy() if as_numpy else action

    def _as_frames(self, obs: torch.Tensor) -> torch.Tensor:
        """The env's own frames: as given, or from rlpipe's channels-first stacks ``[..., C, H, W]``."""
        shape, last, stack = self.frame
        own = tuple(obs.shape[obs.ndim - len(shape):]) == shape
        if own and not (len(shape) == 2 and tuple(obs.shape) == stack):  # [1, H, W]: one stack of an HxW frame
            return obs
        if tuple(obs.shape[-3:]) != stack:
            return obs  # _check_shape names what is expected
        if len(shape) == 2:
            return obs.squeeze(-3)
        return obs.movedim(-3, -1) if last else obs

    def _check_shape(self, what: str, got: torch.Size, expected: tuple[int, ...] | None) -> None:
        """ValueError, one line, where ``got`` does not end with ``expected`` (one observation's shape)."""
        if expected is None or (len(got) >= len(expected) and tuple(got[len(got) - len(expected):]) == tuple(expected)):
            return
        also = f", or rlpipe's channels-first stack {list(self.frame[2])}" if self.frame is not None else ""
        raise ValueError(f"{what} of shape {list(got)}: this policy takes {list(expected)}{also} (one observation, "
                         f"or a batch of them on leading axes), as policy.json's inputs say")

    def _on_entries(self, observation: Mapping):
        """Actions for a Dict env's own observation (one, or a batch): each entry as the env gives it."""
        if self.entry_sizes is None:
            raise ValueError("this policy takes one observation, not a mapping of entries")
        first = observation[next(iter(self.entry_sizes))]
        as_numpy = not isinstance(first, torch.Tensor)
        missing = [name for name in self.entry_sizes if name not in observation]
        if missing:
            raise ValueError(f"an observation without {', '.join(map(repr, missing))}: this policy takes the entries "
                             f"{', '.join(map(repr, self.entry_sizes))}, as policy.json's inputs say")
        parts, batch = [], None
        for name, size in self.entry_sizes.items():
            image, discrete = name in self.entry_images, name in self.entry_discrete
            dtype = torch.uint8 if image else torch.int64 if discrete else torch.float32
            part = observation[name]
            part = torch.as_tensor(np.asarray(part, dtype=_NUMPY[dtype]) if as_numpy else part)
            shape = (self.entry_images[name][0] if image else self.entry_discrete[name][0] if discrete
                     else _trailing(part.shape, size))
            if not (image or discrete) and math.prod(shape) != size:
                shape = (size,)  # not this entry's: _check_shape names it
            self._check_shape(f"entry {name!r}", part.shape, shape)
            leading = part.shape[:part.ndim - len(shape)]
            if batch is not None and leading != batch:
                raise ValueError(f"entry {name!r} of shape {list(part.shape)}: a batch of {list(leading)} where the "
                                 f"entries before it have {list(batch)}; this policy takes {name!r} as "
                                 f"{list(shape)} per observation, as policy.json's inputs say")
            batch = leading
            parts.append(part.reshape(-1, *(shape if image or discrete else (size,))).to(dtype).cpu())
        with torch.no_grad():
            action = self.act_entries(parts)
        action = action.reshape((*batch, *action.shape[1:])).to(first.device if not as_numpy else "cpu")
        return action.numpy() if as_numpy else action

    def act(self, observations: torch.Tensor) -> torch.Tensor:
        """A batch ``[B, D]`` -> actions ``[B, ...]`` (a Dict env's: its entries joined, as the networks read them)."""
        if self.entry_sizes is None:
            return self.act_observations(observations)
        parts = []
        for name, part in zip(self.entry_sizes, observations.split(list(self.entry_sizes.values()), -1)):
            if name in self.entry_images:  # back to the env's own: uint8, its channels where the env has them
                shape, last = self.entry_images[name]
                first = (shape[-1], *shape[:-1]) if last else shape
                part = part.reshape(-1, *first)
                part = (part.movedim(1, -1) if last else part).round().to(torch.uint8)
            elif name in self.entry_discrete:  # back to the env's own values, from their one-hot spans
                shape, nvec, start = self.entry_discrete[name]
                values = [span.argmax(-1) for span in part.split(nvec, -1)]
                part = (torch.stack(values, -1) + torch.tensor(start)).reshape(-1, *shape)
            parts.append(part)
        return self.act_entries(parts)

    def act_observations(self, observations: torch.Tensor) -> torch.Tensor:
        """One observation input: a batch ``[B, *shape]`` -> actions ``[B, ...]``."""
        raise NotImplementedError

    def act_entries(self, entries: list[torch.Tensor]) -> torch.Tensor:
        """A Dict env's entries, each a batch ``[B, *its shape]`` in the env's order -> actions ``[B, ...]``."""
        raise NotImplementedError

    def train(self, mode: bool = True) -> ExportedPolicy:
        # An exported policy has no training mode; torch.export's modules refuse to be told one.
        self.training = mode
        return self


_ONNX_DTYPES = {"tensor(float)": torch.float32, "tensor(uint8)": torch.uint8}
_NUMPY = {torch.float32: np.float32, torch.uint8: np.uint8, torch.int64: np.int64}


class OnnxPolicy(ExportedPolicy):
    """An ONNX policy, run by ONNX Runtime on one thread (a policy's matmuls are too small for more)."""

    def __init__(self, model: bytes):
        super().__init__()
        import onnxruntime

        options = onnxruntime.SessionOptions()
        options.intra_op_num_threads = options.inter_op_num_threads = 1
        options.log_severity_level = 3  # errors only: the caller gets them as exceptions
        # From bytes, not a path: weights stored outside the file ("external data") have nothing to
        # resolve against, so a crafted model cannot make the runtime read other files.
        self.session = onnxruntime.InferenceSession(model, options, providers=["CPUExecutionProvider"])
        inputs = self.session.get_inputs()
        model_input = inputs[0]
        self.input_name = model_input.name
        if len(inputs) > 1:  # a Dict env's entries, by name (NamedEntries); joined, a float32 vector
            # an image entry's channel layout is in policy.json (load_policy reads it); its length is the same
            self.entry_sizes = {i.name: int(np.prod(i.shape[1:])) for i in inputs}
            return
        # the model says what it takes: float32 vectors, or uint8 image stacks [B, C, H, W]
        self.observation_dtype = _ONNX_DTYPES.get(model_input.type, torch.float32)
        self.observation_ndim = max(1, len(model_input.shape) - 1)

    def act_observations(self, observations: torch.Tensor) -> torch.Tensor:
        return torch.from_numpy(self.session.run(None, {self.input_name: np.ascontiguousarray(observations.numpy())})[0])

    def act_entries(self, entries: list[torch.Tensor]) -> torch.Tensor:
        names = [i.name for i in self.session.get_inputs()]
        feed = {name: np.ascontiguousarray(entry.numpy()) for name, entry in zip(names, entries)}
        return torch.from_numpy(self.session.run(None, feed)[0])


class TorchExportPolicy(ExportedPolicy):
    """A ``.pt2`` program (batched input), loaded by ``torch.export.load``: trusted files only."""

    def __init__(self, program: nn.Module):
        super().__init__()
        self.program = program

    def act_observations(self, observations: torch.Tensor) -> torch.Tensor:
        return self.program(observations)

    def act_entries(self, entries: list[torch.Tensor]) -> torch.Tensor:
        return self.program(*entries)


def load_policy(folder: Path, *, step: int | None = None, trust: bool = False) -> tuple[ExportedPolicy, dict]:
    """The exported policy of a run (``RUN/policy``), the latest or that of ``step``, and its description.

    ONNX (``.onnx``, data only) is loaded when there is one. A ``.pt2`` alone is loaded only with
    ``trust=True``: ``torch.export.load`` unpickles parts of it, so a crafted file runs code.
    ``InputError`` if there is no such policy, it is only a ``.pt2`` and not trusted, or it is unusable.
    """
    folder = Path(folder)
    if step is None:
        onnx_path, pt2_path = folder / "policy.onnx", folder / "policy.pt2"
    else:
        steps = available_steps(folder)
        if step not in steps:
            have = ", ".join(map(str, steps)) if steps else "none (the run kept no policy history)"
            raise InputError(f"--step {step}: {folder} holds no policy exported at iteration {step}; "
                             f"expected one of the exported steps: {have}")
        onnx_path, pt2_path = folder / step_name(step, ".onnx"), folder / step_name(step, ".pt2")
    try:
        info = json.loads((folder / "policy.json").read_text())
    except (OSError, ValueError):
        info = {}
    dim = info.get("observation_dim")
    shape = info.get("observation_shape") or ([dim] if isinstance(dim, int) else None)
    dtype = getattr(torch, str(info.get("observation_dtype", "float32")), None)
    if not isinstance(dtype, torch.dtype):
        raise InputError(f"{folder / 'policy.json'}: observation_dtype {info.get('observation_dtype')!r} is not a torch "
                         "dtype; expected the file an export wrote (e.g. 'float32', 'uint8')")
    if onnx_path.exists():
        policy = _load(onnx_path, lambda: OnnxPolicy(onnx_path.read_bytes()), shape, dtype, info)
    elif pt2_path.exists():
        if not trust:
            raise InputError(
                f"{pt2_path}: this policy exists only as a torch.export archive, and loading one unpickles parts of it, "
                f"which can run code; pass --trust (trust=True) to load it if you trust where it came from "
                f"(a policy.onnx, data only, would load without)")
        policy = _load(pt2_path, lambda: TorchExportPolicy(_torch_export_load(pt2_path)), shape, dtype, info)
    else:
        raise InputError(f"{folder / 'policy.onnx'}: no exported policy; expected a run that finished or saved its policy")
    policy.path = onnx_path if onnx_path.exists() else pt2_path
    return policy, info


def _load(path: Path, make, shape: list[int] | None, dtype: torch.dtype, info: dict | None = None) -> ExportedPolicy:
    try:
        policy = make()
        policy.observation_dtype = dtype
        inputs = (info or {}).get("inputs") or {}
        if len(inputs) > 1:  # a Dict env's entries (the .pt2 program takes them one by one too)
            spans = (info or {}).get("observation_entries") or {}
            policy.entry_sizes = {name: int(spans[name][1] - spans[name][0]) if name in spans else int(size[-1])
                                  for name, size in inputs.items()}
            policy.entry_images = {name: (tuple(image["shape"]), bool(image["channels_last"]))
                                   for name, image in ((info or {}).get("image_inputs") or {}).items()}
            policy.entry_discrete = {name: (tuple(entry["shape"]), list(entry["nvec"]), list(entry["start"]))
                                     for name, entry in ((info or {}).get("discrete_inputs") or {}).items()}
        frame = (info or {}).get("image_input")
        if frame:
            policy.frame = (tuple(frame["shape"]), bool(frame["channels_last"]), tuple(frame["stack_shape"]))
        if shape:  # a file that loads but is not this run's policy fails here, not mid-episode
            policy.observation_ndim, policy.observation_shape = len(shape), tuple(shape)
            policy(torch.zeros(1, *shape, dtype=dtype))
        return policy
    except Exception as exc:  # onnxruntime and torch.export raise many kinds on a damaged file
        raise InputError(f"{path}: corrupt or not an exported policy ({type(exc).__name__}); "
                         "expected the policy a run exported") from exc


def _torch_export_load(path: Path) -> nn.Module:
    # torch.export logs a traceback of its own for a damaged file; the caller's own
    # logging.disable level is kept while loading and restored after.
    disabled = logging.root.manager.disable
    logging.disable(max(disabled, logging.WARNING))
    try:
        return torch.export.load(path).module()
    finally:
        logging.disable(disabled)
