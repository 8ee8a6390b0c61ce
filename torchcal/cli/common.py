"""What every ``torchcal`` command shares: option checks at parse time, ``--config`` files,
logging, the record each output directory keeps (``run.yaml``, ``provenance.json``), and the
robot and data an integrator points the commands at."""
from __future__ import annotations

import argparse
import dis
import errno
import glob
import json
import logging
import math
import os
import re
import sys
import traceback
import warnings
from pathlib import Path

import yaml

from torchcal.cli.strict import UniqueKeyLoader
from torchcal.kinematics.robot import Robot
from torchcal.kinematics.tree import Marker, parse_marker
from torchcal.kinematics.urdf import urdf_links
from torchcal.measure.columns import marker_columns_in
from torchcal.cli.formats import format_of
from torchcal.measure.io import UNITS, load_measurements, read_table
from torchcal.outputs import atomic_write_text, provenance

__all__ = ["int_at_least", "positive_float", "nonnegative_float", "fraction", "probability", "add_common", "expand_config",
           "setup_logging", "run_record", "robot_and_data", "robot_for", "parse_markers", "PATH_OPTIONS",
           "is_refusal", "report_failure", "join_negative_values", "EXIT_REFUSED", "EXIT_BUG", "inputs_of"]

logger = logging.getLogger("torchcal")

# options holding paths: relative ones in a --config file are read from the file's folder
PATH_OPTIONS = ("robot", "data", "test", "out", "model", "targets")
_MAX_MARKER_GUESS_M = 2.0  # a marker point further than 2 m from its link is a guess in millimetres


# ------------------------------------------------------------------ refusals and bugs
# A command ends in one of three ways: it works (exit 0, or 3 when `correct` has failed targets),
# it refuses (exit 2), or it meets a bug (exit 70, EX_SOFTWARE of sysexits.h).
#
# A refusal is deliberate: torchcal checked the options, the input or the place it writes to, and
# says what is wrong and how to fix it. argparse refuses bad options. torchcal refuses by raising
# ValueError (or its subclasses UnitsError, WorkspaceError, NoSuchParameter) or ImportError (an
# optional extra is missing) from a `raise` statement in its own code, the package's convention
# for input checked at the door, as in scikit-learn. The system refuses with OSError (a file
# missing or in the way, a folder not writable, a full disk), whoever raised it.
#
# Any other exception is a bug: KeyError, IndexError, TypeError, RuntimeError, AttributeError…,
# a ValueError that torch, numpy or the standard library raised inside torchcal's work (a shape
# torchcal built wrongly), and one that a call such as float() raised in torchcal's code without
# a check before it. A name the user gave that names nothing raises NoSuchParameter, a KeyError
# that is also a ValueError; any other KeyError is a lookup torchcal got wrong. A bug's message
# names the exception and asks for a report; --verbose prints its traceback.
EXIT_REFUSED, EXIT_BUG = 2, 70
# what to do about an error of the file system, by its errno (the true cause, not always the disk)
_FIXES = {errno.ENOSPC: "free some space or choose another --out", errno.EDQUOT: "free some of your quota or choose "
          "another --out", errno.ENAMETOOLONG: "choose a shorter --out", errno.EROFS: "the file system is read-only: "
          "choose another --out", errno.ELOOP: "a symbolic link on the path loops: fix it or choose another --out"}
_REFUSED_BY_TORCHCAL = (ValueError, ImportError)


def _raised_by_torchcal(e: BaseException) -> bool:
    """Whether ``e`` left a ``raise`` statement in a torchcal module (its innermost frame)."""
    tb = e.__traceback__
    if tb is None:
        return False
    while tb.tb_next is not None:
        tb = tb.tb_next
    if not str(tb.tb_frame.f_globals.get("__name__", "")).startswith("torchcal"):
        return False
    ops = {i.offset: i.opname for i in dis.get_instructions(tb.tb_frame.f_code)}
    op = ops.get(tb.tb_lasti) or ops.get(2 * tb.tb_lasti)  # a byte offset, or (Python 3.10) a code unit
    return op in ("RAISE_VARARGS", "RERAISE")


def is_refusal(e: BaseException) -> bool:
    """Whether ``e`` is a deliberate refusal (exit 2) rather than a bug (exit 70); see above."""
    return isinstance(e, OSError) or (isinstance(e, _REFUSED_BY_TORCHCAL) and _raised_by_torchcal(e))


def report_failure(cmd: str, e: Exception, verbose: bool, out=None) -> int:
    """Print a refusal or a bug to stderr as the exit status says; return that status. An error of
    the file system (a full disk, a drive gone) names the file and says nothing was written."""
    if isinstance(e, OSError) and not isinstance(e, (FileNotFoundError, FileExistsError, IsADirectoryError,
                                                     NotADirectoryError, PermissionError)):
        name = str(e.filename or out)
        name = name if len(name) <= 200 else name[:200] + "…"  # never a whole file's text
        fix = _FIXES.get(e.errno, "choose another --out")
        print(f"torchcal {cmd}: error: could not write {name}: {e.strerror or e}; {fix}, and run again (nothing was "
              "written)", file=sys.stderr)
        return EXIT_REFUSED
    if isinstance(e, MemoryError) or (isinstance(e, RuntimeError) and "can't allocate memory" in str(e)):
        print(f"torchcal {cmd}: error: ran out of memory ({str(e)[:120] or 'MemoryError'}); use fewer rows, or run "
              "where there is more memory (nothing was written)", file=sys.stderr)
        return EXIT_REFUSED
    if is_refusal(e):
        msg = e.args[0] if isinstance(e, KeyError) and e.args else e
        print(f"torchcal {cmd}: error: {msg}", file=sys.stderr)
        return EXIT_REFUSED
    if verbose:
        traceback.print_exception(e, file=sys.stderr)
    print(f"torchcal {cmd}: internal error (a bug): {type(e).__name__}: {e}. "
          + ("The traceback is above; please report it with the command line"
             if verbose else "Rerun with --verbose for the traceback and report it"), file=sys.stderr)
    return EXIT_BUG


# a value that starts with a minus and a digit: a negative number or a list such as -1.2,1.2
_NEGATIVE = re.compile(r"-\.?\d")


def join_negative_values(argv: list[str], sub: dict[str, argparse.ArgumentParser]) -> list[str]:
    """``argv`` with ``--opt -1.2,1.2,…`` written ``--opt=-1.2,1.2,…`` for options that take one
    value: argparse reads a leading minus as the next option unless the value is a plain number."""
    if not argv or argv[0] not in sub:
        return argv
    takes_one = {o for a in sub[argv[0]]._actions if a.nargs is None and a.option_strings for o in a.option_strings}
    out = argv[:1]
    i = 1
    while i < len(argv):
        tok = argv[i]
        if tok in takes_one and i + 1 < len(argv) and _NEGATIVE.match(argv[i + 1]):
            out.append(f"{tok}={argv[i + 1]}")
            i += 2
        else:
            out.append(tok)
            i += 1
    return out


def int_at_least(lo: int):
    def check(text: str) -> int:
        try:
            v = int(text)
        except ValueError:
            raise argparse.ArgumentTypeError(f"{text!r} is not a whole number") from None
        if v < lo:
            raise argparse.ArgumentTypeError(f"must be at least {lo}, got {v}")
        return v
    return check


def _float(text: str, ok, what: str) -> float:
    try:
        v = float(text)
    except ValueError:
        raise argparse.ArgumentTypeError(f"{text!r} is not a number") from None
    if not math.isfinite(v):
        raise argparse.ArgumentTypeError(f"must be a finite number, got {text!r}")
    if not ok(v):
        raise argparse.ArgumentTypeError(f"must be {what}, got {v}")
    return v


def positive_float(text: str) -> float:
    return _float(text, lambda v: v > 0, "positive")


def nonnegative_float(text: str) -> float:
    return _float(text, lambda v: v >= 0, "zero or positive")


def fraction(text: str) -> float:
    return _float(text, lambda v: 0 <= v < 1, "a fraction in [0, 1)")


def probability(text: str) -> float:
    return _float(text, lambda v: 0 < v < 1, "a probability in (0, 1)")


def add_common(p: argparse.ArgumentParser, units: bool = True) -> None:
    """Options every command takes."""
    p.add_argument("--config", help="YAML file of options (keys as the long options, e.g. 'noise-mm: 0.02'); "
                                    "options given on the command line win; relative paths are read from the "
                                    "file's folder")
    p.add_argument("--force", action="store_true", help="replace an existing output (refused otherwise)")
    p.add_argument("--threads", type=int_at_least(1), default=1, help="torch threads (≥ 1)")
    g = p.add_mutually_exclusive_group()
    g.add_argument("--quiet", action="store_true", help="warnings and errors only")
    g.add_argument("--verbose", action="store_true", help="debug messages too")
    if units:
        p.add_argument("--units", action="append", choices=UNITS, default=[],
                       help="declare units of the data and marker guesses: 'deg' for joint angles, 'mm' for "
                            "positions and prismatic joints (repeatable); converted on reading. Without it, "
                            "values that look like degrees or millimetres stop the run")


def expand_config(argv: list[str], sub: dict[str, argparse.ArgumentParser]) -> list[str]:
    """``argv`` with the options of a ``--config`` YAML file put before the command line's own
    (so that those win; repeatable options add up)."""
    if not argv or argv[0] not in sub:
        return argv
    cfg = None
    for i, tok in enumerate(argv):
        if tok == "--config" and i + 1 < len(argv):
            cfg = argv[i + 1]
        elif tok.startswith("--config="):
            cfg = tok.split("=", 1)[1]
    if cfg is None:
        return argv
    path = Path(cfg)
    _need_new_out(argv, path)
    if not path.is_file():
        raise SystemExit(f"torchcal {argv[0]}: error: config file not found: {path}")
    try:
        data = yaml.load(path.read_bytes().decode("utf-8-sig"), Loader=UniqueKeyLoader) or {}
    except UnicodeDecodeError as e:
        raise SystemExit(f"torchcal {argv[0]}: error: {path} is not UTF-8 text ({e.reason} at byte {e.start}); save "
                         "it as UTF-8") from None
    except yaml.YAMLError as e:
        raise SystemExit(f"torchcal {argv[0]}: error: {path} is not valid YAML: {e}") from None
    if not isinstance(data, dict):
        raise SystemExit(f"torchcal {argv[0]}: error: {path} must hold a mapping of option: value")
    # the options a user may set: hidden ones (help=SUPPRESS) are the command's own business
    actions = {a.dest: a for a in sub[argv[0]]._actions
               if a.option_strings and a.help != argparse.SUPPRESS and a.dest not in ("help", "config")}
    tokens: list[str] = []
    for key, value in data.items():
        dest = str(key).replace("-", "_")
        a = actions.get(dest)
        where = f"torchcal {argv[0]}: error: {path}: option {key!r}"
        old = next((x.renamed for x in sub[argv[0]]._actions if f"--{key}" in x.option_strings
                    and hasattr(x, "renamed")), None)
        if old is not None:
            raise SystemExit(f"{where}: {old}")
        if a is None:
            known = sorted(k.replace("_", "-") for k in actions)
            raise SystemExit(f"torchcal {argv[0]}: error: {path}: unknown option {key!r}; options are {known}")
        flag = a.option_strings[-1] if a.option_strings[-1].startswith("--") else a.option_strings[0]
        switch = isinstance(a, (argparse._StoreTrueAction, argparse.BooleanOptionalAction))
        if switch and not (isinstance(value, bool) or value is None):
            # a quoted "false" is text, and text is true: never guess what a switch was meant to be
            raise SystemExit(f"{where} must be true or false (a YAML boolean, without quotes), got {value!r}")
        if isinstance(value, (dict, set)):
            raise SystemExit(f"{where} must be a value or a list of values, got a mapping")
        if isinstance(value, list) and not (a.nargs in ("*", "+") or isinstance(a, argparse._AppendAction)):
            raise SystemExit(f"{where} takes one value, got a list {value}")
        if dest in PATH_OPTIONS and value is not None:
            value = str((path.parent / str(value)).resolve()) if not Path(str(value)).is_absolute() else str(value)
        if isinstance(a, argparse._StoreTrueAction):
            if value:
                tokens.append(flag)
        elif isinstance(a, argparse.BooleanOptionalAction):
            if value is not None:
                tokens.append(flag if value else flag.replace("--", "--no-", 1))
        elif isinstance(value, list):
            if a.nargs in ("*", "+"):
                tokens += [flag] + [str(v) for v in value]
            else:
                for v in value:
                    tokens += [flag, str(v)]
        elif value is not None:
            tokens += [flag, str(value)]
    return [argv[0]] + tokens + argv[1:]


def inputs_of(a: argparse.Namespace) -> list[str]:
    """The files a command reads (its ``--config``, URDF, data, held-out data, model, targets;
    a fleet's directories and globs expanded): outputs never go over them."""
    out = [getattr(a, "config", None)]
    for k in PATH_OPTIONS:
        v = getattr(a, k, None)
        if k == "out" or v is None:
            continue
        out += sorted(glob.glob(str(v))) if glob.has_magic(str(v)) else [v]
    return [str(x) for x in out if x is not None]


class _Stderr(logging.StreamHandler):
    """Writes to whatever ``sys.stderr`` is when a message comes (a notebook, a test harness or
    a caller may have replaced it since the handler was made), like logging's last resort."""

    def __init__(self):
        super().__init__(sys.stderr)

    @property
    def stream(self):
        return sys.stderr

    @stream.setter
    def stream(self, value) -> None:
        pass


def setup_logging(a: argparse.Namespace) -> None:
    """``torchcal`` messages to stderr: warnings only with ``--quiet``, debug with ``--verbose``.
    Python warnings go the same way, as one line each, once per run (no source line)."""
    level = logging.WARNING if getattr(a, "quiet", False) else logging.DEBUG if getattr(a, "verbose", False) \
        else logging.INFO
    logger.setLevel(level)
    if not any(getattr(h, "_torchcal", False) for h in logger.handlers):
        h = _Stderr()
        h.setFormatter(logging.Formatter("%(message)s"))
        h._torchcal = True
        logger.addHandler(h)
        logger.propagate = False
    shown: set[str] = set()

    def show(message, category, filename, lineno, file=None, line=None) -> None:
        text = str(message)
        key = re.sub(r"\d+(\.\d+)?(e[-+]?\d+)?", "#", text)  # the same warning with other numbers is the same
        if key not in shown:
            shown.add(key)
            logger.warning(f"torchcal {getattr(a, 'cmd', '')}: warning: {text}")
    warnings.showwarning = show


def _need_new_out(argv: list[str], path: Path) -> None:
    """A ``run.yaml`` that a run wrote (its folder holds ``provenance.json``) repeats that run,
    whose output is its own folder: without a new ``--out`` say so, in one line."""
    if (path.parent / "provenance.json").is_file() and not any(t == "--out" or t.startswith("--out=") for t in argv):
        raise SystemExit(f"torchcal {argv[0]}: error: {path} repeats the run that wrote {path.parent}; give the repeat "
                         f"its own output: --out {path.parent.name}-repeat (or another new path)")


def run_record(a: argparse.Namespace, out: Path, files: dict, argv: list[str]) -> dict:
    """Write ``run.yaml`` (the exact options, paths relative to the output folder it lies in, no
    ``out``: ``--config OUT/run.yaml --out NEW`` repeats the run into NEW) and
    ``provenance.json`` into ``out``; return the provenance."""
    skip = {"func", "config", "cmd", "command", "force", "out"}
    home = Path(a.out).resolve() if getattr(a, "out", None) else Path(out).resolve()
    opts = {}
    for k, v in sorted(vars(a).items()):
        if k in skip or k.startswith("_") or v is None or v == [] or v is False:
            continue
        if k in PATH_OPTIONS:
            v = os.path.relpath(Path(v).resolve(), home)
        opts[k.replace("_", "-")] = v
    prov = provenance(files, ["torchcal", *argv])
    atomic_write_text(out / "run.yaml", f"# torchcal {a.cmd}: the exact options of this run, paths relative to this "
                      f"folder; `torchcal {a.cmd} --config {Path(a.out).name}/run.yaml --out NEW` repeats it into "
                      "NEW\n" + yaml.safe_dump(opts, sort_keys=True))

    atomic_write_text(out / "provenance.json", json.dumps(prov, indent=2) + "\n")
    return prov


def parse_markers(specs: list[str], units: list[str] | None) -> list[Marker]:
    """Declared markers, their guesses (m) converted from millimetres when declared, refused when
    they look like millimetres otherwise. ``units``: the command's ``--units``, or None for a
    command without that option (the refusal then asks for metres only)."""
    out = []
    for spec in specs:
        m = parse_marker(spec)
        xyz = tuple(v / 1000.0 for v in m.xyz) if units and "mm" in units else m.xyz
        far = max(abs(v) for v in xyz)
        if far > _MAX_MARKER_GUESS_M:
            raise ValueError(f"marker {spec!r}: a guess {far:.3g} m from its link looks like millimetres; give metres "
                             f"(e.g. {m.name}@{m.link}={','.join(f'{v / 1000:g}' for v in m.xyz)})"
                             + (" or declare --units mm" if units is not None else ""))
        out.append(Marker(m.name, m.link, xyz, m.rpy))
    return out


def robot_for(urdf, markers: list[str] | None, data_path, units: list[str], fmt=None) -> Robot:
    """The robot with its markers: those declared, or else the marker columns of the CSV
    ``data_path`` (an instrument's export written as ``fmt`` says) that are links of the URDF."""
    if not markers:
        header, _ = read_table(data_path, fmt)
        cols = marker_columns_in(header)
        links = set(urdf_links(urdf))
        unknown = [c for c in cols if c not in links]
        if unknown:
            raise ValueError(f"marker column(s) {unknown} are not links of {urdf}; declare each as an unknown point "
                             f"on a link, e.g. --marker {unknown[0]}@LINK or --marker {unknown[0]}@LINK=0.05,0,0.1 (m)")
        if not cols:
            raise ValueError(f"{data_path} has no '<marker>.x/.y/.z' columns")
        markers = cols
    return Robot.from_urdf(urdf, markers=parse_markers(markers, units))


def robot_and_data(a: argparse.Namespace):
    """The robot (markers declared, or the data's marker columns that are links) and the
    training and held-out measurements, in metres and radians."""
    units, fmt = list(getattr(a, "units", []) or []), format_of(a)
    robot = robot_for(a.robot, a.marker, a.data, units, fmt)
    train = load_measurements(a.data, robot, units=units, fmt=fmt)
    test = load_measurements(a.test, robot, units=units, fmt=fmt) if a.test else None
    if test is None and getattr(a, "holdout", 0):
        train, test = train.split(a.holdout, seed=a.seed)
    return robot, train, test
