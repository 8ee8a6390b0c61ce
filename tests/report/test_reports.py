"""Reports that tell the truth (issue 25, item 5) and the files every output directory holds
(item 4's calibration.yaml): through the command line for loop, calibrate, fleet and plan; the
report pieces (significance, units, dates, noise floor, outliers, figures, the HTML page) checked
against numbers computed here."""
from __future__ import annotations

import json
import math
import re
import subprocess

import numpy as np
import pytest
import torch
import yaml

from torchcal import Robot
from torchcal.cli.app import main as cli
from torchcal.effects.compliance import JointCompliance
from torchcal.kinematics.robots import urdf_path
from torchcal.measure.stats import error_stats, noise_floor
from torchcal.report.figures import error_figure, evidence_figure, fleet_figure, plan_figure, readable_axis
from torchcal.report.findings import effect_findings
from torchcal.report.plotting import overlapping_labels
from torchcal.report.sections import flags_section
from torchcal.report.units import shown, with_error

from conftest import MOVED  # held-out rows of the report data moved by 8 mm

UR5E, KR5 = str(urdf_path("ur5e")), str(urdf_path("kuka_kr5_arc"))


# the compliant UR5e's data, its loop and a 10-KR5 fleet are tests/conftest.py's (the HTML checks in
# tests/report/ read the same pages)
@pytest.fixture(scope="module")
def data(report_data):
    return report_data


@pytest.fixture(scope="module")
def looped(looped_report):
    return looped_report


# ----------------------------------------------------------------------------- every output directory
@pytest.mark.slow
def test_loop_writes_calibration_yaml_and_report_html(looped):
    for f in ("calibrated.urdf", "calibration.yaml", "report.md", "report.html", "report.json"):
        assert (looped / f).is_file(), f
    cal = yaml.safe_load((looped / "calibration.yaml").read_text())
    assert cal["robot"] == "ur5e" and cal["units"]["x"] == "m" and cal["corrections"]
    rep = json.loads((looped / "report.json").read_text())
    geo = {p["name"]: p["value"] for p in rep["parameters"]}
    j, c = next(iter(cal["corrections"].items()))
    for key, slot in (("x", "dx"), ("roll", "droll")):  # the correction is the fitted error itself
        assert c[key] == pytest.approx(geo.get(f"{j}.{slot}", 0.0), abs=1e-15)


@pytest.mark.slow
def test_calibrate_and_fleet_write_calibration_yaml_and_report_html(data, tmp_path):
    d, _ = data
    assert cli(["calibrate", "--robot", UR5E, "--data", str(d / "train.csv"), "--test", str(d / "test.csv"),
                "--out", str(tmp_path / "cal")]) == 0
    for f in ("calibrated.urdf", "calibration.yaml", "report.html", "errors.png", "errors_test.png"):
        assert (tmp_path / "cal" / f).is_file(), f
    md = (tmp_path / "cal" / "report.md").read_text()
    assert "| train mean | train RMSE | train p95 | train max | test mean | test RMSE | test p95 | test max |" in md
    html = (tmp_path / "cal" / "report.html").read_text()
    assert html.count("data:image/png;base64,") == 2 and "<table>" in html


@pytest.fixture(scope="module")
def fleet_out(fleet_report_out):
    return fleet_report_out


@pytest.mark.slow
def test_fleet_writes_each_robots_files_and_a_spread_figure(fleet_out):
    rep = json.loads((fleet_out / "fleet.json").read_text())
    assert [(f["robot"], f["parameter"]) for f in rep["flags"]] == [("kr5_06", "joint_a3.offset")]
    for i in range(10):
        d = fleet_out / f"kr5_{i:02d}"
        for f in ("calibrated.urdf", "calibration.yaml", "report.html"):
            assert (d / f).is_file(), (d, f)
    offsets = [yaml.safe_load((fleet_out / f"kr5_{i:02d}" / "calibration.yaml").read_text())["zero_offsets"]
               .get("joint_a3", 0.0) for i in range(10)]
    others = float(np.median(offsets[:6] + offsets[7:]))
    assert abs(offsets[6] - others - 8e-3) < 1e-3  # the moved axis stands 8 mrad out, in rad as stated
    md = (fleet_out / "fleet.md").read_text()
    assert "![each parameter's spread" in md and (fleet_out / "fleet_spread.png").is_file()
    assert "| train RMSE | train p95 | train max |" in md
    page = (fleet_out / "fleet.html").read_text()
    assert 'href="kr5_06/report.html"' in page and "data:image/png;base64," in page


def test_fleet_figure_marks_the_flagged_robot(tmp_path):
    from torchcal.report.fleet import spread_rows
    rows = [{"name": "joint_a3.offset", "z": np.array([0.3, -1.0, 9.5, 0.2, 0.8]), "robots": list("abcde"),
             "flagged": {"c"}, "z_needed": 7.0},
            {"name": "joint_a2.offset", "z": np.array([0.1, 0.4, -0.3, 1.2, -0.9]), "robots": list("abcde"),
             "flagged": set(), "z_needed": 7.0}]
    fig = fleet_figure(rows, tmp_path / "f.png", 5.0, "test")
    texts = [t.get_text() for t in fig.findobj(lambda a: hasattr(a, "get_text"))]
    assert "c" in texts and "a" not in texts  # only the flagged robot is named
    assert [t.get_text() for t in fig.axes[0].get_yticklabels()] == ["joint_a2.offset", "joint_a3.offset"]
    assert not overlapping_labels(fig)
    assert spread_rows is not None


# ----------------------------------------------------------------------------- what the report states
@pytest.mark.slow
def test_heldout_outliers_are_listed(looped):
    rep = json.loads((looped / "report.json").read_text())
    assert sorted(s["row"] for s in rep["suspect_rows_test"]) == sorted(MOVED)
    assert all(7.0 < s["error_mm"] < 9.0 for s in rep["suspect_rows_test"])
    md = (looped / "report.md").read_text()
    assert "2 suspect observation(s) among the held-out rows" in md and "held-out file order" in md
    assert "suspect_rows" in rep and "stages" in rep and "effects" in rep  # the existing keys stay


@pytest.mark.slow
def test_tables_show_rmse_and_p95(looped):
    rep = json.loads((looped / "report.json").read_text())
    md = (looped / "report.md").read_text()
    fin = rep["stages"][-1]
    row = next(x for x in md.splitlines() if x.startswith(f"| {fin['name']} |"))
    cells = [c.strip() for c in row.strip("|").split("|")]
    assert cells[2:6] == [f"{fin['train'][k]:.4f}" for k in ("mean_mm", "rmse_mm", "p95_mm", "max_mm")]
    assert cells[6:10] == [f"{fin['test'][k]:.4f}" for k in ("mean_mm", "rmse_mm", "p95_mm", "max_mm")]
    e = torch.tensor(np.random.default_rng(1).exponential(1e-4, 101))
    st = error_stats(e)
    assert st["p95_mm"] == pytest.approx(float(np.percentile(e.numpy() * 1e3, 95)), rel=1e-12)
    assert st["rmse_mm"] == pytest.approx(float(np.sqrt(np.mean((e.numpy() * 1e3) ** 2))), rel=1e-12)


@pytest.mark.slow
def test_noise_floor_states_its_source(looped, data):
    _, med = data
    rep = json.loads((looped / "report.json").read_text())
    assert rep["noise_floor_mm"] == pytest.approx(med, rel=1e-9)
    assert "marker_std_mm" in rep["noise_floor_source"]
    assert f"noise floor {med:.4f} mm, the median of the data's `marker_std_mm` column" in (looped / "report.md").read_text()


def test_noise_floor_from_repeated_commands():
    """Rows that repeat a command: their pooled spread is the noise; known σ = 0.05 mm."""
    robot = Robot.from_urdf(KR5, markers=["flange"])
    g = torch.Generator().manual_seed(3)
    q = torch.rand(40, 6, generator=g, dtype=torch.float64).repeat(5, 1)
    p = robot.positions(q) + 5e-5 * torch.randn(200, 1, 3, generator=g, dtype=torch.float64)
    from torchcal.measure.data import Measurements
    d = Measurements(q, p, ["flange"], list(robot.joint_names))
    v, src = noise_floor(d)
    assert v == pytest.approx(0.05 * 2 * math.sqrt(2 / math.pi), rel=0.08) and "pure error of 40 repeated" in src
    # the pure error is measured on these very rows: it comes before the instrument's specification
    assert noise_floor(d, 0.03)[0] == pytest.approx(v)
    once = d.subset(torch.arange(40))
    assert noise_floor(once) == (None, None)
    assert noise_floor(once, 0.03) == (0.03, "given by the caller (noise_mm, --noise-floor-mm: from the "
                                             "instrument's specification)")


def test_a_finding_is_stated_only_when_significant():
    """The UR5e report said "the base is not quite level" from 4.45 ± 6.2 mrad."""
    eff = JointCompliance(Robot.from_urdf(UR5E, markers=["flange"]))
    names = eff.param_names
    vals = dict.fromkeys(names, 0.0)
    se = dict.fromkeys(names, 1e-6)
    vals["joint_compliance.elbow_joint.twist"] = 9.1e-6
    vals["joint_compliance.payload.m"], se["joint_compliance.payload.m"] = 2.5, 0.1
    vals["joint_compliance.gravity.tilt_x"], se["joint_compliance.gravity.tilt_x"] = 4.45e-3, 6.2e-3
    se["joint_compliance.gravity.tilt_y"] = 6.2e-3
    f = effect_findings(eff, vals, se)
    assert not any("level" in s for s in f.stated)
    assert any("elbow_joint twists" in s and "9.1 µrad per N·m" in s for s in f.stated)
    assert any(s.startswith("gravity:") and "4.450 ± 6.2 mrad" in s for s in f.not_significant)
    vals["joint_compliance.gravity.tilt_x"] = 40e-3  # 6.5 standard errors: now it is a finding
    assert any("not quite level" in s for s in effect_findings(eff, vals, se).stated)


@pytest.mark.slow
def test_the_loop_report_states_significant_findings_only(looped):
    rep = json.loads((looped / "report.json").read_text())
    md = (looped / "report.md").read_text()
    from scipy import stats
    eff = {e["stage"]: e for e in rep["effects"]}
    for f in rep["findings"]:
        a = eff[f["stage"]]
        for g in f["groups"]:  # recomputed here from the values and standard errors in report.json
            chi2 = sum((a["params"][n] / a["standard_errors"][n]) ** 2 for n in g["params"])
            assert g["significant"] == bool(stats.chi2.sf(chi2, len(g["params"])) < 2 * stats.norm.sf(3.0)), g
        for s in f["stated"]:
            assert s in md
    assert any(g["significant"] for f in rep["findings"] for g in f["groups"])
    tilt = [g for f in rep["findings"] for g in f["groups"] if g["label"] == "gravity"]
    if tilt and not tilt[0]["significant"]:
        assert "not quite level" not in md


@pytest.mark.slow
def test_one_display_unit_per_quantity(looped):
    md = (looped / "report.md").read_text()
    for raw in ("rad/N/m", "rad/(N*m)", "kg*m", "rad/N "):
        assert raw not in md
    assert "µrad/(N·m)" in md
    effect_rows = [x for x in md.splitlines() if x.startswith("| joint_compliance.")]
    assert effect_rows and not any(re.search(r"\d[eE][-+]?\d", x) for x in effect_rows)
    assert shown(6.6e-05, "rad/N/m") == shown(6.6e-05, "rad/(N*m)") == ("66.00", "µrad/(N·m)")
    assert with_error(4.45e-3, 6.2e-3, "rad") == "4.450 ± 6.2 mrad"


def test_time_covariates_are_printed_as_dates():
    flag = {"effect": "thermal_drift", "covariate": "t_start_robot", "train_range": [1.63829e9, 1.6383e9],
            "test_range": [1.6384e9, 1.6385e9], "fraction_outside": 1.0, "note": "time does not extrapolate"}
    text = "\n".join(flags_section([flag]))
    assert "2021-11-30T" in text and "2021-12-01T" in text and "e+09" not in text
    assert readable_axis("t_start_robot − reference [s]", [-86400.0, 86400.0]) == ("t_start_robot − reference [h]",
                                                                                   1 / 3600)


# ----------------------------------------------------------------------------- figures
def _details(n: int, scale: float, seed: int) -> dict:
    g = torch.Generator().manual_seed(seed)
    xyz = scale * torch.randn(n, 3, generator=g, dtype=torch.float64)
    return {"e": xyz.norm(dim=-1), "xyz": xyz, "dist": 0.3 + torch.rand(n, generator=g, dtype=torch.float64)}


def test_the_overlap_check_sees_overlaps(tmp_path):
    from torchcal.report.plotting import pyplot, save
    fig, ax = pyplot().subplots(figsize=(3, 2))
    ax.set_title("a title")
    ax.text(0.5, 0.5, "one label")
    ax.text(0.52, 0.5, "another label")
    assert overlapping_labels(fig) == [("one label", "another label")]
    ax.set_xticks([0.0, 0.001], ["left tick", "its neighbour"])  # two tick labels on each other
    save(fig, tmp_path / "o.png")  # hides the later of two colliding tick labels
    assert [t.get_text() for t in ax.get_xticklabels() if t.get_visible()] == ["left tick"]


@pytest.mark.slow
def test_error_figure_shows_every_axis_before_and_after(tmp_path):
    stages = [("before", _details(80, 2e-3, 0)), ("geometric", _details(80, 3e-4, 1)), ("full", _details(80, 2e-5, 2))]
    fig = error_figure(stages, tmp_path / "e.png", noise_floor_mm=0.03)
    per_axis = next(a for a in fig.axes if a.get_title().startswith("per axis"))
    assert [t.get_text() for t in per_axis.get_xticklabels()] == ["x", "y", "z"]
    assert len([p for p in per_axis.patches]) == 9  # 3 stages × 3 axes
    # one legend for the four panels, outside every panel: it covers none of the boxes
    assert per_axis.get_legend() is None and len(fig.legends) == 1
    keys = [t.get_text() for t in fig.legends[0].get_texts()]
    assert [k.split(":")[0] for k in keys] == ["before", "geometric", "full", "noise floor 0.030 mm"]
    fig.canvas.draw()
    legend, boxes = fig.legends[0].get_window_extent(), per_axis.get_window_extent()
    assert legend.y1 < boxes.y0 or legend.x0 > boxes.x1 or legend.y0 > boxes.y1
    assert not overlapping_labels(fig)


def test_evidence_panels_in_joint_order(tmp_path):
    """Panels follow the robot's joints whatever order the modes come in; a mode without an
    independent signature says so (the loop's own evidence without inertials:
    cli/test_integrator_workflow.py::test_figures_and_evidence_without_inertials)."""
    robot = Robot.from_urdf(KR5, markers=["flange"])
    order = [jt.name for jt in robot.joints]
    x = np.linspace(-2, 2, 40)
    ev = {f"{j}.twist": {"x": x.tolist(), "residual": (1e-5 * np.sin(x + k)).tolist(), "fitted": (1e-5 * np.sin(x + k))
                         .tolist(), "r": 0.99, "xlabel": f"{j} angle [rad]", "ylabel": "joint twist [rad]",
                         "independent": False, "note": "no signature independent of the fit"}
          for k, j in enumerate(["joint_a5", "joint_a2", "joint_a3", "joint_a1"])}
    fig = evidence_figure("joint_compliance", ev, tmp_path / "ev.png", order)
    titles = [a.get_title().split(" ")[0] for a in fig.axes if a.get_title()]
    assert titles == ["joint_a1.twist", "joint_a2.twist", "joint_a3.twist", "joint_a5.twist"]
    assert all("no independent signature" in a.get_title() for a in fig.axes if a.get_title())
    assert fig.axes[0].get_ylabel() == "joint twist [µrad]"
    assert not overlapping_labels(fig)


def test_plan_writes_a_coverage_figure(tmp_path):
    out = tmp_path / "poses.csv"
    assert cli(["plan", "--robot", KR5, "--marker", "smr@flange=0,0,0", "--candidates", "300", "--select", "12",
                "--refine-steps", "0", "--reachable=-1.2,1.2,-1.2,1.2,0.2,1.6", "--out", str(out)]) == 0
    assert (tmp_path / "poses.plan.png").read_bytes()[:8] == b"\x89PNG\r\n\x1a\n"
    assert "](poses.plan.png)" in (tmp_path / "poses.plan.md").read_text()
    robot = Robot.from_urdf(KR5, markers=["flange"])
    q = np.random.default_rng(0).uniform(-1, 1, (12, 6))
    lo, hi = (x.numpy() for x in robot.joint_limits)
    fig = plan_figure(q, (lo, hi), list(robot.joint_names), robot.positions(torch.tensor(q)).numpy(),
                      tmp_path / "p.png", box=[-1.2, 1.2, -1.2, 1.2, 0.2, 1.6])
    assert [t.get_text() for t in fig.axes[0].get_yticklabels()] == list(reversed(robot.joint_names))
    assert len(fig.axes) == 3 and not overlapping_labels(fig)


# ----------------------------------------------------------------------------- the HTML page
@pytest.mark.slow
def test_report_html_renders_in_headless_chromium(looped, tmp_path, chromium):
    browser = chromium
    page = (looped / "report.html").as_uri()
    flags = ["--headless", "--no-sandbox", "--disable-gpu", "--hide-scrollbars", f"--user-data-dir={tmp_path / 'p'}"]
    dom = subprocess.run([browser, *flags, "--dump-dom", page], capture_output=True, text=True, timeout=120).stdout
    assert "<title>Calibration loop: ur5e</title>" in dom
    assert dom.count("<table>") >= 5 and dom.count('src="data:image/png;base64,') >= 3
    assert 'href="#fig-evidence_joint_compliance_' in dom and 'id="fig-evidence_joint_compliance_' in dom
    assert "src=\"http" not in dom and "<script" not in dom  # self-contained
    shot = tmp_path / "shot.png"
    subprocess.run([browser, *flags, "--window-size=1280,1800", f"--screenshot={shot}", page], capture_output=True,
                   timeout=120)
    from matplotlib.image import imread
    img = imread(shot)
    assert img.shape[0] == 1800 and img.shape[1] == 1280
    gray = img[..., :3].mean(-1)
    assert gray.std() > 0.05 and (gray < 0.5).mean() > 0.005  # text, tables and figures drawn, not a blank page
