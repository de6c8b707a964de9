"""Processes and actors that collect and evaluate: the collector backends (local processes, Ray
actors), the evaluators (in the learner, in a process, on a Ray actor) and their supervision.

    backend.py      the collector-backend interface (``CollectorBackend``, ``Health``)
    factory.py      ``make_backend`` / ``backend_class``: the one place that reads ``collector.backend``
    local.py        TorchRL's collectors on this machine (in process, or worker processes)
    ray.py          TorchRL's ``RayCollector`` on Ray actors, with version stamps and staleness
    ray_runtime.py  the run's hold on Ray (join or start one), its address and CPU checks
    supervision.py  restarts, deadlines on every wait, the watchdog
    evaluation.py   evaluate(); the background evaluator in a process (TorchRL's ``Evaluator``)
    ray_eval.py     the background evaluator on a Ray actor
    gym_collector.py         a TorchRL collector stepping one gymnasium env directly (``GymCollector``)
    snapshot_collector.py    TorchRL's collector with its envs' mid-episode state in its state_dict (exact resume)
"""
