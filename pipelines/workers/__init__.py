"""Processes and actors that collect and evaluate: the collector backends (local processes, Ray
actors), the evaluators (in the learner, in a process, on a Ray actor) and their supervision.

``backend``: the collector-backend interface (``CollectorBackend``) and ``make_backend``, the one place
that reads ``collector.backend``; ``local``: TorchRL's collectors on this machine; ``ray``: TorchRL's
``RayCollector`` on Ray actors; ``supervision``: restarts, deadlines, the watchdog; ``evaluation`` and
``ray_eval``: the background evaluators."""
