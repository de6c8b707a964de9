"""The benchmark pages are what ``benchmarks/pages.py`` makes from the committed result JSON (no training).

``benchmarks/`` is this repository's own (results, page generator, the TF-Agents tutorial copies), outside the
installed package: its generator is loaded from the checkout.
"""

import importlib.util
import re
import sys
from pathlib import Path

_spec = importlib.util.spec_from_file_location("benchmark_pages", Path(__file__).parents[1] / "benchmarks" / "pages.py")
pages = sys.modules["benchmark_pages"] = importlib.util.module_from_spec(_spec)  # its dataclasses look it up there
_spec.loader.exec_module(pages)


def test_the_committed_benchmark_pages_are_what_the_committed_json_makes():
    index = (pages.PAGES / "index.md").read_text()
    assert index == pages.index_page(), "docs/benchmarks/index.md is stale: run python benchmarks/pages.py"
    benchmarks = pages.BENCHMARKS.read_text()
    assert pages.with_summary(benchmarks) == benchmarks, "BENCHMARKS.md's summary is stale: run the same"
    plots = re.findall(r"\]\(([\w-]+\.png)\)", index)
    assert len(plots) == 4 + len(pages.ANYTIME) and all((pages.PAGES / plot).is_file() for plot in plots), plots
    headings = {line.lstrip("#").strip() for line in benchmarks.splitlines() if line.startswith("#")}
    missing = {pair.heading for pair in pages.TIME_TO_TARGET} - headings
    assert {heading for heading, _ in pages.ANYTIME.values()} <= headings
    assert not missing, f"the summary links to headings BENCHMARKS.md lacks: {missing}"
