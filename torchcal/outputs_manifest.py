"""What torchcal wrote in a result folder, so that replacing it never takes what the user put there.

Every result folder gets a manifest (``.torchcal-manifest.json``): the torchcal version and the
relative path of every file the run wrote. ``--force`` (or a run that finishes while someone made
the folder) replaces only those files: anything else in the folder, a ``notes.txt`` the user
added, a plot they saved, is carried over into the new result, and the run says what it kept.

Permissions follow the user's umask, as every other tool's files do: temporary files and folders
are made private by the standard library (0600 / 0700), and get the umask's modes when they
become the result, so that another account (a ROS launch user) can read a calibration.
"""
from __future__ import annotations

import json
import logging
import os
import shutil
from pathlib import Path

from torchcal.version import __version__

__all__ = ["MANIFEST", "write_manifest", "read_manifest", "all_files", "swap_in", "umask", "public_modes"]

MANIFEST = ".torchcal-manifest.json"
logger = logging.getLogger("torchcal")


def umask() -> int:
    """The process's umask, read without changing it where the system says it (Linux)."""
    try:
        for line in Path("/proc/self/status").read_text().splitlines():
            if line.startswith("Umask:"):
                return int(line.split()[1], 8)
    except (OSError, ValueError, IndexError):
        pass
    old = os.umask(0o022)
    os.umask(old)
    return old


def public_modes(root: Path) -> None:
    """Give ``root`` (a folder or a file) and everything below it the modes that the umask gives a
    new file (0666 & ~umask) or folder (0777 & ~umask)."""
    mask = umask()
    fmode, dmode = 0o666 & ~mask, 0o777 & ~mask
    if root.is_file():
        os.chmod(root, fmode)
        return
    for here, dirs, files in os.walk(root):
        os.chmod(here, dmode)
        for f in files:
            q = Path(here) / f
            if not q.is_symlink():
                os.chmod(q, fmode)


def _files(root: Path) -> list[str]:
    return sorted(str(Path(h, f).relative_to(root)) for h, _, fs in os.walk(root) for f in fs if f != MANIFEST)


def write_manifest(root: Path) -> None:
    """Record every file under ``root`` as written by this torchcal run."""
    rec = {"torchcal": __version__, "files": _files(root)}
    (root / MANIFEST).write_text(json.dumps(rec, indent=1) + "\n")


def all_files(root: Path) -> set[str]:
    """Every file under ``root``: what a torchcal result written before manifests counts as its own."""
    return set(_files(root))


def read_manifest(root: Path) -> set[str] | None:
    """The files a torchcal run recorded in ``root``, or None when it holds no readable manifest."""
    try:
        rec = json.loads((root / MANIFEST).read_text())
    except (OSError, ValueError):
        return None
    if not isinstance(rec, dict) or not isinstance(rec.get("files"), list):
        return None
    return {str(f) for f in rec["files"] if isinstance(f, str)}


def _theirs(old: Path, ours: set[str] | None) -> list[str]:
    """The entries of ``old`` that torchcal did not write (top-level names, or paths inside a
    folder torchcal wrote): with no manifest (a folder someone made during the run), all of them."""
    if ours is None:
        return sorted(x.name for x in old.iterdir())
    dirs = {str(Path(f).parent) for f in ours} | {str(p) for f in ours for p in Path(f).parents}
    out = []
    for here, subdirs, files in os.walk(old):
        rel = Path(here).relative_to(old)
        for name in files + [d for d in subdirs if str(rel / d) not in dirs]:
            r = str(rel / name)
            if name != MANIFEST and r not in ours:
                out.append(r)
        subdirs[:] = [d for d in subdirs if str(rel / d) in dirs]
    return sorted(out)


def swap_in(tmp: Path, p: Path, ours: set[str] | None) -> list[str]:
    """Put the finished result ``tmp`` at ``p``. An existing ``p`` is set aside; what in it torchcal
    did not write (see :func:`_theirs`; ``ours`` its manifest) is moved into the new result (a name
    the new result also has is kept as ``NAME.yours``); the rest is removed. Returns what was kept."""
    if not p.exists():
        os.rename(tmp, p)
        return []
    old = p.with_name(f".{p.name}.replaced-{os.getpid()}")
    os.rename(p, old)
    kept = []
    for rel in _theirs(old, ours):
        dst = tmp / rel
        if dst.exists() or dst.is_symlink():
            dst = dst.with_name(dst.name + ".yours")
        dst.parent.mkdir(parents=True, exist_ok=True)
        os.rename(old / rel, dst)
        kept.append(str(dst.relative_to(tmp)))
    os.rename(tmp, p)
    shutil.rmtree(old, ignore_errors=True)
    if kept:
        logger.warning(f"torchcal: {p} held files torchcal did not write; they were kept in the new result: "
                       f"{', '.join(kept[:10])}{' …' if len(kept) > 10 else ''}")
    return kept
