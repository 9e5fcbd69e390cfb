"""benchmarks/sample_load.py times a dataset's own training samples; its two picture arms agree."""
import re
import subprocess
import sys
from pathlib import Path

import numpy as np

from dagr_lite.data.dataset import picture_state
from dagr_lite.data.picture import add_events

ROOT = Path(__file__).resolve().parents[1]


def test_the_picture_kernel_on_stored_columns_equals_it_on_cast_columns():
    """The benchmark's baseline feeds the kernel int64 / float64 columns; the loader feeds the stored ones."""
    rng = np.random.default_rng(0)
    height, width, n = 18, 32, 5000
    x, y = rng.integers(0, width, n).astype(np.uint16), rng.integers(0, height, n).astype(np.uint16)
    t, p = np.sort(rng.integers(0, 10**9, n)).astype(np.int64), rng.integers(0, 2, n).astype(np.uint8)
    states = []
    for columns in ((x, y, t, p), (x.astype(np.int64), y.astype(np.int64), t.astype(np.float64), p.astype(np.int64))):
        counts, last = picture_state(height, width)
        add_events(counts, last, *columns, width)
        states.append((counts, last))
    np.testing.assert_array_equal(states[0][0], states[1][0])
    np.testing.assert_array_equal(states[0][1], states[1][1])
    assert states[0][0].sum() == n


def test_the_benchmark_times_the_stub_samples_part_by_part():
    out = subprocess.run([sys.executable, str(ROOT / "benchmarks" / "sample_load.py"), "--dataset", "stub",
                          "--samples", "24"], capture_output=True, text=True, cwd=ROOT, check=True).stdout
    for part in ("events read", "frame decoded", "carry picture", "augmentation", "rest", "sample", "graphs"):
        assert f"  {part} " in out, out
    assert "24 training samples" in out, out
    ratio = re.search(r"on columns cast first \(baseline\): [0-9.]+ ms, ([0-9.]+)x$", out.strip())
    assert ratio is not None and float(ratio.group(1)) > 0, out
