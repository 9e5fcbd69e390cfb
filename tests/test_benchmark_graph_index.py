"""benchmarks/graph_index.py times both arms of each part on a dataset's own training batches."""
import re
import subprocess
import sys
from pathlib import Path

ROOT = Path(__file__).resolve().parents[1]


def test_the_benchmark_times_each_part_both_ways_on_the_stub():
    out = subprocess.run([sys.executable, str(ROOT / "benchmarks" / "graph_index.py"), "--dataset", "stub",
                          "--batches", "1", "--rounds", "1", "--models", "events_only"],
                         capture_output=True, text=True, cwd=ROOT, check=True).stdout
    rows = re.findall(r"^  (.+?) +compiled +([0-9.]+) ms +sorts \(baseline\) +([0-9.]+) ms +([0-9.]+)x$", out, re.M)
    assert [row[0] for row in rows] == ["event graph: matrix and its transpose",
                                        "first pooling (8 px cells) with cell edges",
                                        "events_only: training step (forward and backward)"], out
    assert all(float(a) > 0 and float(b) > 0 for _, a, b, _ in rows), out
