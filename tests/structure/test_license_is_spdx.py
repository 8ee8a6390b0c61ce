"""``pyproject.toml`` states its licence as an SPDX expression, which setuptools reads without the
deprecation warning a ``{text = …}`` table draws on every install (issue 35 §4)."""
from __future__ import annotations

import shutil
import subprocess
import sys
from pathlib import Path

import pytest

REPO = Path(__file__).resolve().parents[2]


def test_the_metadata_builds_without_a_deprecation_warning_and_names_the_licence(tmp_path):
    setuptools = pytest.importorskip("setuptools")
    if int(setuptools.__version__.split(".")[0]) < 77:
        pytest.skip(f"setuptools {setuptools.__version__} predates SPDX licence strings; pip's build uses >= 77")
    for f in ("pyproject.toml", "README.md"):
        shutil.copy(REPO / f, tmp_path / f)
    (tmp_path / "torchcal").mkdir()
    (tmp_path / "torchcal" / "__init__.py").write_text("")
    code = ("import setuptools.build_meta as b, sys; "
            "print(b.prepare_metadata_for_build_wheel(sys.argv[1]))")
    out = tmp_path / "meta"
    out.mkdir()
    run = subprocess.run([sys.executable, "-W", "always", "-c", code, str(out)], cwd=tmp_path, capture_output=True,
                         text=True, timeout=120)
    assert run.returncode == 0, run.stderr
    assert "DeprecationWarning" not in run.stderr, run.stderr
    meta = (out / run.stdout.strip().splitlines()[-1] / "METADATA").read_text()
    assert "License-Expression: Apache-2.0" in meta, meta[:500]
