"""The demo's loop knows no noise floor, and the floor the demo prints comes from the truth file
only it reads: the output says which is which (issue 35 §4)."""
from __future__ import annotations

import os
import subprocess
import sys
from pathlib import Path

import pytest

REPO = Path(__file__).resolve().parents[2]


@pytest.mark.slow
def test_the_demo_tells_the_loop_s_floor_from_the_truth_s(tmp_path):
    env = {**os.environ, "PYTHONPATH": str(REPO), "OMP_NUM_THREADS": "1"}
    run = subprocess.run([sys.executable, str(REPO / "scripts" / "demo.py"), "--out", str(tmp_path / "demo"),
                          "--poses", "80", "--test-poses", "40", "--targets", "5"], cwd=tmp_path, env=env,
                         capture_output=True, text=True, timeout=900)
    assert run.returncode == 0, run.stderr[-2000:]
    text = run.stdout + run.stderr
    assert "no noise floor is known" in text  # the loop's own words: its data give none
    last = next(line for line in run.stdout.splitlines() if "noise floor" in line and "truth" in line)
    assert "the loop above knew no noise floor" in last and "never saw" in last, last
    assert "only now" in last and "truth.json" in last, last
