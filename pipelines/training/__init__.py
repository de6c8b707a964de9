"""The loop and what runs inside it: ``Loop`` (collect, update, triggers), the triggers, the run's
state and rate limiter, speeds and losses (``meters``), and the CUDA-graphed update."""
