"""The report pages as a browser lays them out (issue 35 §3): ``report.html`` of a loop and
``fleet.html`` of a fleet rendered in headless Chromium, where a script added to a copy of each
page measures every element against the page's width and follows every "evidence" link to the
figure it names. Skipped, saying so, where Chromium is not installed."""
from __future__ import annotations

import json
import subprocess

import pytest

# measured in the page once it is laid out; the result is written into the DOM Chromium dumps
CHECK = """<script>
(() => {
  const W = document.documentElement.clientWidth, wide = [];
  for (const el of document.body.querySelectorAll('*')) {
    const r = el.getBoundingClientRect();
    if (r.width > 0 && (r.right > W + 0.5 || r.left < -0.5)) {
      wide.push(el.tagName + ' ' + Math.round(r.right) + 'px: ' + (el.textContent || '').trim().slice(0, 60));
    } else if (el.scrollWidth > el.clientWidth + 1 && getComputedStyle(el).overflowX !== 'visible') {
      wide.push(el.tagName + ' scrolls: ' + (el.textContent || '').trim().slice(0, 60));
    }
  }
  const links = [...document.querySelectorAll('a')].filter(a => a.textContent.trim() === 'evidence');
  const evidence = links.map(a => {
    const t = document.getElementById((a.getAttribute('href') || '').slice(1));
    const img = t ? t.querySelector('img') : null;
    return {href: a.getAttribute('href'), finding: a.closest('li') ? a.closest('li').textContent : '',
            target: t ? t.tagName : null, alt: img ? img.alt : null};
  });
  const out = document.createElement('pre');
  out.id = 'page-check';
  out.textContent = JSON.stringify({width: W, page: document.documentElement.scrollWidth, wide, evidence});
  document.body.appendChild(out);
})();
</script>"""
FLAGS = ["--headless", "--no-sandbox", "--disable-gpu", "--hide-scrollbars"]


def _measure(chromium: str, page, tmp_path, width: int) -> dict:
    copy = tmp_path / f"checked_{page.stem}_{width}.html"
    copy.write_text(page.read_text().replace("</body>", CHECK + "\n</body>"))
    dom = subprocess.run([chromium, *FLAGS, f"--user-data-dir={tmp_path / 'profile'}", f"--window-size={width},900",
                          "--dump-dom", copy.as_uri()], capture_output=True, text=True, timeout=180).stdout
    start = dom.index('<pre id="page-check">') + len('<pre id="page-check">')
    import html

    return json.loads(html.unescape(dom[start:dom.index("</pre>", start)]))


@pytest.mark.slow
@pytest.mark.parametrize("width", [1280, 900])
def test_no_element_of_the_loop_report_is_wider_than_the_page(looped_report, chromium, tmp_path, width):
    got = _measure(chromium, looped_report / "report.html", tmp_path, width)
    assert got["width"] <= width and got["page"] <= got["width"], got["page"]
    assert not got["wide"], "wider than the page: " + "; ".join(got["wide"][:8])


@pytest.mark.slow
def test_every_evidence_link_points_at_its_own_figure(looped_report, chromium, tmp_path):
    ev = _measure(chromium, looped_report / "report.html", tmp_path, 1280)["evidence"]
    assert len(ev) >= 2, ev  # the compliant UR5e: several joints found, each with a link
    assert len({e["href"] for e in ev}) == len(ev), [e["href"] for e in ev]
    for e in ev:
        assert e["target"] == "FIGURE" and e["alt"], e
        mode = e["alt"].rsplit(": ", 1)[1]  # "evidence for joint_compliance: elbow_joint.twist"
        assert mode.split(".")[0] in e["finding"], e  # the figure of the joint the finding names


@pytest.mark.slow
@pytest.mark.parametrize("width", [1280, 900])
def test_no_element_of_the_fleet_report_is_wider_than_the_page(fleet_report_out, chromium, tmp_path, width):
    got = _measure(chromium, fleet_report_out / "fleet.html", tmp_path, width)
    assert got["page"] <= got["width"] and not got["wide"], "wider than the page: " + "; ".join(got["wide"][:8])
    robot = _measure(chromium, fleet_report_out / "kr5_06" / "report.html", tmp_path, width)
    assert not robot["wide"], "wider than the page: " + "; ".join(robot["wide"][:8])
