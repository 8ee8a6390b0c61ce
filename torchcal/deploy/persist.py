"""Saving and loading :class:`~torchcal.deploy.model.CalibratedModel` directories.

A model directory holds three files (and the manifest by which a later ``force`` knows what torchcal wrote):

* ``model.json``: metadata: format name and version, torchcal version, the robot (name, SHA-256
  of its URDF text, joint and marker names, markers, dtype), parameter names and units, the
  residual ELM's configuration, effects (type, name, non-tensor state), covariate names, units
  and conventions, and the free ``meta`` (training data summary, metrics);
* ``tensors.safetensors``: every tensor (parameter values, bounds and free flags, ELM weights
  and scaling, effect tensors), stored bit-exactly;
* ``robot.urdf``: the URDF text the robot was built from, so :func:`load` can rebuild the robot
  without the original file.

Loading for a robot whose URDF hash, joints or markers differ from the saved ones is refused:
a model corrects one robot description, not another. ``model.json`` records the SHA-256 of the
tensor file, and a model whose tensors changed (a flipped byte changes every command it gives)
is refused too; a truncated or malformed file is named in the error. ``model.json`` itself carries
a checksum of its content (which holds those of the tensors and the URDF), so an edited marker
point is refused as well; its fields are checked one by one (:mod:`torchcal.deploy.model_schema`).
A robot passed to :func:`load` must match the saved one by its URDF and its markers' links and
points, not only their names.

:func:`save` never replaces an existing model directory unless ``force=True``, and builds the
directory under a temporary name: an interrupted save leaves nothing half-written.
"""
from __future__ import annotations

import hashlib
import json
import os
import warnings
from pathlib import Path

import torch
from safetensors import SafetensorError
from safetensors.torch import load_file, save_file
from torch import Tensor

from torchcal.advice import advice
from torchcal.elm import ELM
from torchcal.deploy.model import ERROR_NAMES, CalibratedModel
from torchcal.deploy.model_schema import CHECKSUM_KEY, check_meta, content_sha256
from torchcal.effects.registry import effect_class, effect_type
from torchcal.kinematics.robot import Robot
from torchcal.kinematics.tree import Marker
from torchcal.outputs import sha256_file, staged_dir
from torchcal.params import ParamSet
from torchcal.version import __version__

__all__ = ["save", "load", "FORMAT", "FORMAT_VERSION"]

FORMAT = "torchcal-model"
FORMAT_VERSION = 1
_JSON, _TENSORS, _URDF = "model.json", "tensors.safetensors", "robot.urdf"


def _urdf_text(robot) -> str:
    text = robot.urdf_text
    if text is None:
        raise ValueError(f"robot {robot.name!r} was not built from a URDF, so it cannot be saved with the model; "
                         "build it with Robot.from_urdf(...) or torchcal.kinematics.robots.shipped(name) (source='urdf')")
    return text


def _marker_record(mk) -> dict:
    return {"name": mk.name, "link": mk.link, "xyz": [float(v) for v in mk.xyz], "rpy": [float(v) for v in mk.rpy]}


def _json_safe(obj, where: str):
    try:
        json.dumps(obj, allow_nan=False)
    except (TypeError, ValueError) as e:
        raise ValueError(f"{where} must be JSON-serialisable (numbers, strings, lists, dicts; no NaN): {e}") from None
    return obj


def _dumps(obj, indent: int = 0) -> str:
    """JSON with one key per line but lists of plain values on one line (readable diffs)."""
    pad, inner = " " * indent, " " * (indent + 1)
    if isinstance(obj, dict) and obj:
        items = [f"{inner}{json.dumps(str(k))}: {_dumps(v, indent + 1)}" for k, v in obj.items()]
        return "{\n" + ",\n".join(items) + "\n" + pad + "}"
    if isinstance(obj, (list, tuple)) and any(isinstance(v, (dict, list, tuple)) for v in obj):
        return "[\n" + ",\n".join(inner + _dumps(v, indent + 1) for v in obj) + "\n" + pad + "]"
    return json.dumps(obj, allow_nan=False)


def save(model: CalibratedModel, directory: str | os.PathLike, *, force: bool = False) -> Path:
    """Write ``model`` to ``directory``.

    Args:
        force: replace an existing, non-empty ``directory`` (refused otherwise).
    Returns:
        the directory path.
    """
    if not isinstance(model, CalibratedModel):
        raise TypeError(f"save() takes a CalibratedModel, got {type(model).__name__}")
    robot = model.robot
    text = _urdf_text(robot)
    with staged_dir(directory, force) as tmp:
        _write(model, robot, text, tmp)
    return Path(directory)


def _write(model: CalibratedModel, robot, text: str, out: Path) -> None:
    tensors: dict[str, Tensor] = {}
    p = model.params
    tensors["params.values"] = p.values
    tensors["params.lower"] = p.lower
    tensors["params.upper"] = p.upper
    tensors["params.free"] = p.free.to(torch.bool)
    residual = None
    if model.residual is not None:
        residual = model.residual.config()
        for k, v in model.residual.state_dict().items():
            tensors[f"residual.{k}"] = v
    effects = []
    for i, e in enumerate(model.effects):
        state = e.state_dict()
        plain = {}
        for k, v in state.items():
            if isinstance(v, Tensor):
                tensors[f"effects.{i}.{k}"] = v
            else:
                plain[k] = v
        key = effect_type(type(e))
        effect_class(key)  # refuse to save what could not be loaded again
        effects.append({"name": e.name, "type": key, "state": _json_safe(plain, f"effect {e.name!r} state")})
    n_out = 0 if model.residual is None else model.residual.n_outputs_

    meta = {
        "format": FORMAT, "format_version": FORMAT_VERSION, "torchcal_version": __version__,
        "robot": {"name": robot.name, "urdf_sha256": robot.urdf_hash(), "urdf_file": _URDF,
                  "joint_names": list(robot.joint_names), "joint_units": list(robot.joint_units),
                  "marker_names": list(robot.marker_names),
                  "markers": [_marker_record(mk) for mk in robot.markers],
                  "dof": robot.dof, "dtype": str(robot.dtype).replace("torch.", "")},
        "params": {"names": list(p.names), "units": list(p.units)},
        "marker": model.marker,
        "covariates": list(model.covariates),
        "residual": residual,
        "residual_outputs": list(ERROR_NAMES[:n_out]),
        "effects": effects,
        "units": {"q": "rad (m for prismatic joints), columns joint_names",
                  "position": "m, instrument frame (the frame of the calibrated base)",
                  "rotation": "rad",
                  "error": "[dx, dy, dz] m = p_meas - p_model (instrument frame); [droll, dpitch, dyaw] rad = "
                           "rotation vector log(R_model^T R_meas) (model frame)"},
        "meta": _json_safe(model.meta, "model.meta"),
    }
    contig = {k: v.detach().contiguous().cpu() for k, v in tensors.items()}
    save_file(contig, str(out / _TENSORS), metadata={"format": FORMAT, "format_version": str(FORMAT_VERSION)})
    meta["tensors_sha256"] = sha256_file(out / _TENSORS)
    meta[CHECKSUM_KEY] = content_sha256(json.loads(_dumps(meta)))  # of what a reader will parse back
    (out / _URDF).write_bytes(text.encode())
    (out / _JSON).write_text(_dumps(meta) + "\n")


def _nearby_model(d: Path) -> str:
    """Where a model directory is, for a path one level off: the folder of a ``model.json`` given
    as the path, or the sub-folders of ``d`` that hold one."""
    if d.name == _JSON and d.is_file():
        return f"; give the folder that holds it: {d.parent}"
    near = sorted(x for x in d.iterdir() if (x / _JSON).is_file())[:3] if d.is_dir() else []
    if near:
        return "; did you mean " + " or ".join(str(x) for x in near) + "?"
    if not d.exists():
        return f"; {d} does not exist"
    return "; " + advice("write one with torchcal.save", "give the model folder of a 'torchcal loop' result (OUT/model)")


def _read_meta(d: Path) -> dict:
    f = d / _JSON
    if not f.is_file():
        raise FileNotFoundError(f"{d} is not a torchcal model directory: {f.name} is missing "
                                f"(a model directory holds {_JSON}, {_TENSORS} and {_URDF}){_nearby_model(d)}")
    try:
        meta = json.loads(f.read_bytes().decode("utf-8-sig"))
    except (json.JSONDecodeError, UnicodeDecodeError, RecursionError) as e:
        raise ValueError(f"{f} is not valid JSON ({e}); the model file is truncated or was edited: save the "
                         "model again") from None
    check_meta(meta, f, FORMAT, FORMAT_VERSION)
    want = meta.get(CHECKSUM_KEY)
    if want is None:
        warnings.warn(f"{f} carries no checksum (saved by an earlier torchcal), so an edit of it cannot be detected; "
                      "save the model again to add one", stacklevel=3)
    elif want != content_sha256(meta):
        raise ValueError(f"{f} does not match its checksum ({CHECKSUM_KEY}): the model changed since it was saved "
                         "(an edit, a copy error), and a changed model gives wrong commands; restore the file or "
                         "save the model again")
    return meta


def _same_markers(robot, r: dict, tol: float = 1e-9) -> str | None:
    """What differs between the markers of ``robot`` and the saved ones (link, point, orientation), or None."""
    for mk, rec in zip(robot.markers, r["markers"]):
        if mk.link != rec["link"]:
            return f"marker {mk.name!r} is on link {mk.link!r}, the model's on {rec['link']!r}"
        for what, got, want, unit in (("point", mk.xyz, rec["xyz"], "m"), ("orientation", mk.rpy, rec["rpy"], "rad")):
            gap = max(abs(float(a) - float(b)) for a, b in zip(got, want))
            if gap > tol:
                return (f"marker {mk.name!r} has the {what} {[round(float(v), 6) for v in got]} {unit}, the model's "
                        f"{[round(float(v), 6) for v in want]} {unit}")
    return None


def _check_robot(robot, meta: dict, d: Path, by_hash: bool = True) -> None:
    r = meta["robot"]
    h = robot.urdf_hash()
    if by_hash and h != r["urdf_sha256"]:
        raise ValueError(
            f"the model in {d} was made for robot {r['name']!r} (URDF sha256 {r['urdf_sha256'][:12]}…), but the "
            f"robot given is {robot.name!r} (URDF sha256 {h[:12]}…). A model only corrects the robot description "
            f"it was calibrated on: load it without robot= to rebuild its own robot from {d / _URDF}, or "
            "calibrate and train a model for this robot")
    if list(robot.joint_names) != r["joint_names"]:
        raise ValueError(f"the model in {d} expects joints {r['joint_names']}, the robot given has {robot.joint_names}")
    if list(robot.marker_names) != r["marker_names"]:
        raise ValueError(f"the model in {d} was made with markers {r['marker_names']}, the robot given has "
                         f"{robot.marker_names}; build the robot with the same markers or load without robot=")
    differs = _same_markers(robot, r) if len(r["markers"]) == len(robot.markers) else "the number of markers differs"
    if differs:
        raise ValueError(f"the robot given does not match the model in {d}: {differs}. A marker's point is part of "
                         "the calibration: load without robot= to use the model's own markers, or build the robot "
                         "with the same ones")


def load(directory: str | os.PathLike, robot=None, *, device: torch.device | str | None = None) -> CalibratedModel:
    """Read a model written by :func:`save`.

    Args:
        directory: the model directory.
        robot: optional :class:`~torchcal.kinematics.robot.Robot` to attach; refused (``ValueError``) when
            its URDF hash, joint names or marker names differ from the saved ones. Default: the
            robot is rebuilt from the saved ``robot.urdf`` and markers.
        device: where to put the tensors (default the given robot's device, else CPU).
    Returns:
        the :class:`~torchcal.deploy.model.CalibratedModel`; predictions equal the saved model's bit for
        bit on the same device.
    """

    d = Path(directory)
    meta = _read_meta(d)
    r = meta["robot"]
    if robot is not None:
        _check_robot(robot, meta, d)
        if device is not None and torch.device(device) != robot.device:
            robot = robot.to(device=device)
    else:
        f = d / r.get("urdf_file", _URDF)
        if not f.is_file():
            raise FileNotFoundError(f"{f} is missing; pass the robot with load(dir, robot=...)")
        raw = f.read_bytes()
        if hashlib.sha256(raw).hexdigest() != r["urdf_sha256"]:
            raise ValueError(f"{f} does not match the hash recorded in {d / _JSON}; the model directory was "
                             "modified or is corrupt")
        markers = [Marker(m["name"], m["link"], tuple(m["xyz"]), tuple(m["rpy"])) for m in r["markers"]]
        dtype = getattr(torch, r.get("dtype") or "float64")
        robot = Robot.from_urdf(raw.decode("utf-8-sig"), markers=markers, dtype=dtype, device=device or "cpu")
        _check_robot(robot, meta, d, by_hash=False)  # the file's own bytes matched the recorded hash above
    dev = robot.device
    tf = d / _TENSORS
    if not tf.is_file():
        raise FileNotFoundError(f"{tf} is missing; a model directory holds {_JSON}, {_TENSORS} and {_URDF}")
    want = meta.get("tensors_sha256")
    if want is not None and sha256_file(tf) != want:
        raise ValueError(f"{tf} does not match the SHA-256 recorded in {d / _JSON}: the tensors changed since the "
                         "model was saved (a copy error, a flipped byte, an edit), and a changed model gives wrong "
                         "commands; restore the file or save the model again")
    try:
        t = load_file(str(tf), device="cpu")
    except (SafetensorError, OSError, ValueError) as e:
        raise ValueError(f"{tf} cannot be read as a safetensors file ({e}); it is truncated or corrupt: restore it "
                         "or save the model again") from None
    t = {k: v.to(dev) for k, v in t.items()}
    try:
        names = meta["params"]["names"]
    except (KeyError, TypeError):
        raise ValueError(f"{d / _JSON} lacks the parameter names; the file is incomplete: save the model again") from None
    if names != robot.param_names:
        raise ValueError(f"the saved parameters ({len(names)}) do not match the robot's ({robot.n_params}); "
                         "the model was saved for another robot layout")
    params = ParamSet(list(names), list(meta["params"]["units"]), t["params.values"], t["params.free"].to(torch.bool),
                      t["params.lower"], t["params.upper"])
    residual = None
    if meta.get("residual"):
        rt = {k.split(".", 1)[1]: v for k, v in t.items() if k.startswith("residual.")}
        residual = ELM.from_state_dict(meta["residual"], rt)
    effects = []
    for i, rec in enumerate(meta.get("effects", [])):
        prefix = f"effects.{i}."
        state = dict(rec.get("state", {}))
        state.update({k[len(prefix):]: v for k, v in t.items() if k.startswith(prefix)})
        effects.append(effect_class(rec["type"]).from_state_dict(state, robot))
    return CalibratedModel(robot, params, effects, residual, marker=meta.get("marker"),
                           covariates=meta.get("covariates"), meta=meta.get("meta", {}))
