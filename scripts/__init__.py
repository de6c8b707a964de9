"""rlpipe.scripts: the command line (``cli``), the ablation runner (``ablate``), the benchmarks (``bench/``)."""

from rlpipe.scripts import _moved

_moved.install()  # the benchmarks' module paths from before bench/ (``rlpipe.scripts.bench_collect``, ...), warned
