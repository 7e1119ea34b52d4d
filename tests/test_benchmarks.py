"""The benchmark suite (`python -m benchmarks`): it lists its members, and the READMEs' generated
tables are those of the committed records (regenerated, not typed), every row under 400
characters."""

from __future__ import annotations

import subprocess
import sys
from pathlib import Path

ROOT = Path(__file__).resolve().parent.parent


def test_suite_lists_its_benchmarks():
    from benchmarks import _suite

    out = subprocess.run([sys.executable, "-m", "benchmarks", "--list"], cwd=ROOT, capture_output=True, text=True,
                         check=True)
    names = [line.split()[0] for line in out.stdout.splitlines()]
    assert names == list(_suite.listing()) and "inverse_speed" in names
    assert all(len(line.split(None, 1)) == 2 for line in out.stdout.splitlines())  # each has a description


def test_readme_tables_are_generated_from_the_records():
    from benchmarks import _suite

    top = _suite.TOP_README.read_text()
    bench = _suite.BENCH_README.read_text()
    assert _suite.replace_block(top, "key numbers", _suite.key_numbers_table()) == top, (
        "README.md's key numbers differ from the records: run `python -m benchmarks --tables`")
    assert _suite.replace_block(bench, "results", _suite.readme_results()) == bench, (
        "benchmarks/README.md's results differ from the records: run `python -m benchmarks --tables`")
    for line in (top + bench).splitlines():
        assert not line.startswith("|") or len(line) <= _suite.MAX_ROW, line[:120]
