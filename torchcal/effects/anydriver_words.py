"""Words and units for :class:`~torchcal.effects.anydriver.ParameterDrivers`: each finding said as
a person would say it ("the instrument frame turns 0.8 mrad per hour (time)", "joint j3's zero
shifts by 1.9 mrad at row 212, and stays", "the marker point differs by 12.4 mm for tool = probe")."""
from __future__ import annotations

from torch import Tensor

from torchcal.effects.drivers import driver_kind, driver_unit, driver_words
from torchcal.effects.shapes import PERIODIC, WINDOW, cycle_period, period_parts, settle_parts, window_parts
from torchcal.params import display_unit

__all__ = ["coef_unit", "axis_label", "parameter_words", "mode_words", "describe"]

_ODD = {"odd2": "squared, its sign kept", "odd3": "cubed"}
_AXIS = {"x": "x", "y": "y", "z": "z", "rx": "about x", "ry": "about y", "rz": "about z", "dx": "x", "dy": "y",
         "dz": "z", "droll": "about x (roll)", "dpitch": "about y (pitch)", "dyaw": "about z (yaw)"}


def coef_unit(param_unit: str, robot, driver: str, tag: str) -> str:
    """The unit of a term's coefficient: the parameter's per driver unit for a rate or a slope."""
    if tag == "lin" or tag.startswith(("hinge", "sat")):
        return f"{param_unit}/{driver_unit(robot, driver)}"
    return param_unit


def axis_label(robot, driver: str) -> str:
    kind = driver_kind(driver)
    if kind == "level":
        return f"{driver.split(':', 1)[1]} (level index)"
    return f"{driver_words(driver)} [{driver_unit(robot, driver)}]"


def parameter_words(eff, p: str) -> str:
    """A parameter in words: a joint's zero or origin, the instrument frame, a marker point."""
    offs = eff._offset_params()
    if p in offs:
        return f"joint {offs[p]}'s zero"
    head, comp = p.rsplit(".", 1)
    turn = comp in ("rx", "ry", "rz", "droll", "dpitch", "dyaw")
    if head == "base":
        return f"the instrument frame ({'turn' if turn else 'position'} {_AXIS.get(comp, comp)})"
    if head in eff.robot.joint_names:
        return f"joint {head}'s origin ({'turn' if turn else 'shift'} {_AXIS.get(comp, comp)})"
    return f"the marker point {head} ({_AXIS.get(comp, comp)})"


def _value(v: float, unit: str) -> str:
    base = unit.split("/")[0]
    f, shown = display_unit(base)
    return f"{v * f:.3g} {shown}"


def _rate(v: float, unit: str, robot, driver: str) -> str:
    du = driver_unit(robot, driver)
    if du == "s":  # a drift per second is unreadable: per hour
        return f"{_value(v * 3600, unit)} per hour"
    return f"{_value(v, unit)} per {du}"


def _span(v: float, robot, driver: str) -> str:
    """A length along a driver (a time constant): minutes or hours for time in s."""
    du = driver_unit(robot, driver)
    if du == "s" and v >= 5400:
        return f"{v / 3600:.3g} h"
    if du == "s" and v >= 90:
        return f"{v / 60:.3g} min"
    return f"{v:.3g} {'rows' if driver_kind(driver) == 'row' else du}"


def mode_words(eff, label: str) -> str:
    p, d, tag = label.split("~")
    if p.endswith(".point") and tag == "levels":
        return f"the marker point {p[:-6]} takes one value per level of {d.split(':', 1)[1]}"
    if p.endswith((".point", ".frame")):
        what = (f"the marker point {p[:-6]} moves" if p.endswith(".point")
                else "the instrument frame moves as one rigid body (3 shifts, 3 turns)")
        if tag == "levels":
            return f"{what} per level of {d.split(':', 1)[1]}"
        if tag.startswith("exp"):
            return f"{what} as it settles along {driver_words(d)}, with a time constant of {_span(settle_parts(tag)[0], eff.robot, d)}"
        if tag.startswith("cyc"):
            return f"{what} in a cycle along {driver_words(d)}, with a period of {_span(cycle_period(tag), eff.robot, d)}"
        if tag.startswith(WINDOW):
            a, b = window_parts(tag)
            return f"{what} from {_at(a, d)} to {_at(b, d)}, and back"
        return f"{what} at {_at(float(tag[4:]), d)}, and stays"
    what = parameter_words(eff, p)
    if tag == "levels":
        return f"{what} takes one value per level of {d.split(':', 1)[1]}"
    if tag.startswith("step"):
        return f"{what} steps at {driver_words(d)} = {float(tag[4:]):.6g}"
    if tag.startswith(WINDOW):
        a, b = window_parts(tag)
        return f"{what} differs from {_at(a, d)} to {_at(b, d)}, and comes back"
    if tag.startswith("exp"):
        tau = _span(settle_parts(tag)[0], eff.robot, d)
        return f"{what} settles along {driver_words(d)}, with a time constant of {tau}"
    if tag.startswith("cyc"):
        return f"{what} cycles along {driver_words(d)}, with a period of {_span(cycle_period(tag), eff.robot, d)}"
    if tag in ("odd2", "odd3"):
        return f"{what} varies with {driver_words(d)} {_ODD[tag]}: a stiffness that changes with the load"
    shape = {"lin": "linearly", "quad": "in a bow", "cube": "in an S"}.get(tag)
    if shape is None:
        shape = ("in a smooth curve" if tag.startswith("spl") else "periodically" if tag[:3] in ("sin", "cos")
                 else "piecewise linearly")
    return f"{what} varies {shape} with {driver_words(d)}"


def _at(x: float, d: str) -> str:
    """Where along the driver ``d`` a break ``x`` sits, in words."""
    return f"row {int(x + 0.5)}" if driver_kind(d) == "row" else f"{driver_words(d)} = {x:.6g}"


def _term(eff, p: str, d: str, tag: str, v: float, unit: str) -> str:
    what = parameter_words(eff, p)
    mean, half = eff.ranges.get(d, (0.0, 1.0))
    if tag.startswith("lvl="):
        return f"{what} differs by {_value(v, unit)} for {d.split(':', 1)[1]} = {tag[4:]}"
    if tag.startswith("step"):
        return f"{what} shifts by {_value(v, unit)} at {_at(float(tag[4:]), d)}, and stays"
    if tag.startswith(WINDOW):
        a, b = window_parts(tag)
        return f"{what} shifts by {_value(v, unit)} from {_at(a, d)} to {_at(b, d)}, and back"
    if tag.startswith("exp"):
        # the column is 1 at the start and 0 once settled: the parameter moves by -v as it settles
        return (f"{what} moves by {_value(-v, unit)} as it settles along {driver_words(d)}, with a time constant "
                f"of {_span(settle_parts(tag)[0], eff.robot, d)}")
    if tag == "lin":
        return f"{what} changes {_rate(v, unit, eff.robot, d)} ({driver_words(d)})"
    if tag.startswith("hinge"):
        k = float(tag[5:])
        return (f"{what}'s rate along {driver_words(d)} changes by {_rate(v, unit, eff.robot, d)} beyond "
                f"{k:.4g} {driver_unit(eff.robot, d)}")
    if tag.startswith("sat"):
        k = float(tag[3:])
        return (f"{what} changes by an extra {_rate(v, unit, eff.robot, d)} ({driver_words(d)}) within ±{k:.4g} "
                f"{driver_unit(eff.robot, d)}, and no further beyond: its stiffness changes there")
    if tag in ("odd2", "odd3"):
        return (f"{what} moves by a further {_value(v, unit)} at {driver_words(d)} = ±{half:.4g} "
                f"{driver_unit(eff.robot, d)}, as {driver_words(d)} {_ODD[tag]}: its stiffness changes with the load")
    if tag.startswith(PERIODIC):
        phase, period, _ = period_parts(tag)
        return (f"{what} swings by ±{_value(abs(v), unit)} ({phase} phase) along {driver_words(d)}, with a period "
                f"of {_span(period, eff.robot, d)}")
    if tag[:3] in ("sin", "cos"):
        return f"{what} varies by ±{_value(abs(v), unit)} with {tag[:3]}({tag[3:]}·{d.split(':', 1)[1]})"
    top = 1.0 if tag in ("quad", "cube") else ((mean + half - float(tag[3:])) / (half or 1.0)) ** 2
    return f"{what} bends by {_value(v * top, unit)} over the range of {driver_words(d)} ({tag})"


def describe(eff, theta: Tensor, free: Tensor | None) -> list[str]:
    """One sentence per identified term, in words and units."""
    out = []
    units = eff.param_units
    for i, (p, d, tag) in enumerate(eff.terms):
        if free is not None and not bool(free[i]):
            continue
        out.append(_term(eff, p, d, tag, float(theta[i]), units[i]))
    return out
