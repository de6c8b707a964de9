"""TF-Agents' "SAC on Minitaur with the Actor-Learner API" tutorial as a timed, standalone script.

Runs only inside the peer venv that ``scripts/bench/peers/tfagents.py`` builds (TensorFlow, TF-Agents, Reverb,
pybullet and the old ``gym``); rlpipe never imports it. It is the tutorial's code cell for cell, with
the same hyperparameters and the same training loop (per iteration: ``collect_actor.run()``, one env
step, then ``agent_learner.run(iterations=1)``, one update on a batch of 256 from Reverb), so that
``rlpipe bench sac`` can time it on the same machine as our pipeline. Differences from the notebook:

- no evaluation before or during training, and no ``PolicySavedModelTrigger`` (both optional here:
  ``--eval-episodes`` evaluates once after the loop, ``--policy-save-interval`` adds the trigger);
- the evaluation policy is ``GreedyPolicy(tf_agent.policy)`` (the distribution's mode); the notebook
  evaluates ``tf_agent.policy`` itself, which for ``SacAgent`` samples just as the collect policy does;
- the strategy is the CPU one (``use_gpu=False``, the tutorial's own choice for a CPU) unless ``--use-gpu``;
- the Learner's and Actors' directories are a fresh temporary directory per run instead of the shared
  ``tempfile.gettempdir()``, so a run never restores a checkpoint left by another one;
- ``--seed`` seeds TensorFlow, NumPy, the envs and the random policy (the notebook seeds nothing);
  Reverb's uniform sampling cannot be seeded, so runs are not bit-for-bit reproducible.

Prints one JSON line at the end: ``{"iterations", "train_s", "initial_collect_s", "final_average_return",
"tf_threads"}``, where ``train_s`` is the wall time of the iteration loop alone (after the initial collect)
and ``tf_threads`` is TensorFlow's inter/intra-op thread settings, left at their defaults (0: one per core).
"""

from __future__ import annotations

import argparse
import json
import os
import shutil
import tempfile
import time

import numpy as np
import reverb
import tensorflow as tf
from tf_agents.agents.ddpg import critic_network
from tf_agents.agents.sac import sac_agent, tanh_normal_projection_network
from tf_agents.environments import suite_pybullet
from tf_agents.metrics import py_metrics
from tf_agents.networks import actor_distribution_network
from tf_agents.policies import greedy_policy, py_tf_eager_policy, random_py_policy
from tf_agents.replay_buffers import reverb_replay_buffer, reverb_utils
from tf_agents.train import actor, learner, triggers
from tf_agents.train.utils import spec_utils, strategy_utils, train_utils

# The tutorial's hyperparameters.
ENV_NAME = "MinitaurBulletEnv-v0"
INITIAL_COLLECT_STEPS = 10000
REPLAY_BUFFER_CAPACITY = 10000
BATCH_SIZE = 256
CRITIC_LEARNING_RATE = 3e-4
ACTOR_LEARNING_RATE = 3e-4
ALPHA_LEARNING_RATE = 3e-4
TARGET_UPDATE_TAU = 0.005
TARGET_UPDATE_PERIOD = 1
GAMMA = 0.99
REWARD_SCALE_FACTOR = 1.0
ACTOR_FC_LAYER_PARAMS = (256, 256)
CRITIC_JOINT_FC_LAYER_PARAMS = (256, 256)
LOG_INTERVAL = 5000

# ``rlpipe bench time-to-return``'s hook (``peers/ttr_tfagents.py``): observers added to both actors, beside the
# tutorial's own, and the run's eval env and greedy policy published for its greedy check. Empty otherwise.
EXTRA_OBSERVERS: list = []
RUN: dict = {}


def parse_args() -> argparse.Namespace:
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("--iterations", type=int, required=True, help="num_iterations (tutorial: 100000)")
    parser.add_argument("--seed", type=int, default=0)
    parser.add_argument("--initial-collect-steps", type=int, default=INITIAL_COLLECT_STEPS,
                        help="random steps before training (tutorial: 10000; at least the batch size, 256)")
    parser.add_argument("--eval-episodes", type=int, default=0,
                        help="after the loop, AverageReturn of the greedy policy over this many episodes (0: none)")
    parser.add_argument("--policy-save-interval", type=int, default=0,
                        help="add the tutorial's PolicySavedModelTrigger with this interval (tutorial: 5000; 0: none)")
    parser.add_argument("--use-gpu", action="store_true", help="MirroredStrategy, as the notebook's use_gpu=True")
    args = parser.parse_args()
    if args.initial_collect_steps < BATCH_SIZE:
        parser.error(f"--initial-collect-steps must be at least the batch size, {BATCH_SIZE}")
    return args


def main() -> None:
    args = parse_args()
    tf.random.set_seed(args.seed)
    np.random.seed(args.seed)
    tempdir = tempfile.mkdtemp(prefix="tfagents_sac_minitaur_")

    collect_env = suite_pybullet.load(ENV_NAME)
    eval_env = suite_pybullet.load(ENV_NAME)
    collect_env.seed(args.seed)
    eval_env.seed(args.seed + 1)

    strategy = strategy_utils.get_strategy(tpu=False, use_gpu=args.use_gpu)

    observation_spec, action_spec, time_step_spec = spec_utils.get_tensor_specs(collect_env)

    with strategy.scope():
        critic_net = critic_network.CriticNetwork(
            (observation_spec, action_spec),
            observation_fc_layer_params=None,
            action_fc_layer_params=None,
            joint_fc_layer_params=CRITIC_JOINT_FC_LAYER_PARAMS,
            kernel_initializer="glorot_uniform",
            last_kernel_initializer="glorot_uniform")

    with strategy.scope():
        actor_net = actor_distribution_network.ActorDistributionNetwork(
            observation_spec,
            action_spec,
            fc_layer_params=ACTOR_FC_LAYER_PARAMS,
            continuous_projection_net=tanh_normal_projection_network.TanhNormalProjectionNetwork)

    with strategy.scope():
        train_step = train_utils.create_train_step()
        tf_agent = sac_agent.SacAgent(
            time_step_spec,
            action_spec,
            actor_network=actor_net,
            critic_network=critic_net,
            actor_optimizer=tf.keras.optimizers.Adam(learning_rate=ACTOR_LEARNING_RATE),
            critic_optimizer=tf.keras.optimizers.Adam(learning_rate=CRITIC_LEARNING_RATE),
            alpha_optimizer=tf.keras.optimizers.Adam(learning_rate=ALPHA_LEARNING_RATE),
            target_update_tau=TARGET_UPDATE_TAU,
            target_update_period=TARGET_UPDATE_PERIOD,
            td_errors_loss_fn=tf.math.squared_difference,
            gamma=GAMMA,
            reward_scale_factor=REWARD_SCALE_FACTOR,
            train_step_counter=train_step)
        tf_agent.initialize()

    table_name = "uniform_table"
    table = reverb.Table(
        table_name,
        max_size=REPLAY_BUFFER_CAPACITY,
        sampler=reverb.selectors.Uniform(),
        remover=reverb.selectors.Fifo(),
        rate_limiter=reverb.rate_limiters.MinSize(1))
    reverb_server = reverb.Server([table])

    reverb_replay = reverb_replay_buffer.ReverbReplayBuffer(
        tf_agent.collect_data_spec,
        sequence_length=2,
        table_name=table_name,
        local_server=reverb_server)

    dataset = reverb_replay.as_dataset(sample_batch_size=BATCH_SIZE, num_steps=2).prefetch(50)

    def experience_dataset_fn() -> tf.data.Dataset:
        return dataset

    eval_policy = py_tf_eager_policy.PyTFEagerPolicy(greedy_policy.GreedyPolicy(tf_agent.policy), use_tf_function=True)
    collect_policy = py_tf_eager_policy.PyTFEagerPolicy(tf_agent.collect_policy, use_tf_function=True)
    RUN.update(eval_env=eval_env, eval_policy=eval_policy, train_step=train_step)
    random_policy = random_py_policy.RandomPyPolicy(
        collect_env.time_step_spec(), collect_env.action_spec(), seed=args.seed)

    rb_observer = reverb_utils.ReverbAddTrajectoryObserver(
        reverb_replay.py_client,
        table_name,
        sequence_length=2,
        stride_length=1)

    initial_collect_actor = actor.Actor(
        collect_env,
        random_policy,
        train_step,
        steps_per_run=args.initial_collect_steps,
        observers=[rb_observer, *EXTRA_OBSERVERS])
    start = time.perf_counter()
    initial_collect_actor.run()
    initial_collect_s = time.perf_counter() - start

    env_step_metric = py_metrics.EnvironmentSteps()
    collect_actor = actor.Actor(
        collect_env,
        collect_policy,
        train_step,
        steps_per_run=1,
        metrics=actor.collect_metrics(10),
        summary_dir=os.path.join(tempdir, learner.TRAIN_DIR),
        observers=[rb_observer, env_step_metric, *EXTRA_OBSERVERS])

    learning_triggers = [triggers.StepPerSecondLogTrigger(train_step, interval=1000)]
    if args.policy_save_interval:
        learning_triggers.insert(0, triggers.PolicySavedModelTrigger(
            os.path.join(tempdir, learner.POLICY_SAVED_MODEL_DIR),
            tf_agent,
            train_step,
            interval=args.policy_save_interval))

    agent_learner = learner.Learner(
        tempdir,
        train_step,
        tf_agent,
        experience_dataset_fn,
        triggers=learning_triggers,
        strategy=strategy)

    tf_agent.train_step_counter.assign(0)

    start = time.perf_counter()
    for _ in range(args.iterations):
        collect_actor.run()
        loss_info = agent_learner.run(iterations=1)
        step = agent_learner.train_step_numpy
        if LOG_INTERVAL and step % LOG_INTERVAL == 0:
            print(f"step = {step}: loss = {loss_info.loss.numpy()}", flush=True)
    train_s = time.perf_counter() - start

    final_average_return = None
    if args.eval_episodes:
        eval_actor = actor.Actor(
            eval_env,
            eval_policy,
            train_step,
            episodes_per_run=args.eval_episodes,
            metrics=actor.eval_metrics(args.eval_episodes),
            summary_dir=os.path.join(tempdir, "eval"))
        eval_actor.run()
        final_average_return = float(next(m.result() for m in eval_actor.metrics if m.name == "AverageReturn"))

    rb_observer.close()
    reverb_server.stop()
    shutil.rmtree(tempdir, ignore_errors=True)

    print(json.dumps({"iterations": args.iterations, "train_s": train_s, "initial_collect_s": initial_collect_s,
                      "final_average_return": final_average_return,
                      "tf_threads": {"inter_op": tf.config.threading.get_inter_op_parallelism_threads(),
                                     "intra_op": tf.config.threading.get_intra_op_parallelism_threads(),
                                     "cpu_count": os.cpu_count()}}), flush=True)


if __name__ == "__main__":
    main()
