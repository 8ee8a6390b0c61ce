"""``report.html``: a report's Markdown as one self-contained page.

The page is made from the very Markdown the report writes (so the two never disagree), with every
figure it shows embedded as a base64 PNG, and every link to a figure turned into a link to that
figure on the page: a finding's "evidence" link jumps to its evidence plot. No script, no
stylesheet or font from elsewhere: the file opens anywhere, offline, and can be mailed."""
from __future__ import annotations

import base64
import html
import re
from pathlib import Path

__all__ = ["markdown_to_html", "write_html"]

_CSS = """
body{font:15px/1.45 system-ui,-apple-system,"Segoe UI",sans-serif;max-width:1180px;margin:2em auto;padding:0 1em;
color:#1d232a}
h1{font-size:1.7em;border-bottom:2px solid #ccd3da;padding-bottom:.2em}h2{font-size:1.3em;margin-top:1.8em;
border-bottom:1px solid #e1e5ea}h3{font-size:1.1em}
table{border-collapse:collapse;margin:.8em 0;font-size:13px;max-width:100%}
th,td{border:1px solid #d0d6dc;padding:3px 8px;text-align:right}
td:first-child,td:last-child{overflow-wrap:anywhere}
th{background:#eef1f4}td:first-child,th:first-child{text-align:left}
code{background:#f2f4f6;padding:0 3px;border-radius:3px;overflow-wrap:anywhere}
pre{background:#f2f4f6;padding:.6em;white-space:pre-wrap;overflow-wrap:anywhere}
figure{display:inline-block;vertical-align:top;margin:1em 1em 0 0;max-width:100%}
figure img{max-width:100%;border:1px solid #e1e5ea}figcaption{font-size:13px;color:#55606b}
a{color:#0b5cad}li{margin:.2em 0}
"""

_IMAGE = re.compile(r"^!\[([^\]]*)\]\(([^)\s]+)\)\s*$")
_LINK = re.compile(r"\[([^\]]+)\]\(([^)\s]+)\)")


def _fig_id(target: str) -> str:
    return "fig-" + re.sub(r"[^A-Za-z0-9_-]", "_", Path(target).stem)


def _inline(text: str, figures: set[str], pages: dict[str, str] | None = None) -> str:
    """Escaped text with ``code``, **bold** and [links](…); a link to an embedded figure points at
    it on the page, a link to a Markdown report at its HTML page where one was written
    (``pages``)."""
    parts = re.split(r"(`[^`]*`)", text)
    out = []
    for p in parts:
        if p.startswith("`") and p.endswith("`") and len(p) > 1:
            out.append(f"<code>{html.escape(p[1:-1])}</code>")
            continue
        s = html.escape(p, quote=False)
        s = re.sub(r"\*\*(.+?)\*\*", r"<strong>\1</strong>", s)
        s = _LINK.sub(lambda m: f'<a href="{_href(m.group(2), figures, pages or {})}">{m.group(1)}</a>', s)
        out.append(s)
    return "".join(out)


def _href(target: str, figures: set[str], pages: dict[str, str]) -> str:
    if target in figures:
        return "#" + _fig_id(target)
    return html.escape(pages.get(target, target))


def _slug(text: str, used: set[str]) -> str:
    base = re.sub(r"[^a-z0-9]+", "-", text.lower()).strip("-") or "section"
    s, k = base, 2
    while s in used:
        s, k = f"{base}-{k}", k + 1
    used.add(s)
    return s


def _table(rows: list[str], figures: set[str], pages: dict[str, str]) -> str:
    cells = [[c.strip() for c in r.strip().strip("|").split("|")] for r in rows]
    sep = len(rows) > 1 and set(rows[1].replace("|", "").strip()) <= set("-: ")
    head, body = cells[0], cells[2:] if sep else cells[1:]
    out = ["<table>", "<thead><tr>" + "".join(f"<th>{_inline(c, figures, pages)}</th>" for c in head) + "</tr></thead>",
           "<tbody>"]
    out += ["<tr>" + "".join(f"<td>{_inline(c, figures, pages)}</td>" for c in r) + "</tr>" for r in body]
    return "\n".join(out + ["</tbody>", "</table>"])


def markdown_to_html(md: str, base_dir, title: str) -> str:
    """The report Markdown (headings, paragraphs, lists, tables, code blocks, images, links) as a
    self-contained HTML page; images are read from ``base_dir`` and embedded."""
    base = Path(base_dir)
    lines = md.splitlines()
    figures = {m.group(2) for m in map(_IMAGE.match, lines) if m and (base / m.group(2)).is_file()}
    pages = {t: str(Path(t).with_suffix(".html")) for _, t in _LINK.findall(md)
             if t.endswith(".md") and (base / t).with_suffix(".html").is_file()}
    out, used, i = [], set(), 0
    while i < len(lines):
        line = lines[i]
        if not line.strip():
            i += 1
            continue
        if line.startswith("```"):
            j = i + 1
            while j < len(lines) and not lines[j].startswith("```"):
                j += 1
            out.append("<pre><code>" + html.escape("\n".join(lines[i + 1:j])) + "</code></pre>")
            i = j + 1
            continue
        h = re.match(r"^(#{1,4})\s+(.*)$", line)
        if h:
            n = len(h.group(1))
            out.append(f'<h{n} id="{_slug(h.group(2), used)}">{_inline(h.group(2), figures, pages)}</h{n}>')
            i += 1
            continue
        m = _IMAGE.match(line)
        if m:
            alt, target = m.groups()
            if target in figures:
                data = base64.b64encode((base / target).read_bytes()).decode()
                out.append(f'<figure id="{_fig_id(target)}"><img src="data:image/png;base64,{data}" '
                           f'alt="{html.escape(alt)}"><figcaption>{html.escape(alt)}</figcaption></figure>')
            else:
                out.append(f"<p><em>figure {html.escape(target)} was not written</em></p>")
            i += 1
            continue
        j = i
        if line.startswith("|"):
            while j < len(lines) and lines[j].startswith("|"):
                j += 1
            out.append(_table(lines[i:j], figures, pages))
        elif line.startswith("- "):
            items = []
            while j < len(lines) and (lines[j].startswith("- ") or (lines[j].startswith("  ") and items)):
                if lines[j].startswith("- "):
                    items.append(lines[j][2:])
                else:
                    items[-1] += " " + lines[j].strip()
                j += 1
            out.append("<ul>" + "".join(f"<li>{_inline(t, figures, pages)}</li>" for t in items) + "</ul>")
        else:
            while j < len(lines) and lines[j].strip() and not re.match(r"^(#|\||- |```|!\[)", lines[j]):
                j += 1
            j = max(j, i + 1)
            out.append("<p>" + _inline(" ".join(x.strip() for x in lines[i:j]), figures, pages) + "</p>")
        i = j
    return ("<!DOCTYPE html>\n<html lang=\"en\">\n<head>\n<meta charset=\"utf-8\">\n"
            f"<title>{html.escape(title)}</title>\n<style>{_CSS}</style>\n</head>\n<body>\n"
            + "\n".join(out) + "\n</body>\n</html>\n")


def write_html(out_dir, md_name: str = "report.md", title: str | None = None, html_name: str | None = None) -> Path:
    """``<out_dir>/report.html`` (or ``html_name``) from ``<out_dir>/<md_name>`` and the figures
    beside it. Returns its path."""
    d = Path(out_dir)
    md = (d / md_name).read_text()
    if title is None:
        first = next((x for x in md.splitlines() if x.startswith("# ")), "# report")
        title = first[2:].strip()
    path = d / (html_name or Path(md_name).with_suffix(".html").name)
    path.write_text(markdown_to_html(md, d, title))
    return path
