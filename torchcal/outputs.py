"""Writing results without losing anything.

* Nothing is overwritten unless asked (``force``): a run that would replace a directory or a
  file is refused with a message naming the path.
* Whether an output can be written is checked before the work starts, not after an hour of it.
* Files are written under a temporary name and renamed into place; a directory of results is
  built under a temporary name beside its final one and renamed when complete. An interrupted
  run leaves no half-written result behind.
* Every result carries its provenance: date, versions, the command line and the SHA-256 of the
  files it was made from.
"""
from __future__ import annotations

import datetime as _dt
import hashlib
import os
import platform
import shutil
import sys
import tempfile
from contextlib import contextmanager
from pathlib import Path
from typing import Iterator

import torch

from torchcal.version import __version__

__all__ = ["check_out_dir", "check_out_file", "staged_dir", "atomic_write_text", "atomic_write_bytes",
           "sha256_file", "provenance"]


def _writable_parent(p: Path) -> None:
    parent = p.parent if str(p.parent) else Path(".")
    try:
        parent.mkdir(parents=True, exist_ok=True)
        with tempfile.NamedTemporaryFile(dir=parent, prefix=".torchcal-probe-"):
            pass
    except OSError as e:
        raise PermissionError(f"cannot write under {parent.resolve()}: {e.strerror or e}; choose another output "
                              "path") from None


def check_out_dir(path, force: bool = False) -> Path:
    """Refuse an existing, non-empty output directory (unless ``force``) or a file in its place,
    and check that it can be written, before any work starts."""
    p = Path(path)
    if p.exists() and not p.is_dir():
        raise FileExistsError(f"{p} exists and is a file, not a directory; choose another output directory")
    if p.is_dir() and any(p.iterdir()) and not force:
        raise FileExistsError(f"{p} exists and is not empty; torchcal does not overwrite results: choose another "
                              "output directory, or pass --force (force=True) to replace it")
    _writable_parent(p)
    return p


def check_out_file(path, force: bool = False, inputs: tuple = ()) -> Path:
    """Refuse an existing output file (unless ``force``) and one that is also an input (which
    would be destroyed while it is read), and check that it can be written."""
    p = Path(path)
    for src in inputs:
        if src is not None and Path(src).exists() and p.exists() and p.resolve() == Path(src).resolve() and not force:
            raise FileExistsError(f"{p} is also an input of this command; writing it would destroy the input: "
                                  "choose another output path (or pass --force)")
    if p.is_dir():
        raise IsADirectoryError(f"{p} is a directory; give a file path")
    if p.exists() and not force:
        raise FileExistsError(f"{p} exists; torchcal does not overwrite it: choose another path, or pass --force")
    _writable_parent(p)
    return p


@contextmanager
def staged_dir(path, force: bool = False) -> Iterator[Path]:
    """Yield a temporary directory beside ``path``; when the block ends without error it takes
    ``path``'s place (an existing one only with ``force``), otherwise it is removed."""
    p = check_out_dir(path, force)
    tmp = Path(tempfile.mkdtemp(prefix=f".{p.name}.", suffix=".partial", dir=p.parent if str(p.parent) else "."))
    try:
        yield tmp
    except BaseException:
        shutil.rmtree(tmp, ignore_errors=True)
        raise
    old = None
    if p.exists():
        old = p.with_name(f".{p.name}.replaced-{os.getpid()}")
        os.rename(p, old)
    os.rename(tmp, p)
    if old is not None:
        shutil.rmtree(old, ignore_errors=True)


def atomic_write_bytes(path, data: bytes) -> None:
    """Write ``data`` to ``path`` through a temporary file in the same directory and a rename."""
    p = Path(path)
    fd, tmp = tempfile.mkstemp(prefix=f".{p.name}.", suffix=".partial", dir=p.parent if str(p.parent) else ".")
    try:
        with os.fdopen(fd, "wb") as fh:
            fh.write(data)
        os.replace(tmp, p)
    except BaseException:
        if os.path.exists(tmp):
            os.unlink(tmp)
        raise


def atomic_write_text(path, text: str) -> None:
    atomic_write_bytes(path, text.encode())


def sha256_file(path) -> str:
    h = hashlib.sha256()
    with open(path, "rb") as fh:
        for block in iter(lambda: fh.read(1 << 20), b""):
            h.update(block)
    return h.hexdigest()


def provenance(files: dict | None = None, argv: list[str] | None = None) -> dict:
    """Where a result came from: UTC date, torchcal / torch / Python versions, the command line,
    and ``role -> {path, sha256}`` of the input ``files`` (``role -> path``; None entries skipped)."""

    return {"date": _dt.datetime.now(_dt.timezone.utc).isoformat(timespec="seconds"),
            "torchcal": __version__, "torch": torch.__version__, "python": platform.python_version(),
            "command": list(sys.argv if argv is None else argv),
            "files": {k: {"path": str(Path(v).resolve()), "sha256": sha256_file(v)}
                      for k, v in (files or {}).items() if v is not None and Path(v).is_file()}}
