"""benchmarks/train_step.py trains the default models, the hybrid with its carry branch among them."""
import re
import subprocess
import sys
from pathlib import Path

ROOT = Path(__file__).resolve().parents[1]


def test_the_benchmark_steps_the_default_hybrid_and_events_only():
    out = subprocess.run([sys.executable, str(ROOT / "benchmarks" / "train_step.py"), "--steps", "1", "--events", "2000",
                          "--variants", "hybrid", "events_only", "--sizes", "160x96", "--workers", "0", "--device", "cpu"],
                         capture_output=True, text=True, cwd=ROOT, check=True).stdout
    for variant in ("hybrid", "events_only"):
        step = re.search(rf"^{variant} +160x96: step +([0-9.]+) s = wait for data", out, re.MULTILINE)
        assert step is not None and float(step.group(1)) > 0, out
    assert out.count("the same steps on batches loaded beforehand") == 2, out
