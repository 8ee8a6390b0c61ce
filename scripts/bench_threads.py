#!/usr/bin/env python
"""torchcal's threading (torchcal/threads.py) against torch's default, on a machine where another
process keeps a core busy, as on a shared workstation or CI runner.

Two measurements, each mode in its own process, interleaved:
* the README's Python API block, as written, on the demo's files (``TORCHCAL_THREADS=caller``:
  torch's default threads, as before torchcal chose; ``auto``: torchcal's choice);
* ``calibrate`` on simulated KR5 rows of several sizes, with torch's default threads and with one
  (``TORCHCAL_THREADS=1``), to show how the choice depends on the size.

Usage: python scripts/bench_threads.py [--busy 1] [--reps 1] [--rows 150,3000] [--demo out/demo] [--no-readme]
Prints one JSON line (wall times in s, ratios default / torchcal's choice).
"""
from __future__ import annotations

import argparse
import json
import os
import re
import statistics
import subprocess
import sys
import tempfile
import time
from pathlib import Path

ROOT = Path(__file__).resolve().parents[1]

_CALIBRATE = """
import sys, time
from torchcal import Robot, calibrate
from torchcal.sim.serial import SimConfig, simulate
robot = Robot.from_urdf(sys.argv[1], markers=["smr@flange=0,0,0"])
data, _ = simulate(robot, SimConfig(n=int(sys.argv[2]), seed=1))
calibrate(robot, data.subset(range(20)))  # warm-up: imports and first calls
t = time.perf_counter()
calibrate(robot, data)
print(time.perf_counter() - t)
"""


def _readme_block() -> str:
    text = (ROOT / "README.md").read_text()
    return re.search(r"## Python API\n\n```python\n(.*?)```", text, re.S).group(1)


def _run(args: list[str], mode: str, cwd: Path) -> tuple[float, str]:
    env = {**os.environ, "PYTHONPATH": str(ROOT), "TORCHCAL_THREADS": mode}
    t = time.perf_counter()
    p = subprocess.run(args, cwd=cwd, env=env, capture_output=True, text=True)
    if p.returncode:
        raise SystemExit(f"{args[:3]} failed ({mode}):\n{p.stderr[-3000:]}")
    return time.perf_counter() - t, p.stdout


def _default_threads() -> int:
    out = subprocess.run([sys.executable, "-c", "import torch; print(torch.get_num_threads())"], capture_output=True,
                         text=True, check=True)
    return int(out.stdout)


def main() -> None:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--busy", type=int, default=1, help="processes spinning on a core during the runs")
    ap.add_argument("--reps", type=int, default=1)
    ap.add_argument("--rows", default="150,3000", help="row counts for calibrate")
    ap.add_argument("--no-readme", action="store_true", help="calibrate only")
    ap.add_argument("--demo", help="the demo's output folder (default: made by scripts/demo.py in a temp folder)")
    args = ap.parse_args()
    with tempfile.TemporaryDirectory() as tmp:
        work = Path(tmp)
        (work / "out").mkdir()
        os.symlink(ROOT / "urdf", work / "urdf")
        if args.no_readme:
            pass
        elif args.demo:
            os.symlink(Path(args.demo).resolve(), work / "out" / "demo")
        else:
            subprocess.run([sys.executable, str(ROOT / "scripts" / "demo.py"), "--out", str(work / "out" / "demo")],
                           check=True, capture_output=True, env={**os.environ, "PYTHONPATH": str(ROOT)})
        (work / "block.py").write_text(_readme_block())
        (work / "calibrate.py").write_text(_CALIBRATE)
        busy = [subprocess.Popen([sys.executable, "-c", "while True: pass"]) for _ in range(args.busy)]
        try:
            block = {"caller": [], "auto": []}
            cal = {n: {"caller": [], "1": []} for n in args.rows.split(",")}
            for _ in range(args.reps):
                for mode in ("caller", "auto"):
                    if not args.no_readme:
                        block[mode].append(_run([sys.executable, "block.py"], mode, work)[0])
                for mode in ("caller", "1"):
                    for n in cal:
                        out = _run([sys.executable, "calibrate.py", str(ROOT / "urdf" / "kuka_kr5_arc.urdf"), n],
                                   mode, work)[1].split()
                        cal[n][mode].append(float(out[0]))
        finally:
            for p in busy:
                p.kill()
    med = {k: statistics.median(v) if v else None for k, v in block.items()}
    print(json.dumps({
        "cores": os.cpu_count(), "busy_processes": args.busy, "reps": args.reps,
        "torch_default_threads": _default_threads(),
        "readme_python_block_s": {k: [round(x, 2) for x in v] for k, v in block.items()},
        "readme_ratio_default_over_torchcal": round(med["caller"] / med["auto"], 2) if med["auto"] else None,
        "calibrate_s": {n: {k: [round(x, 4) for x in v] for k, v in d.items()} for n, d in cal.items()},
        "calibrate_ratio_default_over_one_thread": {n: round(statistics.median(d["caller"]) / statistics.median(d["1"]), 2)
                                                    for n, d in cal.items()},
    }))


if __name__ == "__main__":
    main()
