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
  refused while the first holds it; a stale lock and the leftovers of a killed run are removed, and
  the run says so (:mod:`torchcal.outputs_lock`).
* ``force`` replaces only the files torchcal listed in the folder's manifest; files the user added
  are kept in the new result (:mod:`torchcal.outputs_manifest`). Only regular files and folders are
  ever replaced: a FIFO, a device node, a socket or a symbolic link in the output's place is refused.
* Results get the modes of the user's umask, as any other tool's files.
"""
from __future__ import annotations

import datetime as _dt
import errno
import hashlib
import json
import os
import platform
import shutil
import stat
import sys
import tempfile
from contextlib import contextmanager
from pathlib import Path
from typing import Iterator

import torch

from torchcal.advice import advice
from torchcal.outputs_lock import OutputBusy, clean_leftovers
from torchcal.outputs_lock import claim as _claim
from torchcal.outputs_manifest import all_files, public_modes, read_manifest, swap_in, umask, write_manifest
from torchcal.version import __version__

__all__ = ["check_out_dir", "check_out_file", "staged_dir", "atomic_write_text", "atomic_write_bytes",
           "sha256_file", "provenance", "claim", "written_by_torchcal", "OutputBusy"]

# files by which a directory says torchcal wrote it: JSON objects that name the torchcal version
_SIGNATURES = ("provenance.json", "model.json")
_VERSION_KEYS = ("torchcal", "torchcal_version")


def _resolve(p: Path) -> Path:
    """``p`` resolved; a symbolic link that loops or leads nowhere, anywhere on the path, is refused."""
    try:
        return p.resolve(strict=False)
    except (RuntimeError, OSError) as e:
        raise NotADirectoryError(f"{p}: a symbolic link on this path loops ({e}); remove or fix the link, or give "
                                 "another output path") from None


def _refuse_special(p: Path, what: str = "output") -> None:
    """Refuse a ``p`` that is a symbolic link, or exists and is neither a regular file nor a folder:
    torchcal never replaces what it cannot have written (``--out /dev/null --force`` as root would
    replace the system's /dev/null)."""
    try:
        st = os.lstat(p)
    except OSError as e:
        if e.errno == errno.ELOOP:
            raise NotADirectoryError(f"{p}: a symbolic link on this path loops; remove or fix the link, or give "
                                     f"another {what} path") from None
        return  # missing, or a file where a folder should be: the checks after this one say which
    if stat.S_ISLNK(st.st_mode):
        try:
            target = os.readlink(p)
            os.stat(p)
        except OSError as e:
            why = "loops" if e.errno == errno.ELOOP else "leads to nothing"
            raise NotADirectoryError(f"{p} is a symbolic link that {why} ({e.strerror}); remove or fix the link, or "
                                     f"give another {what} path") from None
        raise FileExistsError(f"{p} is a symbolic link (to {target}); torchcal does not write through or over links: "
                              f"give the real path ({_resolve(p)}) or another {what} path")
    if not (stat.S_ISREG(st.st_mode) or stat.S_ISDIR(st.st_mode)):
        kind = ("a FIFO" if stat.S_ISFIFO(st.st_mode) else "a device node" if stat.S_ISCHR(st.st_mode)
                or stat.S_ISBLK(st.st_mode) else "a socket" if stat.S_ISSOCK(st.st_mode) else "not a regular file")
        raise FileExistsError(f"{p} is {kind}, not a regular file or folder; torchcal never writes over it (not even "
                              f"when forced): give another {what} path")


def _existing_ancestor(p: Path) -> Path:
    """The nearest folder above ``p`` that exists (its parent, unless folders are still to make)."""
    a = _resolve(p).parent
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
    """Whether ``folder`` is a directory torchcal wrote: it holds torchcal's manifest, or (written
    before manifests) a ``provenance.json`` or a ``model.json`` that names the torchcal version."""
    if read_manifest(Path(folder)) is not None:
        return True
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
    here, target = Path.cwd().resolve(), _resolve(p)
    if target == here or target in here.parents:
        raise IsADirectoryError(f"{p} is the current directory{'' if target == here else ' or above it'}; give a new "
                                f"folder for the results, e.g. {advice(repr('cell1'), '--out cell1')}")


def _holds_input(p: Path, inputs) -> list[str]:
    """The inputs that lie in (or are) ``p``."""
    target = _resolve(p)
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
    _refuse_special(p, "output directory")
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
    _refuse_special(p, "output file")
    for src in inputs:
        if src is not None and Path(src).exists() and p.exists() and _resolve(p) == _resolve(Path(src)):
            raise FileExistsError(f"{p} is also an input; writing it would destroy the input (torchcal never writes "
                                  "over its inputs, not even when forced): choose another output path")
    if p.is_dir():
        raise IsADirectoryError(f"{p} is a directory; give a file path")
    if p.exists() and not force:
        raise FileExistsError(f"{p} exists; torchcal does not overwrite it: choose another path, or pass "
                              f"{advice('force=True', '--force')}")
    _writable_parent(p)
    clean_leftovers(_resolve(p))
    return p


@contextmanager
def claim(path) -> Iterator[Path]:
    """Hold ``path`` (a file or directory to be written) for this run: a lock file beside it,
    created atomically, removed when the block ends. A second run that claims the same path while
    the first holds it gets :class:`OutputBusy`; a stale lock (its run gone) is taken over, and what
    a killed run left beside the output is removed, both said (:mod:`torchcal.outputs_lock`)."""
    p = _resolve(Path(path))
    _refuse_special(Path(path))
    _writable_parent(p)
    with _claim(p, _existing_ancestor(p)) as held:
        clean_leftovers(p)
        yield held


@contextmanager
def staged_dir(path, force: bool = False) -> Iterator[Path]:
    """Yield a temporary directory beside ``path``; when the block ends without error it takes
    ``path``'s place (an existing one only with ``force``, see :func:`check_out_dir`), otherwise
    it is removed. The result gets a manifest of its files (what a later ``force`` may replace),
    a ``provenance.json`` unless it holds a ``model.json`` or one already, and the umask's modes.
    Files in ``path`` that torchcal did not write (added before a ``force``, or while the run
    worked) are carried into the new result, and said."""
    p = _resolve(check_out_dir(path, force))
    clean_leftovers(p)
    p.parent.mkdir(parents=True, exist_ok=True)
    tmp = Path(tempfile.mkdtemp(prefix=f".{p.name}.", suffix=f".{os.getpid()}.partial", dir=p.parent))
    try:
        yield tmp
        if not any((tmp / n).exists() for n in _SIGNATURES):
            atomic_write_text(tmp / "provenance.json", json.dumps(provenance(), indent=2) + "\n")
        write_manifest(tmp)
        public_modes(tmp)
        _refuse_special(p, "output directory")  # made while the run worked: still never replaced
        if p.exists() and not p.is_dir():
            raise FileExistsError(f"{p} became a file while the run worked; the result was not written: choose "
                                  "another output directory")
        swap_in(tmp, p, _owned(p))
    except BaseException:
        shutil.rmtree(tmp, ignore_errors=True)
        raise


def _owned(p: Path) -> set[str] | None:
    """The files of ``p`` torchcal wrote: its manifest; everything, for a torchcal result written
    before manifests; None (nothing) for a folder someone else made."""
    if not p.exists():
        return None
    ours = read_manifest(p)
    if ours is None and written_by_torchcal(p):
        ours = all_files(p)
    return ours


def atomic_write_bytes(path, data: bytes) -> None:
    """Write ``data`` to ``path`` through a temporary file in the same directory and a rename; the
    file gets the umask's modes, as a plain ``open`` would give it."""
    p = Path(path)
    p.parent.mkdir(parents=True, exist_ok=True)
    fd, tmp = tempfile.mkstemp(prefix=f".{p.name}.", suffix=f".{os.getpid()}.partial",
                               dir=p.parent if str(p.parent) else ".")
    try:
        os.fchmod(fd, 0o666 & ~umask())
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
