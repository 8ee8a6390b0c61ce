"""Writing results without losing anything.

* Nothing is overwritten unless asked (``force``): a run that would replace a directory or a
  file is refused with a message naming the path.
* Whether an output can be written is checked before the work starts, not after an hour of it.
* Files are written under a temporary name and renamed into place; a directory of results is
  built under a temporary name beside its final one and renamed when complete. An interrupted
  run leaves no half-written result behind.
* Every result carries its provenance: date, versions, the command line and the SHA-256 of the
  files it was made from. ``force`` replaces only what torchcal wrote (a directory with its
  ``provenance.json`` or ``model.json``), never a folder holding an input of the run.
* A run claims its output before the work (:func:`claim`): a second run on the same output is
  refused while the first holds it.
"""
from __future__ import annotations

import datetime as _dt
import errno
import hashlib
import json
import os
import platform
import shutil
import sys
import tempfile
from contextlib import contextmanager
from pathlib import Path
from typing import Iterator

import torch

from torchcal.advice import advice
from torchcal.version import __version__

__all__ = ["check_out_dir", "check_out_file", "staged_dir", "atomic_write_text", "atomic_write_bytes",
           "sha256_file", "provenance", "claim", "written_by_torchcal", "OutputBusy"]

# files by which a directory says torchcal wrote it: JSON objects that name the torchcal version
_SIGNATURES = ("provenance.json", "model.json")
_VERSION_KEYS = ("torchcal", "torchcal_version")


class OutputBusy(FileExistsError):
    """Another run holds the output (see :func:`claim`)."""


def _existing_ancestor(p: Path) -> Path:
    """The nearest folder above ``p`` that exists (its parent, unless folders are still to make)."""
    a = p.resolve().parent
    while not a.exists():
        a = a.parent
    return a


def _writable_parent(p: Path) -> None:
    """Check that ``p`` can be written: the nearest existing folder above it takes a file. The
    folders still missing are made when the result is written, so a refused run leaves none."""
    parent = _existing_ancestor(p)
    try:
        if not parent.is_dir():
            raise NotADirectoryError(errno.ENOTDIR, "a file stands where a folder should be")
        with tempfile.NamedTemporaryFile(dir=parent, prefix=".torchcal-probe-"):
            pass
    except OSError as e:
        raise PermissionError(f"cannot write under {parent}: {e.strerror or e}; choose another output "
                              "path") from None


def written_by_torchcal(folder) -> bool:
    """Whether ``folder`` is a directory torchcal wrote: it holds a ``provenance.json`` or a
    ``model.json`` that names the torchcal version that wrote it."""
    for name in _SIGNATURES:
        f = Path(folder) / name
        try:
            rec = json.loads(f.read_text())
        except (OSError, ValueError):
            continue
        if isinstance(rec, dict) and any(k in rec for k in _VERSION_KEYS):
            return True
    return False


def _refuse_cwd(p: Path) -> None:
    """The working directory (or a folder above it) cannot become a result: it would be renamed
    from under the shell that runs the command."""
    here, target = Path.cwd().resolve(), p.resolve()
    if target == here or target in here.parents:
        raise IsADirectoryError(f"{p} is the current directory{'' if target == here else ' or above it'}; give a new "
                                f"folder for the results, e.g. {advice(repr('cell1'), '--out cell1')}")


def _holds_input(p: Path, inputs) -> list[str]:
    """The inputs that lie in (or are) ``p``."""
    target = p.resolve()
    out = []
    for src in inputs:
        if src is None:
            continue
        s = Path(src).resolve()
        if s == target or target in s.parents:
            out.append(str(src))
    return out


def check_out_dir(path, force: bool = False, inputs: tuple = ()) -> Path:
    """Refuse an existing, non-empty output directory (unless ``force``, and then only one that
    torchcal wrote, see :func:`written_by_torchcal`), one that holds an input of the run, the
    working directory, or a file in its place; check that it can be written. All before any work."""
    p = Path(path)
    _refuse_cwd(p)
    if p.exists() and not p.is_dir():
        raise FileExistsError(f"{p} exists and is a file, not a directory; choose another output directory")
    held = _holds_input(p, inputs)
    if held:
        raise FileExistsError(f"{p} holds {held[0]}, an input of this run; torchcal never writes its results over "
                              "its inputs (not even when forced): choose another output directory")
    if p.is_dir() and any(p.iterdir()):
        if not force:
            raise FileExistsError(f"{p} exists and is not empty; torchcal does not overwrite results: choose another "
                                  f"output directory, or {advice('pass force=True', 'pass --force')} to replace an "
                                  "earlier torchcal result")
        if not written_by_torchcal(p):
            theirs = sorted(x.name for x in p.iterdir())[:3]
            raise FileExistsError(f"{p} was not written by torchcal (it holds {theirs}, and no provenance.json), so "
                                  f"{advice('force=True', '--force')} does not replace it: choose another output "
                                  "directory, or empty it yourself")
    _writable_parent(p)
    return p


def check_out_file(path, force: bool = False, inputs: tuple = ()) -> Path:
    """Refuse an existing output file (unless ``force``) and one that is also an input (which
    would be destroyed while it is read; not even with ``force``), and check that it can be
    written."""
    p = Path(path)
    for src in inputs:
        if src is not None and Path(src).exists() and p.exists() and p.resolve() == Path(src).resolve():
            raise FileExistsError(f"{p} is also an input; writing it would destroy the input (torchcal never writes "
                                  "over its inputs, not even when forced): choose another output path")
    if p.is_dir():
        raise IsADirectoryError(f"{p} is a directory; give a file path")
    if p.exists() and not force:
        raise FileExistsError(f"{p} exists; torchcal does not overwrite it: choose another path, or pass "
                              f"{advice('force=True', '--force')}")
    _writable_parent(p)
    return p


def _alive(pid: int) -> bool:
    try:
        os.kill(pid, 0)
    except ProcessLookupError:
        return False
    except PermissionError:
        return True
    return True


@contextmanager
def claim(path) -> Iterator[Path]:
    """Hold ``path`` (a file or directory to be written) for this run: a lock file beside it,
    created atomically, removed when the block ends. A second run that claims the same path while
    the first holds it gets :class:`OutputBusy`; a lock left by a run that no longer exists
    (killed) is taken over."""
    p = Path(path).resolve()
    _writable_parent(p)
    # beside the output, or in the nearest existing folder above it (named for the path below)
    home = _existing_ancestor(p)
    lock = home / f".{str(p.relative_to(home)).replace(os.sep, '%')}.torchcal-lock"
    for _ in range(3):
        try:
            fd = os.open(lock, os.O_CREAT | os.O_EXCL | os.O_WRONLY, 0o644)
        except FileExistsError:
            try:
                pid = int(lock.read_text().split()[0])
            except (OSError, ValueError, IndexError):
                pid = None  # being written this instant: a live claim
            if pid is not None and not _alive(pid):
                lock.unlink(missing_ok=True)
                continue
            raise OutputBusy(f"another torchcal run{'' if pid is None else f' (process {pid})'} is writing {path}; "
                             f"wait for it to finish, or choose another output (if no run is left, delete {lock})"
                             ) from None
        try:
            os.write(fd, f"{os.getpid()}\n".encode())
        except OSError:
            lock.unlink(missing_ok=True)  # a full disk: no claim, and no empty lock left behind
            raise
        finally:
            os.close(fd)
        break
    else:
        raise OutputBusy(f"could not claim {path}: {lock} keeps coming back; delete it if no torchcal run is left")
    try:
        yield p
    finally:
        lock.unlink(missing_ok=True)


@contextmanager
def staged_dir(path, force: bool = False) -> Iterator[Path]:
    """Yield a temporary directory beside ``path``; when the block ends without error it takes
    ``path``'s place (an existing one only with ``force``, see :func:`check_out_dir`), otherwise
    it is removed. A result that carries neither ``provenance.json`` nor ``model.json`` gets a
    ``provenance.json``, by which a later ``force`` knows torchcal wrote it."""
    p = check_out_dir(path, force).resolve()
    p.parent.mkdir(parents=True, exist_ok=True)
    tmp = Path(tempfile.mkdtemp(prefix=f".{p.name}.", suffix=".partial", dir=p.parent))
    try:
        yield tmp
        if not any((tmp / n).exists() for n in _SIGNATURES):
            atomic_write_text(tmp / "provenance.json", json.dumps(provenance(), indent=2) + "\n")
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
    p.parent.mkdir(parents=True, exist_ok=True)
    fd, tmp = tempfile.mkstemp(prefix=f".{p.name}.", suffix=".partial", dir=p.parent if str(p.parent) else ".")
    try:
        with os.fdopen(fd, "wb") as fh:
            fh.write(data)
        os.replace(tmp, p)
    except BaseException as e:
        if os.path.exists(tmp):
            os.unlink(tmp)
        if isinstance(e, OSError) and e.filename is None and e.errno is not None:
            raise OSError(e.errno, e.strerror, str(p)) from None  # say which file could not be written
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
