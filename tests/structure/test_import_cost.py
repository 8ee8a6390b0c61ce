"""What ``import torchcal``, the command line's door and reading a URDF load (issue 33 §3): no
plotting library, no scipy, no URDF mesh library, no pytorch-kinematics (whose IK module loads
matplotlib), checked on ``sys.modules`` of a fresh interpreter rather than on a clock that depends
on the machine."""
from __future__ import annotations

import json
import os
import subprocess
import sys
from pathlib import Path

REPO = Path(__file__).resolve().parents[2]
HEAVY = ("matplotlib", "scipy", "trimesh", "yourdfpy", "pytorch_kinematics")
# a Jupyter kernel exports this; before matplotlib was lazy it broke torchcal's import
NOTEBOOK_BACKEND = "module://matplotlib_inline.backend_inline"


def _loaded_after(code: str) -> tuple[list[str], subprocess.CompletedProcess]:
    probe = (f"import sys, json\n{code}\n"
             f"print(json.dumps(sorted({{m.split('.')[0] for m in sys.modules}} & set({list(HEAVY)!r}))))")
    env = {**os.environ, "PYTHONPATH": str(REPO), "MPLBACKEND": NOTEBOOK_BACKEND}
    r = subprocess.run([sys.executable, "-c", probe], capture_output=True, text=True, env=env, cwd=REPO, timeout=300)
    assert r.returncode == 0, r.stderr
    return json.loads(r.stdout.strip().splitlines()[-1]), r


def test_import_loads_no_plotting_scipy_or_mesh_library():
    loaded, _ = _loaded_after("import torchcal")
    assert loaded == [], f"import torchcal loads {loaded}: import them where a command uses them"


# the door: help texts, and a refusal of a missing file (what a new user meets first)
DOOR = [["--help"], ["calibrate", "--help"], ["loop", "--help"], ["fleet", "--help"], ["plan", "--help"],
        ["calibrate", "--robot", "missing.urdf", "--data", "missing.csv", "--out", "o"]]


def test_the_command_line_door_loads_none_of_them():
    code = ("from torchcal.cli.app import main\n"
            f"for argv in {DOOR!r}:\n"
            "    try:\n        rc = main(argv)\n    except SystemExit as e:\n        rc = e.code\n"
            "    print(argv[0], 'rc', rc, file=sys.stderr)")
    loaded, r = _loaded_after(code)
    assert "Traceback" not in r.stderr, r.stderr
    assert r.stderr.count(" rc ") == len(DOOR) and "missing.csv" in r.stderr  # every door was reached
    assert loaded == [], f"the command line's help and refusals load {loaded}"


def test_reading_a_urdf_loads_no_mesh_library():
    # meshes are read only where a plan checks mesh collision shapes; a robot from a URDF needs none
    loaded, _ = _loaded_after("from torchcal import Robot\nfrom torchcal.kinematics.robots import urdf_path\n"
                              "r = Robot.from_urdf(urdf_path('ur5e'), markers=['flange'])\nassert r.dof == 6")
    assert loaded == [], f"reading a URDF loads {loaded}"
