"""``rlpipe bench floor``: each algorithm's update against its arithmetic floor on this CPU.

The floor of one update is its matmul FLOPs (counted from the layer sizes, below) divided by the
rate this machine's BLAS reaches on the same kind of matmul ([256, 256] x [256, 256], measured in
the same run, one thread). The fraction reached is floor / measured update time: 1.0 would be an
update that does nothing but its matmuls at full speed. Elementwise work (activations, the loss,
Adam, the target update) is left out of the floor, so it shows up as the gap.

An update is timed as the pipeline makes it (``pipeline.update_step`` on a fixed replay-sized
batch, one learner thread, the median over chunks), without sampling or collection.
"""

from __future__ import annotations

import statistics
import time

import torch

# (preset, overrides, what it is): CleanRL's network and batch sizes, and the tutorials' own.
CASES = [
    ("sac", ["env=Pendulum-v1"], "SAC, Pendulum-v1, 256x256, batch 256 (CleanRL's sizes; the tutorial's too)"),
    ("sac", [], "SAC, Minitaur (28 obs, 8 actions), 256x256, batch 256 (the tutorial)"),
    ("sac-minitaur", [], "SAC, Minitaur, 64x64, batch 256 (`sac-minitaur`)"),
    ("sac-minitaur", ["critic_layer_norm=true"], "SAC, Minitaur, 64x64, batch 256, critics with LayerNorm"),
    ("td3", ["actor_fc_layer_params=[256,256]", "critic_fc_layer_params=[256,256]"],
     "TD3, Pendulum-v1, 256x256, batch 256 (CleanRL's sizes)"),
    ("td3", [], "TD3, Pendulum-v1, 256, batch 256 (the tutorial)"),
    ("dqn-cleanrl", [], "DQN, CartPole-v1, 120-84, batch 128 (CleanRL's)"),
    ("crossq-pendulum", ["actor_fc_layer_params=[256,256]", "critic_fc_layer_params=[256,256]"],
     "CrossQ, Pendulum-v1, 256x256 batch-renormalised critics, batch 256 (SAC's sizes above)"),
]


def mlp_flops(sizes: list[int], batch: int, *, forward: bool = True, weight_grads: bool = False,
              input_grads: bool = False, first_input_grad: bool = False) -> int:
    """Matmul FLOPs (2 per multiply-add) of an MLP ``sizes[0] -> ... -> sizes[-1]`` on ``batch`` rows:
    its forward, the gradients of its weights, and of its layers' inputs (the first layer's only
    with ``first_input_grad``: the observation needs none, an action being optimised does)."""
    pairs = list(zip(sizes[:-1], sizes[1:], strict=True))
    one = [2 * batch * a * b for a, b in pairs]
    total = sum(one) if forward else 0
    if weight_grads:
        total += sum(one)
    if input_grads:
        total += sum(one[1:]) + (one[0] if first_input_grad else 0)
    return total


def update_flops(pipeline) -> int:
    """Matmul FLOPs of one update of a SAC, TD3, DQN or CrossQ pipeline built with rlpipe's networks."""
    cfg, b = pipeline.config, pipeline.config.batch_size
    obs = pipeline.observation_dim
    if pipeline.algo == "dqn":
        q = [obs, *cfg.fc_layer_params, int(pipeline.action_spec.space.n)]
        target = mlp_flops(q, b) * (2 if cfg.double_dqn else 1)
        return target + mlp_flops(q, b, weight_grads=True, input_grads=True)
    act = int(pipeline.action_spec.shape[-1])
    if pipeline.algo == "crossq":
        actor, critic = [obs, *cfg.actor_fc_layer_params, 2 * act], [obs + act, *cfg.critic_fc_layer_params, 1]
        # no targets: the next action, then both critics on (s, a) and (s', a') joined (2b rows)
        critic_loss = mlp_flops(actor, b) + 2 * mlp_flops(critic, 2 * b, weight_grads=True, input_grads=True)
        # the actor and temperature every policy_delay-th update: both critics judge its action
        actor_loss = (mlp_flops(actor, b, weight_grads=True, input_grads=True)
                      + 2 * mlp_flops(critic, b, input_grads=True, first_input_grad=True))
        return critic_loss + actor_loss // cfg.policy_delay
    if pipeline.algo == "sac":
        actor, critic = [obs, *cfg.actor_fc_layer_params, 2 * act], [obs + act, *cfg.critic_joint_fc_layer_params, 1]
        target = mlp_flops(actor, b) + 2 * mlp_flops(critic, b)
        critic_loss = 2 * mlp_flops(critic, b, weight_grads=True, input_grads=True)
        # actor loss: both critics judge the sampled action; gradient flows through them to it
        actor_loss = (mlp_flops(actor, b, weight_grads=True, input_grads=True)
                      + 2 * mlp_flops(critic, b, input_grads=True, first_input_grad=True))
        return target + critic_loss + actor_loss
    actor, critic = [obs, *cfg.actor_fc_layer_params, act], [obs + act, *cfg.critic_fc_layer_params, 1]
    target = mlp_flops(actor, b) + 2 * mlp_flops(critic, b)
    critic_loss = 2 * mlp_flops(critic, b, weight_grads=True, input_grads=True)
    # the actor (every policy_delay-th update): Q1 of its action, gradient through Q1 to the actor
    actor_loss = (mlp_flops(actor, b, weight_grads=True, input_grads=True)
                  + mlp_flops(critic, b, input_grads=True, first_input_grad=True))
    return target + critic_loss + actor_loss // cfg.policy_delay


def matmul_flops_per_s(size: int = 256, seconds: float = 1.0) -> float:
    """This CPU's rate on ``[size, size] @ [size, size]`` with torch's current threads (best of 5)."""
    a, b = torch.randn(size, size), torch.randn(size, size)
    for _ in range(20):
        a @ b
    best = 0.0
    for _ in range(5):
        n, t0 = 0, time.perf_counter()
        while time.perf_counter() - t0 < seconds / 5:
            a @ b
            n += 1
        best = max(best, 2 * size**3 * n / (time.perf_counter() - t0))
    return best


def update_seconds(pipeline, chunks: int = 12, per_chunk: int = 20) -> float:
    """Median seconds of one ``pipeline.update_step`` over chunks, on a fixed random batch."""
    from tensordict import TensorDict

    b, obs, key = pipeline.config.batch_size, pipeline.observation_dim, pipeline.observation_key
    spec = pipeline.action_spec
    g = torch.Generator().manual_seed(0)
    if pipeline.algo == "dqn":
        action = torch.randint(0, int(spec.space.n), (b,), generator=g)
    else:
        action = (torch.rand(b, int(spec.shape[-1]), generator=g) * 2 - 1).clamp(spec.space.low, spec.space.high)
    batch = TensorDict({
        key: torch.randn(b, obs, generator=g), "action": action,
        "next": {key: torch.randn(b, obs, generator=g), "reward": torch.randn(b, 1, generator=g),
                 "terminated": torch.zeros(b, 1, dtype=torch.bool), "done": torch.zeros(b, 1, dtype=torch.bool),
                 "truncated": torch.zeros(b, 1, dtype=torch.bool)},
    }, [b])
    keys = pipeline.replay_keys
    batch = (batch.select(*keys, strict=False) if keys else batch).to(pipeline.device)
    sync = torch.cuda.synchronize if pipeline.device.type == "cuda" else (lambda: None)
    index = 0
    for _ in range(30):
        index += 1
        pipeline.update_step(batch.clone(), index)
    times = []
    for _ in range(chunks):
        sync()
        t0 = time.perf_counter()
        for _ in range(per_chunk):
            index += 1
            pipeline.update_step(batch.clone(), index)
        sync()
        times.append((time.perf_counter() - t0) / per_chunk)
    return statistics.median(times)


def bench_floor(args, out) -> dict:
    from rlpipe.pipelines import pipeline_class, resolve_preset
    from rlpipe.pipelines.config import apply_overrides
    from rlpipe.pipelines.system.runtime import keep_freed_memory

    before = torch.get_num_threads()
    torch.set_num_threads(1)
    keep_freed_memory()  # as the training loop does
    try:
        rate = matmul_flops_per_s()
        rows, figures = [], {"matmul_gflops_per_s": rate / 1e9, "cases": []}
        for preset, overrides, label in CASES:
            algo, cfg = resolve_preset(preset)
            pipeline = pipeline_class(algo)(apply_overrides(cfg, [*overrides, *args.overrides]))
            flops = update_flops(pipeline)
            seconds = update_seconds(pipeline)
            floor = flops / rate
            figures["cases"].append({"case": label, "update_ms": seconds * 1e3, "gflop": flops / 1e9,
                                     "floor_ms": floor * 1e3, "fraction": floor / seconds})
            rows.append(f"| {label} | {flops / 1e9:.3f} | {floor * 1e3:.2f} | {seconds * 1e3:.2f} | {floor / seconds:.0%} |")
    finally:
        torch.set_num_threads(before)
    table = "\n".join([
        f"Update against its arithmetic floor, one thread. This CPU: {rate / 1e9:.1f} GFLOP/s on "
        "[256, 256] x [256, 256] matmuls (best of 5, same run).",
        "",
        "| update | matmul GFLOP | floor ms | measured ms (median) | fraction of the floor reached |",
        "|---|---|---|---|---|",
        *rows,
    ])
    return {**figures, "table": table}
