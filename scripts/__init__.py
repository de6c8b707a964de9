"""rlpipe.scripts: the command line (``cli``), the ablation runner (``ablate``), the benchmarks (``bench/``)."""
