"""Processes and actors that collect and evaluate: the collector backends (local processes, Ray
actors), the evaluators (in the learner, in a process, on a Ray actor) and their supervision."""
