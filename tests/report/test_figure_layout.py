"""Figures a reader can read (issue 35 §3) and that cost one drawing (issue 33 §3): the fleet's
x range holds every bound it draws, the leftover panels keep their labels and title inside the
figure and apart, and a notebook's ``MPLBACKEND`` neither breaks a figure nor is switched."""
from __future__ import annotations

import os
import subprocess
import sys
from pathlib import Path
from types import SimpleNamespace

import numpy as np

from torchcal.report.figures import fleet_figure, leftover_figure
from torchcal.report.plotting import overlapping_labels

REPO = Path(__file__).resolve().parents[2]


def _inside(fig) -> bool:
    """Whether everything drawn (titles, labels, the tick labels in view, legends) lies inside the
    figure: nothing is clipped when it is written."""
    fig.canvas.draw()
    tight, page = fig.get_tightbbox(fig.canvas.get_renderer()), fig.bbox_inches
    tol = 1.0 / fig.dpi  # a pixel
    return (tight.x0 >= page.x0 - tol and tight.y0 >= page.y0 - tol and tight.x1 <= page.x1 + tol
            and tight.y1 <= page.y1 + tol)


def test_the_fleet_figure_shows_every_bound_it_draws(tmp_path):
    # 6 robots: the bound (about 9.9) lies beyond the largest |z| (7), which is not flagged
    rows = [{"name": f"joint_a{i}.offset", "z": np.array([0.3, -1.0, 7.0, 0.2, 0.8, -0.5]),
             "robots": list("abcdef"), "flagged": set(), "z_needed": 9.9} for i in range(1, 4)]
    fig = fleet_figure(rows, tmp_path / "f.png", 5.0, "six robots")
    ax = fig.axes[0]
    lo, hi = ax.get_xlim()
    assert lo < -9.9 and hi > 9.9  # the bound is drawn inside the plot, right of the robot at z = 7
    assert not overlapping_labels(fig) and _inside(fig)


def test_leftover_panels_keep_their_labels_apart_and_inside(tmp_path):
    rng = np.random.default_rng(0)
    signals = ["wrist_3_joint angle", "temperature of the controller cabinet [K]", "shoulder_lift_joint.twist",
               "time since the first row [s]"]
    assoc = [SimpleNamespace(x=rng.uniform(-1, 1, 60).tolist(), y=(1e-5 * rng.standard_normal(60)).tolist(),
                             signal=s, axis="xyz"[i % 3], r2=0.1 + 0.05 * i) for i, s in enumerate(signals)]
    fig = leftover_figure(assoc, tmp_path / "leftover.png")
    assert (tmp_path / "leftover.png").read_bytes()[:8] == b"\x89PNG\r\n\x1a\n"
    assert not overlapping_labels(fig), overlapping_labels(fig)
    assert _inside(fig)


def test_a_notebook_backend_neither_breaks_a_figure_nor_is_switched(tmp_path):
    code = ("import sys, numpy as np\n"
            "from torchcal.report.figures import fleet_figure\n"
            "rows = [{'name': 'a', 'z': np.array([0.1, 2.0, -1.0, 0.5, 0.0]), 'robots': list('abcde'),"
            " 'flagged': set(), 'z_needed': 6.0}]\n"
            f"fleet_figure(rows, {str(tmp_path / 'n.png')!r}, 5.0, 'notebook')\n"
            "print('pyplot' if 'matplotlib.pyplot' in sys.modules else 'no pyplot')\n")
    env = {**os.environ, "PYTHONPATH": str(REPO), "MPLBACKEND": "module://matplotlib_inline.backend_inline"}
    r = subprocess.run([sys.executable, "-c", code], capture_output=True, text=True, env=env, timeout=300)
    assert r.returncode == 0, r.stderr
    assert r.stdout.strip() == "no pyplot" and (tmp_path / "n.png").stat().st_size > 1000
