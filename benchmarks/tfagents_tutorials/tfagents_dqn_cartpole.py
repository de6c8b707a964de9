"""TF-Agents' "Train a Deep Q Network with TF-Agents" tutorial (DQN on CartPole-v0) as a timed, standalone script.

Runs only inside the peer venv that ``scripts/bench/peers/tfagents.py`` builds (TensorFlow, TF-Agents and the
old ``gym``); rlpipe never imports it. It follows the tutorial's text (1_dqn_tutorial.ipynb, the version
with hand-written ``collect_step``/``collect_data`` instead of a driver) cell for cell: the same
hyperparameters, ``QNetwork(fc_layer_params=(100,))``, ``tf.compat.v1.train.AdamOptimizer(1e-3)``,
``DqnAgent`` with ``common.element_wise_squared_loss``, ``TFUniformReplayBuffer(max_length=100000)``, the
dataset ``as_dataset(num_parallel_calls=3, sample_batch_size=64, num_steps=2).prefetch(3)``,
``agent.train = common.function(agent.train)`` and the same loop (per iteration: one eager
``collect_step`` with ``agent.collect_policy``, ``next(iterator)``, one ``agent.train``; a loss line every
200 steps), so that ``rlpipe bench dqn`` can time it on the same machine as our pipeline. Differences from
the notebook:

- no evaluation before or during training (the notebook's ``compute_avg_return`` over 10 episodes before
  the loop and every 1000 iterations): ``--eval-episodes K`` runs it once, after the loop, over K episodes;
- the initial random collect is ``--initial-collect-steps`` steps, by default 100: the notebook defines
  ``initial_collect_steps = 1000`` but its cell calls ``collect_data(..., steps=100)``, and this follows the
  code that runs;
- no virtual display, rendering, plot or videos (the setup, "Визуализация" and example-policy cells);
- ``--seed`` seeds TensorFlow, NumPy and the two envs (the notebook seeds nothing); the dataset's three
  parallel sampling calls still make runs not bit-for-bit reproducible.

Prints one JSON line at the end: ``{"iterations", "train_s", "initial_collect_s", "final_average_return",
"tf_threads"}``, where ``train_s`` is the wall time of the iteration loop alone (after the initial collect,
including the first ``agent.train`` call's tracing) and ``tf_threads`` is TensorFlow's inter/intra-op thread
settings, left at their defaults (0: one per core).
"""

from __future__ import annotations

import argparse
import json
import os
import time

import numpy as np
import tensorflow as tf
from tf_agents.agents.dqn import dqn_agent
from tf_agents.environments import suite_gym, tf_py_environment
from tf_agents.networks import q_network
from tf_agents.policies import random_tf_policy, tf_policy
from tf_agents.replay_buffers import tf_uniform_replay_buffer
from tf_agents.trajectories import trajectory
from tf_agents.utils import common

# The tutorial's hyperparameters (num_iterations, num_eval_episodes and eval_interval are command-line
# options or dropped, see the module docstring).
ENV_NAME = "CartPole-v0"
INITIAL_COLLECT_STEPS = 100  # what the notebook's collect_data call uses; its unused initial_collect_steps is 1000
COLLECT_STEPS_PER_ITERATION = 1
REPLAY_BUFFER_MAX_LENGTH = 100000
BATCH_SIZE = 64
LEARNING_RATE = 1e-3
LOG_INTERVAL = 200
FC_LAYER_PARAMS = (100,)


def parse_args() -> argparse.Namespace:
    """``--iterations`` (required), ``--seed``, ``--initial-collect-steps`` and ``--eval-episodes``."""
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("--iterations", type=int, required=True, help="num_iterations (tutorial: 20000)")
    parser.add_argument("--seed", type=int, default=0)
    parser.add_argument("--initial-collect-steps", type=int, default=INITIAL_COLLECT_STEPS,
                        help="random steps before training (tutorial's code: 100; at least 2, one sampled pair)")
    parser.add_argument("--eval-episodes", type=int, default=0,
                        help="after the loop, AverageReturn of agent.policy over this many episodes (0: none)")
    args = parser.parse_args()
    if args.initial_collect_steps < 2:
        parser.error("--initial-collect-steps must be at least 2 (the dataset samples num_steps=2)")
    if args.eval_episodes < 0:
        parser.error("--eval-episodes must be 0 (no evaluation) or more")
    return args


def compute_avg_return(environment: tf_py_environment.TFPyEnvironment, policy: tf_policy.TFPolicy,
                       num_episodes: int = 10) -> float:
    """The tutorial's average undiscounted return of ``policy`` over ``num_episodes`` whole episodes."""
    total_return = 0.0
    for _ in range(num_episodes):
        time_step = environment.reset()
        episode_return = 0.0
        while not time_step.is_last():
            action_step = policy.action(time_step)
            time_step = environment.step(action_step.action)
            episode_return += time_step.reward
        total_return += episode_return
    avg_return = total_return / num_episodes
    return float(avg_return.numpy()[0])


def collect_step(environment: tf_py_environment.TFPyEnvironment, policy: tf_policy.TFPolicy,
                 buffer: tf_uniform_replay_buffer.TFUniformReplayBuffer) -> None:
    """The tutorial's one env step with ``policy``, its transition added to ``buffer``."""
    time_step = environment.current_time_step()
    action_step = policy.action(time_step)
    next_time_step = environment.step(action_step.action)
    traj = trajectory.from_transition(time_step, action_step, next_time_step)
    buffer.add_batch(traj)


def collect_data(env: tf_py_environment.TFPyEnvironment, policy: tf_policy.TFPolicy,
                 buffer: tf_uniform_replay_buffer.TFUniformReplayBuffer, steps: int) -> None:
    """The tutorial's ``steps`` calls of ``collect_step``."""
    for _ in range(steps):
        collect_step(env, policy, buffer)


def main() -> None:
    """Build the tutorial's env, agent and replay buffer, collect, train, optionally evaluate, print the summary."""
    args = parse_args()
    tf.random.set_seed(args.seed)
    np.random.seed(args.seed)

    train_py_env = suite_gym.load(ENV_NAME)
    eval_py_env = suite_gym.load(ENV_NAME)
    train_py_env.seed(args.seed)
    eval_py_env.seed(args.seed + 1)
    train_env = tf_py_environment.TFPyEnvironment(train_py_env)
    eval_env = tf_py_environment.TFPyEnvironment(eval_py_env)

    q_net = q_network.QNetwork(
        train_env.observation_spec(),
        train_env.action_spec(),
        fc_layer_params=FC_LAYER_PARAMS)

    optimizer = tf.compat.v1.train.AdamOptimizer(learning_rate=LEARNING_RATE)

    train_step_counter = tf.Variable(0)

    agent = dqn_agent.DqnAgent(
        train_env.time_step_spec(),
        train_env.action_spec(),
        q_network=q_net,
        optimizer=optimizer,
        td_errors_loss_fn=common.element_wise_squared_loss,
        train_step_counter=train_step_counter)
    agent.initialize()

    random_policy = random_tf_policy.RandomTFPolicy(train_env.time_step_spec(), train_env.action_spec())

    replay_buffer = tf_uniform_replay_buffer.TFUniformReplayBuffer(
        data_spec=agent.collect_data_spec,
        batch_size=train_env.batch_size,
        max_length=REPLAY_BUFFER_MAX_LENGTH)

    start = time.perf_counter()
    collect_data(train_env, random_policy, replay_buffer, steps=args.initial_collect_steps)
    initial_collect_s = time.perf_counter() - start

    dataset = replay_buffer.as_dataset(
        num_parallel_calls=3,
        sample_batch_size=BATCH_SIZE,
        num_steps=2).prefetch(3)
    iterator = iter(dataset)

    agent.train = common.function(agent.train)
    agent.train_step_counter.assign(0)

    start = time.perf_counter()
    for _ in range(args.iterations):
        for _ in range(COLLECT_STEPS_PER_ITERATION):
            collect_step(train_env, agent.collect_policy, replay_buffer)

        experience, _ = next(iterator)
        train_loss = agent.train(experience).loss

        step = agent.train_step_counter.numpy()
        if step % LOG_INTERVAL == 0:
            print(f"step = {step}: loss = {train_loss}", flush=True)
    train_s = time.perf_counter() - start

    final_average_return = None
    if args.eval_episodes:
        final_average_return = compute_avg_return(eval_env, agent.policy, args.eval_episodes)
        print(f"step = {agent.train_step_counter.numpy()}: Average Return = {final_average_return}", flush=True)

    print(json.dumps({"iterations": args.iterations, "train_s": train_s, "initial_collect_s": initial_collect_s,
                      "final_average_return": final_average_return,
                      "tf_threads": {"inter_op": tf.config.threading.get_inter_op_parallelism_threads(),
                                     "intra_op": tf.config.threading.get_intra_op_parallelism_threads(),
                                     "cpu_count": os.cpu_count()}}), flush=True)


if __name__ == "__main__":
    main()
