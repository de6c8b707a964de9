"""The benchmark pages are what ``scripts/bench/pages.py`` makes from the committed result JSON (no training)."""

import re

from rlpipe.scripts.bench import pages


def test_the_committed_benchmark_pages_are_what_the_committed_json_makes():
    index = (pages.PAGES / "index.md").read_text()
    assert index == pages.index_page(), "docs/benchmarks/index.md is stale: run python -m rlpipe.scripts.bench.pages"
    benchmarks = pages.BENCHMARKS.read_text()
    assert pages.with_summary(benchmarks) == benchmarks, "BENCHMARKS.md's summary is stale: run the same"
    plots = re.findall(r"\]\(([\w-]+\.png)\)", index)
    assert len(plots) == 5 and all((pages.PAGES / plot).is_file() for plot in plots), plots
    headings = {line.lstrip("#").strip() for line in benchmarks.splitlines() if line.startswith("#")}
    missing = {pair.heading for pair in pages.TIME_TO_TARGET} - headings
    assert pages.ANYTIME_HEADING in headings
    assert not missing, f"the summary links to headings BENCHMARKS.md lacks: {missing}"
