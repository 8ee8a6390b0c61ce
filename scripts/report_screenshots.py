"""Full-page screenshots of the report pages, for a reviewer (issue 35 §3): the loop's
``report.html`` on a compliant UR5e (90 training rows, 30 held out) and a 10-robot KR5 fleet's
``fleet.html``, rendered in headless Chromium at 1280 px and saved at half size into ``reports/``.

Usage: python scripts/report_screenshots.py [--out reports] [--work out/screenshots]
(needs Chromium: apt-get install chromium)."""
from __future__ import annotations

import argparse
import html
import re
import shutil
import subprocess
import sys
from pathlib import Path

ROOT = Path(__file__).resolve().parents[1]
sys.path.insert(0, str(ROOT))

from torchcal.cli.app import main as cli  # noqa: E402
from torchcal.kinematics.robots import shipped, urdf_path  # noqa: E402
from torchcal.measure.io import save_measurements  # noqa: E402
from torchcal.sim.serial import SimConfig, simulate_fleet  # noqa: E402

FLAGS = ["--headless", "--no-sandbox", "--disable-gpu", "--hide-scrollbars"]
HEIGHT = '<script>document.body.insertAdjacentHTML("beforeend", "<i id=h>" + ' \
         'document.documentElement.scrollHeight + "</i>")</script>'


def _chromium() -> str:
    for name in ("chromium", "chromium-browser", "google-chrome"):
        if shutil.which(name):
            return shutil.which(name)
    raise SystemExit("headless Chromium is not installed (Debian: apt-get install chromium)")


def screenshot(browser: str, page: Path, png: Path, profile: Path, width: int = 1280) -> None:
    """``page`` as one full-height PNG ``width`` px wide, saved at half that size."""
    page = page.resolve()
    probe = page.with_name(page.stem + "_height.html")
    probe.write_text(page.read_text().replace("</body>", HEIGHT + "</body>"))
    dom = subprocess.run([browser, *FLAGS, f"--user-data-dir={profile}", f"--window-size={width},900",
                          "--dump-dom", probe.as_uri()], capture_output=True, text=True, timeout=180).stdout
    probe.unlink()
    height = int(html.unescape(re.search(r"<i id=\"?h\"?>(\d+)</i>", dom).group(1)))
    full = png.with_name(png.stem + "_full.png")
    subprocess.run([browser, *FLAGS, f"--user-data-dir={profile}", f"--window-size={width},{height}",
                    f"--screenshot={full}", page.as_uri()], capture_output=True, timeout=180, check=True)
    from PIL import Image

    img = Image.open(full).convert("RGB")
    img = img.resize((img.width // 2, img.height // 2), Image.LANCZOS).quantize(colors=128)
    img.save(png, optimize=True)
    full.unlink()
    print(f"{png}: {img.width} x {img.height} px, {png.stat().st_size // 1024} KiB")


def main() -> None:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--out", default=str(ROOT / "reports"))
    ap.add_argument("--work", default=str(ROOT / "out" / "screenshots"))
    args = ap.parse_args()
    browser, out, work = _chromium(), Path(args.out), Path(args.work)
    shutil.rmtree(work, ignore_errors=True)
    work.mkdir(parents=True)
    out.mkdir(parents=True, exist_ok=True)
    ur5e, kr5 = str(urdf_path("ur5e")), str(urdf_path("kuka_kr5_arc"))
    assert cli(["simulate", "--robot", ur5e, "--poses", "120", "--effect", "joint_compliance", "--seed", "4",
                "--out", str(work / "all.csv")]) == 0
    head, *rows = (work / "all.csv").read_text().splitlines()
    (work / "train.csv").write_text("\n".join([head] + rows[:90]) + "\n")
    (work / "test.csv").write_text("\n".join([head] + rows[90:]) + "\n")
    assert cli(["loop", "--robot", ur5e, "--data", str(work / "train.csv"), "--test", str(work / "test.csv"),
                "--no-elm", "--out", str(work / "loop")]) == 0
    cfg = SimConfig(n=30, seed=5)
    train, _, _ = simulate_fleet(shipped("kuka_kr5_arc"), 10, cfg, spread=0.2e-3 / cfg.angle_error,
                                 moved={6: {"joint_a3.offset": 8e-3}})
    (work / "fleet_data").mkdir()
    for i, m in enumerate(train):
        save_measurements(work / "fleet_data" / f"kr5_{i:02d}.csv", m)
    assert cli(["fleet", "--robot", kr5, "--data", str(work / "fleet_data"), "--out", str(work / "fleet")]) == 0
    screenshot(browser, work / "loop" / "report.html", out / "loop_report.png", work / "profile")
    screenshot(browser, work / "fleet" / "fleet.html", out / "fleet_report.png", work / "profile")
    screenshot(browser, work / "fleet" / "kr5_06" / "report.html", out / "fleet_robot_report.png", work / "profile")


if __name__ == "__main__":
    main()
