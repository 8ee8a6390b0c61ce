"""The README is the proof: every fenced ```bash and ```python block of README.md runs as written.

How the test reads the README:
* Blocks run in the order they appear, in one temporary folder (a user's working copy): later
  blocks use what earlier ones wrote (``cell1/model`` from ``torchcal loop``). ``urdf/``,
  ``models/``, ``scripts/`` and the ``Makefile`` are linked into it; ``out/demo`` is made first by
  the demo's script (``python scripts/demo.py``, what ``make demo`` runs, on fewer poses), since
  ``make`` itself does not run here.
* A ``bash`` block runs under ``bash -e -o pipefail`` (the first failing command fails it), with
  ``torchcal`` and ``python`` on the PATH meaning this checkout and this interpreter; a ``python``
  block runs as a script in a fresh interpreter. Each has 10 minutes.
* A block that only illustrates (it would install, recurse into ``make test``, or needs hardware)
  carries a visible note on the line just above its fence, in italics::

      *(illustration, not run by the README test: the reason)*

  It is skipped, and its reason must be given. Nothing else skips a block.
* Only ``bash`` and ``python`` run. Other shell or Python spellings (``sh``, ``console``, ``py``…)
  are refused by :func:`test_every_runnable_block_is_bash_or_python`, so that no block escapes
  the test by its fence; text, YAML, tree listings and the like are not code to run.

New blocks are picked up as they are written; the slow test is ``make test``'s, not a quick check.
"""
from __future__ import annotations

import os
import re
import subprocess
import sys
from dataclasses import dataclass
from pathlib import Path

import pytest

REPO = Path(__file__).resolve().parents[2]
README = REPO / "README.md"
ILLUSTRATION = re.compile(r"^\*\(illustration, not run by the README test: (?P<why>.+)")
RUN = ("bash", "python")
REFUSED = ("sh", "shell", "console", "zsh", "py", "python3", "pycon", "ipython")
LINKED = ("urdf", "models", "scripts", "Makefile")


@dataclass
class Block:
    line: int  # the line of the opening fence (1-based)
    lang: str
    code: str
    illustration: str | None  # the reason given, for a block that only illustrates


def readme_blocks(text: str) -> list[Block]:
    """Every fenced block of ``text``, with its language and the illustration note above it."""
    lines = text.splitlines()
    out, i = [], 0
    while i < len(lines):
        m = re.match(r"^(\s*)(```+|~~~+)\s*([\w+-]*)", lines[i])
        if not m:
            i += 1
            continue
        fence, start = m.group(2), i
        j = i + 1
        while j < len(lines) and not lines[j].strip().startswith(fence):
            j += 1
        above = start - 1
        while above >= 0 and not lines[above].strip():
            above -= 1
        # a note of several lines: its first line starts the italic parenthesis; a fence ends the search
        first, note = above, None
        while first >= 0 and lines[first].strip() and not lines[first].lstrip().startswith(("```", "~~~")):
            if lines[first].lstrip().startswith("*("):
                note = ILLUSTRATION.match(lines[first].strip())
                break
            first -= 1
        out.append(Block(start + 1, m.group(3).lower(), "\n".join(lines[start + 1:j]) + "\n",
                         note.group("why").rstrip(" )*") if note else None))
        i = j + 1
    return out


def test_every_runnable_block_is_bash_or_python():
    blocks = readme_blocks(README.read_text())
    odd = [(b.line, b.lang) for b in blocks if b.lang in REFUSED]
    assert not odd, f"README.md blocks {odd}: write ```bash or ```python so that tests/structure/test_readme_blocks.py runs them"
    run = [b for b in blocks if b.lang in RUN and b.illustration is None]
    assert len(run) >= 4, f"only {len(run)} README blocks run; the README test would prove little"
    for b in blocks:
        if b.lang in RUN and b.illustration is not None:
            assert len(b.illustration) > 10, f"README.md line {b.line}: say why the block is not run"


def test_the_block_reader_sees_notes_and_fences():
    text = ("intro\n\n```bash\necho run\n```\n\n*(illustration, not run by the README test: it installs.)*\n"
            "```python\nimport nothing\n```\n```\nplain\n```\n")
    b = readme_blocks(text)
    assert [(x.line, x.lang, x.illustration) for x in b] == [(3, "bash", None), (8, "python", "it installs."),
                                                             (11, "", None)]
    assert b[0].code == "echo run\n" and b[1].code == "import nothing\n"


def _shims(bin_dir: Path) -> None:
    """``torchcal`` and ``python`` as a user of this checkout has them."""
    bin_dir.mkdir()
    for name, cmd in (("torchcal", f'"{sys.executable}" -m torchcal'), ("python", f'"{sys.executable}"')):
        p = bin_dir / name
        p.write_text(f'#!/bin/sh\nexec {cmd} "$@"\n')
        p.chmod(0o755)


def _tail(text: str, n: int = 4000) -> str:
    return text if len(text) <= n else "…" + text[-n:]


@pytest.mark.slow
def test_every_readme_block_runs_as_written(tmp_path):
    blocks = [b for b in readme_blocks(README.read_text()) if b.lang in RUN]
    work = tmp_path / "work"
    work.mkdir()
    for name in LINKED:
        os.symlink(REPO / name, work / name)
    _shims(tmp_path / "bin")
    env = {**os.environ, "PYTHONPATH": str(REPO), "PATH": f"{tmp_path / 'bin'}{os.pathsep}{os.environ['PATH']}",
           "MPLBACKEND": "Agg"}
    env.pop("TORCHCAL_THREADS", None)  # the library's default threading, as a user gets it
    demo = subprocess.run([sys.executable, "scripts/demo.py", "--out", "out/demo", "--poses", "120", "--test-poses",
                           "40", "--targets", "4"], cwd=work, env=env, capture_output=True, text=True, timeout=600)
    assert demo.returncode == 0, f"the demo failed:\n{_tail(demo.stderr)}"
    ran = []
    for b in blocks:
        if b.illustration is not None:
            continue
        if b.lang == "bash":
            cmd = ["bash", "-e", "-o", "pipefail", "-c", b.code]
        else:
            script = work / f".readme_line_{b.line}.py"
            script.write_text(b.code)
            cmd = [sys.executable, script.name]
        p = subprocess.run(cmd, cwd=work, env=env, capture_output=True, text=True, timeout=600)
        assert p.returncode == 0, (f"README.md line {b.line} ({b.lang}) failed with status {p.returncode}:\n"
                                   f"{b.code}\n--- stdout\n{_tail(p.stdout)}\n--- stderr\n{_tail(p.stderr)}")
        ran.append((b, p.stdout))
    assert ran, "no README block ran"
    # what a block claims in a comment, where a wrong claim would fail no command
    api = [out for b, out in ran if "Corrector(model).correct(" in b.code]
    assert api and re.search(r"^True tensor\(\[", api[0], re.M), \
        f"the Python API block's comment says it prints True and the commands:\n{api}"
