"""Workarounds for library versions, one module per library. Each names the version it is for and
when to delete it, so that an upgrade removes it in one commit.

    torchrl.py   TorchRL 0.14: weight-sync acks with a deadline (``AckDeadline``), weight-sync queues
                 left open by a collector's shutdown, the Ray scheme's version stamp, the replay
                 writer's cursor, the process ``Evaluator``'s worker start, threads, shutdown and
                 trajectory-format warning, a user's env given the transforms the policy reads
    torch.py     torch 2.13: the TorchScript ONNX exporter's C++ log on every export
    ray.py       Ray 2.60: ``ray.init`` taking over SIGTERM; ``ray.init`` retrying an unreachable
                 address for minutes

This is the lowest room of ``pipelines`` (it imports no other part of rlpipe), so any room may use it.
What it does not hold, and why:

* where the workaround is a deadline of our own on a wait TorchRL 0.14 leaves unbounded: the watchdog
  on a new collector's or evaluator's start-up (TorchRL reads a worker's first message with no
  timeout; ``workers.supervision.Watchdog`` with ``kill_new_children``), used by the supervisor and
  ``workers.backend.CollectorBackend.start_evaluator``.
* below ``pipelines`` (``modules/`` and ``envs/`` never import it): ``modules/fast/optim.py``'s ``LeanAdam``
  calls torch 2.13's private ``torch._fused_adam_`` with that version's arguments (a speed path,
  checked bitwise against ``Adam`` by tests/test_optim.py at each upgrade).
* features the libraries lack rather than bugs (ours until a version has them, nothing to patch):
  supervision and restarts (``workers/supervision.py``), the samples-per-insert limiter
  (``training/rate_limiter.py``), the Ray evaluator (``workers/ray_eval.py``: TorchRL 0.14's
  ``RayEvalWorker`` plays one rollout and ignores ``num_trajectories``), one evaluation request at a
  time (``workers/evaluation.py``: TorchRL 0.14's ``Evaluator`` loses a second request queued while the
  first finishes), DQN's hard target update as a lerp (``dqn.py``: ``HardUpdate`` copies every second
  call).
"""
