"""Pipelines: one module per algorithm (``dqn``, ``td3``, ``sac``, ``crossq``) on one shared loop.

    from rlpipe.pipelines import dqn
    result = dqn.DQN(dqn.preset("dqn")).train("runs/dqn")

The map of this package (each room's ``__init__`` maps its own modules):

    base         OffPolicyPipeline: the algorithm contract, the plug-in surface (env, eval_env,
                 actor, qvalue, loss_module, observation_key) and its assembly (device, optimisers,
                 replay buffer, collector backend); ``train`` hands the run to ``training.run.Run``
    own_parts    what a user's own env, eval env and modules must be, checked before anything is built
    algos        ALGOS: each algorithm's name -> its pipeline class (``pipeline_class``)
    dqn, td3, sac, crossq  the algorithms: each a config, its modules and loss, one ``update``
    config       the shared keys (``TrainConfig``), each key's rule declared with its field, overrides
    errors       InputError (one line, exit 2), TrainingDiverged
    training/    the loop and what runs inside it: the run's lifecycle, Loop, the triggers (log, eval,
                 export, checkpoint, video), evaluations, run state, rate limiter, meters, threads
    workers/     what collects and evaluates: the collector-backend interface and its local and Ray
                 backends, the evaluators, supervision
    artifacts/   what a run leaves on disk: run directory, checkpoints, exported policy, video, files
    system/      the operating system's side: stop signals, the fault hook, child processes, memory
    compat/      each workaround for a library version, one module per library
    analysis/    reading finished runs: tables, statistics, plots, report pages

Presets are YAML files (the top-level ``presets/`` folder, installed as ``rlpipe.presets``), named after the
tutorials they reproduce (``sac``, ``td3``, ``dqn``) or the task they are sized for (``sac-pendulum``,
``dqn-cartpole-v0``, ...); ``presets`` reads and writes them (``presets.names()`` lists them, ``presets.load``,
``presets.save``), ``preset_info(name)`` says what each is for (env, target returns), ``size_hint`` what to use
instead when a preset meets another env.
"""

from __future__ import annotations

from rlpipe.pipelines import presets
from rlpipe.pipelines.algos import ALGOS, pipeline_class
from rlpipe.pipelines.config import PresetInfo, layer_sizes
from rlpipe.pipelines.errors import InputError

__all__ = ["ALGOS", "InputError", "PresetInfo", "device_hint", "pipeline_class", "preset_info", "presets",
           "resolve_preset", "size_hint", "sized_presets"]

def resolve_preset(name: str):
    """(algo, config) for a preset's name such as 'dqn' or 'td3-hopper', or a preset file's path (``presets.load``)."""
    return presets.load(name)


def preset_info(name: str) -> PresetInfo | None:
    """The task preset ``name`` (a name or a file) is for (env, target returns, whether it is sized for time to
    them); None for an unknown name or a preset that declares none."""
    if not presets.is_file(name) and name not in presets.names():
        return None
    return presets.info(name)


def sized_presets(env: str) -> list[str]:
    """The presets sized for time to a target on ``env``, in ``presets.names()`` order."""
    return [name for name in presets.names()
            if (info := presets.info(name)) is not None and info.sized and info.env == env]


def size_hint(name: str, cfg) -> str | None:
    """One line for a preset (a name or a file) pointed at an env other than its own (``rlpipe train sac
    env=Pendulum-v1``): the preset sized for that env, or, for an env no preset knows, the keys that size a run
    and the command that sizes one (``rlpipe train sac`` pointed at an env is sized for it: ``sizing``). None when
    ``cfg`` trains on the preset's own env."""
    preset = presets.read(name)
    own = preset.config.env
    if cfg.env == own:
        return None
    fits = sized_presets(cfg.env)
    info = preset.info
    what = f"preset {name!r} ({info.task}) is sized for {own}" if info and info.task else f"preset {name!r} is sized for {own}"
    if fits:
        best = next((p for p in fits if presets.names()[p] == preset.algo), fits[0])
        target = preset_info(best).target
        to = f" (to {target:g})" if target is not None else ""
        return f"{what}; the one sized for {cfg.env}{to} is {best!r}: rlpipe train {best}"
    networks = "/".join(layer_sizes(cfg))
    sized = (f"; `rlpipe train {preset.algo} env={cfg.env}` sizes a run from the env (pipelines/sizing.py)"
             if preset.algo in ("sac", "td3", "dqn") else "")
    return (f"{what} and none is sized for {cfg.env}; what matters most for a run's size: {networks} (networks), "
            f"initial_collect_steps (random steps), collector.workers and collector.sync (a process for the env, "
            f"or the learner's own), batch_size, num_threads{sized}")


def device_hint(cfg) -> str | None:
    """One line for a run on a GPU whose collect policy acts on the GPU (``collector.policy_device=''``): each
    env step then waits on a GPU call, and the loop runs several times slower than it can. None otherwise."""
    c = cfg.collector
    if not str(cfg.device).startswith("cuda") or c.policy_device or c.backend != "local":
        return None
    return (f"device={cfg.device} with the collect policy on the GPU: each env step waits on a GPU call; on an H200 "
            "(BENCHMARKS.md, 'Whole training loops on a GPU') SAC on HalfCheetah-v5 ran 1,572 env steps/s with "
            "collector.policy_device=cpu collector.sync=false collector.frames_per_batch=32 (a collector process acting "
            "from a CPU copy while the GPU updates) against 235 with one step a block and 756 with 32, the policy on "
            "the GPU")
