"""What a saved model's ``model.json`` must hold, checked field by field before anything is built
from it, and the checksum that covers everything a model is.

A model file edited by hand, truncated or written by something else must be refused with the
field that is wrong and the way out, never met later as a KeyError or a TypeError. The checksum
(``content_sha256``) is the SHA-256 of the JSON itself in a canonical form (sorted keys, no
white space), which records the SHA-256 of the tensor file and of the URDF text: a changed
marker point, parameter name or tensor byte gives another checksum.
"""
from __future__ import annotations

import hashlib
import json
import math
import re
from pathlib import Path

__all__ = ["check_meta", "content_sha256", "CHECKSUM_KEY", "DTYPES"]

CHECKSUM_KEY = "content_sha256"
DTYPES = ("float32", "float64")
_HEX64 = re.compile(r"[0-9a-f]{64}")


def content_sha256(meta: dict) -> str:
    """SHA-256 of ``meta`` (without its own checksum) as canonical JSON."""
    body = {k: v for k, v in meta.items() if k != CHECKSUM_KEY}
    text = json.dumps(body, sort_keys=True, separators=(",", ":"), allow_nan=False, ensure_ascii=True)
    return hashlib.sha256(text.encode()).hexdigest()


class _Fields:
    def __init__(self, f: Path):
        self.f = f

    def refuse(self, field: str, want: str, got) -> None:
        shown = repr(got) if not isinstance(got, (dict, list)) else type(got).__name__
        raise ValueError(f"{self.f}: field {field!r} must be {want}, got {shown[:80]}; the model file was edited or "
                         "written by something else: restore it from the saved copy or save the model again")

    def get(self, rec: dict, key: str, field: str, kind, want: str, optional: bool = False):
        if key not in rec:
            if optional:
                return None
            raise ValueError(f"{self.f}: field {field!r} is missing; the model file is incomplete: restore it or save "
                             "the model again")
        v = rec[key]
        if optional and v is None:
            return None
        if not kind(v):
            self.refuse(field, want, v)
        return v


def _is_int(v) -> bool:
    return isinstance(v, int) and not isinstance(v, bool)


def _is_num(v) -> bool:
    return isinstance(v, (int, float)) and not isinstance(v, bool) and math.isfinite(v)


def _strings(v) -> bool:
    return isinstance(v, list) and all(isinstance(x, str) for x in v)


def _vec3(v) -> bool:
    return isinstance(v, list) and len(v) == 3 and all(_is_num(x) for x in v)


def _check_robot(r: dict, F: _Fields) -> None:
    F.get(r, "name", "robot.name", lambda v: isinstance(v, str), "text")
    F.get(r, "urdf_sha256", "robot.urdf_sha256", lambda v: isinstance(v, str) and _HEX64.fullmatch(v),
          "a SHA-256 (64 hex digits)")
    F.get(r, "urdf_file", "robot.urdf_file", lambda v: isinstance(v, str) and v and "/" not in v and "\\" not in v
          and v not in (".", ".."), "a file name inside the model folder", optional=True)
    joints = F.get(r, "joint_names", "robot.joint_names", _strings, "a list of joint names")
    F.get(r, "joint_units", "robot.joint_units", _strings, "a list of units", optional=True)
    F.get(r, "marker_names", "robot.marker_names", _strings, "a list of marker names")
    markers = F.get(r, "markers", "robot.markers", lambda v: isinstance(v, list), "a list of markers")
    for i, m in enumerate(markers):
        where = f"robot.markers[{i}]"
        if not isinstance(m, dict):
            F.refuse(where, "an object {name, link, xyz, rpy}", m)
        F.get(m, "name", f"{where}.name", lambda v: isinstance(v, str), "text")
        F.get(m, "link", f"{where}.link", lambda v: isinstance(v, str), "text")
        F.get(m, "xyz", f"{where}.xyz", _vec3, "three finite numbers (m)")
        F.get(m, "rpy", f"{where}.rpy", _vec3, "three finite numbers (rad)")
    F.get(r, "dof", "robot.dof", lambda v: _is_int(v) and v == len(joints), f"the number of joints ({len(joints)})",
          optional=True)
    F.get(r, "dtype", "robot.dtype", lambda v: v in DTYPES, " or ".join(DTYPES), optional=True)


def check_meta(meta, f: Path, format_name: str, format_version: int) -> None:
    """Refuse (``ValueError`` naming ``f`` and the field) a ``model.json`` that is not a model of
    this format, or one whose fields have the wrong type or shape."""
    F = _Fields(f)
    if not isinstance(meta, dict):
        raise ValueError(f"{f} holds a JSON {type(meta).__name__}, not a torchcal model (an object with 'format': "
                         f"{format_name!r}); give the model folder a torchcal command wrote")
    if meta.get("format") != format_name:
        raise ValueError(f"{f} is not a torchcal model (format {meta.get('format')!r}, expected {format_name!r})")
    v = F.get(meta, "format_version", "format_version", lambda x: _is_int(x) and x >= 1, "a whole number ≥ 1")
    if v > format_version:
        raise ValueError(f"{f} has format version {v}, newer than this torchcal reads ({format_version}); "
                         "upgrade torchcal")
    F.get(meta, "robot", "robot", lambda x: isinstance(x, dict), "an object (the robot the model is for)")
    _check_robot(meta["robot"], F)
    params = F.get(meta, "params", "params", lambda x: isinstance(x, dict), "an object {names, units}")
    names = F.get(params, "names", "params.names", _strings, "a list of parameter names")
    F.get(params, "units", "params.units", lambda x: _strings(x) and len(x) == len(names),
          f"a list of {len(names)} units")
    F.get(meta, "marker", "marker", lambda x: isinstance(x, str), "a marker name or null", optional=True)
    F.get(meta, "covariates", "covariates", _strings, "a list of covariate names", optional=True)
    F.get(meta, "residual", "residual", lambda x: isinstance(x, dict), "an object or null", optional=True)
    effects = F.get(meta, "effects", "effects", lambda x: isinstance(x, list), "a list", optional=True) or []
    for i, e in enumerate(effects):
        if not isinstance(e, dict):
            F.refuse(f"effects[{i}]", "an object {name, type, state}", e)
        F.get(e, "type", f"effects[{i}].type", lambda x: isinstance(x, str), "an effect type")
        F.get(e, "state", f"effects[{i}].state", lambda x: isinstance(x, dict), "an object", optional=True)
    F.get(meta, "meta", "meta", lambda x: isinstance(x, dict), "an object", optional=True)
    F.get(meta, "tensors_sha256", "tensors_sha256", lambda x: isinstance(x, str) and _HEX64.fullmatch(x),
          "a SHA-256 (64 hex digits)", optional=True)
