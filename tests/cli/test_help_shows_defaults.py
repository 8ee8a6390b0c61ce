"""``torchcal <cmd> --help``: every option has a help text and shows its default; one option name
has one meaning across commands; renamed options are refused with their new name; each solver is
listed once (issue 35 §4)."""
from __future__ import annotations

import argparse
import re

import pytest

from torchcal.cli.app import build_parser, main
from torchcal.optim import solvers

_, COMMANDS = build_parser()


def _help(cmd: str, capsys, collapse: bool = True) -> str:
    with pytest.raises(SystemExit) as e:
        main([cmd, "--help"])
    assert e.value.code == 0
    out = capsys.readouterr().out
    return " ".join(out.split()) if collapse else out  # argparse wraps lines: compare with spaces collapsed


def _entries(cmd: str, capsys) -> dict[str, str]:
    """Each option's entry in ``--help`` (its flags, then its text, spaces collapsed), by its last flag."""
    raw = _help(cmd, capsys, collapse=False).split("\noptions:\n", 1)[1]
    out = {}
    for chunk in re.split(r"\n(?=  -)", raw):
        flags = re.findall(r"(--?[\w-]+)", chunk.split("  ", 2)[1] if chunk.startswith("  ") else chunk)
        for f in flags:
            out[f] = " ".join(chunk.split())
    return out


def _options(cmd: str) -> list[argparse.Action]:
    return [a for a in COMMANDS[cmd]._actions if a.option_strings and a.help != argparse.SUPPRESS
            and not isinstance(a, argparse._HelpAction)]


@pytest.mark.parametrize("cmd", sorted(COMMANDS))
def test_every_option_has_help_and_shows_its_default(cmd, capsys):
    entries = _entries(cmd, capsys)
    for a in _options(cmd):
        flag = a.option_strings[-1]
        assert (a.help or "").strip(), f"torchcal {cmd} {flag} has no help text"
        assert flag in entries, f"torchcal {cmd} {flag} is not in --help"
        if a.required or a.default in (None, False, []):
            continue
        shown = f"(default: {a.default})"
        assert shown in entries[flag], f"torchcal {cmd} {flag}: {shown} missing from its help: {entries[flag]}"


def test_noise_mm_means_a_per_axis_standard_deviation_wherever_it_is_taken(capsys):
    takers = [cmd for cmd in COMMANDS if any("--noise-mm" in a.option_strings for a in _options(cmd))]
    assert sorted(takers) == ["plan", "simulate"]
    for cmd in takers:
        assert "--noise-mm NOISE_MM instrument noise: standard deviation per axis (mm)" in _help(cmd, capsys)


@pytest.mark.parametrize("argv, new", [
    (["loop", "--noise-mm", "0.03"], "--noise-floor-mm"),
    (["loop", "--candidates", "backlash", "joint_scale"], "--effect"),
    (["loop", "--candidates"], "--effect"),
])
def test_a_renamed_option_is_refused_with_its_new_name(argv, new, capsys):
    with pytest.raises(SystemExit) as e:
        main(argv + ["--robot", "r.urdf", "--data", "d.csv", "--out", "o"])
    assert e.value.code == 2
    err = capsys.readouterr().err
    assert f"{argv[1]} is now {new}" in err


def test_effects_are_picked_the_same_way_in_loop_plan_and_fleet():
    for cmd in ("loop", "plan", "fleet", "simulate"):
        eff = [a for a in _options(cmd) if "--effect" in a.option_strings]
        assert len(eff) == 1 and isinstance(eff[0], argparse._AppendAction), cmd
    # and no command takes effect names another way
    assert not any("--candidates" in a.option_strings for a in _options("loop"))
    parsed = COMMANDS["loop"].parse_args(["--effect", "backlash", "--effect", "joint_scale", "--robot", "r",
                                          "--data", "d", "--out", "o"])
    assert parsed.effect == ["backlash", "joint_scale"]


def test_each_method_is_listed_once_and_an_alias_still_works(capsys):
    text = _help("calibrate", capsys).split(" options: ", 1)[1]
    listed = text.split("--method METHOD", 1)[1].split("(default: lm)")[0]
    for name, aliases in solvers().items():
        assert len(re.findall(rf"(?<![\w+-]){re.escape(name)}(?![\w+-])", listed)) >= 1, name
        for al in aliases:
            assert f"also {al}" in listed or f", {al}" in listed, al
    # a parser built now, beside the registry read now (a test may have registered a toy solver since
    # this module's parser was built)
    (method,) = [a for a in build_parser()[1]["calibrate"]._actions if "--method" in a.option_strings]
    assert sorted(method.choices) == sorted(solvers()), "the choices are the solvers, each once"
    assert COMMANDS["calibrate"].parse_args(["--method", "Levenberg-Marquardt", "--robot", "r", "--data", "d",
                                             "--out", "o"]).method == "lm"


def test_no_effect_goes_with_no_other(tmp_path, capsys):
    assert main(["loop", "--effect", "none", "--effect", "backlash", "--robot", "r.urdf", "--data", "d.csv",
                 "--out", str(tmp_path / "o")]) == 2
    assert "--effect none (the geometry alone) cannot go with other effects ['backlash']" in capsys.readouterr().err


def test_a_config_file_with_a_renamed_key_is_told_the_new_name(tmp_path, capsys):
    cfg = tmp_path / "cfg.yaml"
    cfg.write_text("noise-mm: 0.03\n")
    assert main(["loop", "--config", str(cfg), "--robot", "r.urdf", "--data", "d.csv", "--out", "o"]) == 2
    assert "option 'noise-mm': --noise-mm is now --noise-floor-mm" in capsys.readouterr().err
