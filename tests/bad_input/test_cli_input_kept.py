"""Issue 36, item 8 and the environment class: nothing the user wrote on the command line or in a
--config file is silently dropped or guessed, and values that would fail deep in the work are
refused at the door."""
from __future__ import annotations

import os
import subprocess
import sys
from pathlib import Path

import pytest

REPO = Path(__file__).resolve().parents[2]
UR5E = str(REPO / "urdf" / "ur5e.urdf")
SMR = "smr@flange=0,0,0.05"


def _base(data, out):
    return ["calibrate", "--robot", UR5E, "--marker", SMR, "--data", data, "--out", out]


def _refused(rc, err, *words):
    assert rc == 2 and "Traceback" not in err, err
    for w in words:
        assert w in err, (w, err)


def test_an_abbreviated_option_is_not_taken_for_another(tmp_path, torchcal_cli, ur5e_csv):
    cfg = tmp_path / "u.yaml"
    cfg.write_text("quiet: true\n")
    rc, _, err = torchcal_cli(*_base(ur5e_csv, tmp_path / "o"), "--conf", cfg)
    _refused(rc, err, "unrecognized arguments: --conf")
    assert not (tmp_path / "o").exists()


def test_a_single_valued_option_given_twice_is_refused(tmp_path, torchcal_cli, ur5e_csv):
    rc, _, err = torchcal_cli(*_base(ur5e_csv, tmp_path / "o"), "--data", ur5e_csv)
    _refused(rc, err, "--data takes one value and was given 2 times", "Give it once")
    rc, _, err = torchcal_cli(*_base(ur5e_csv, tmp_path / "o"), "--seed", "1", "--seed=2")
    _refused(rc, err, "--seed takes one value")
    # repeatable options stay repeatable (refused here only for the output, which holds the data)
    rc, _, err = torchcal_cli(*_base(ur5e_csv, ur5e_csv.parent), "--free", "*.x", "--free", "*.y")
    _refused(rc, err, "an input of this run")
    assert "given 2 times" not in err


def test_conflicting_options_are_refused(tmp_path, torchcal_cli, ur5e_csv):
    rc, _, err = torchcal_cli(*_base(ur5e_csv, tmp_path / "o"), "--test", ur5e_csv, "--holdout", "0.3")
    _refused(rc, err, "--test and --holdout were both given", "not both")


def test_a_yaml_key_given_twice_is_refused(tmp_path, torchcal_cli, ur5e_csv):
    cfg = tmp_path / "run.yaml"
    cfg.write_text(f"robot: {UR5E}\ndata: {ur5e_csv}\nmarker: ['{SMR}']\nseed: 1\nseed: 2\nout: {tmp_path / 'o'}\n")
    rc, _, err = torchcal_cli("calibrate", "--config", cfg)
    _refused(rc, err, "the key 'seed' is given twice (lines 4 and 5)")


def test_a_huge_seed_and_a_latin1_path_are_refused_at_the_door(tmp_path, torchcal_cli, ur5e_csv):
    rc, _, err = torchcal_cli(*_base(ur5e_csv, tmp_path / "o"), "--seed", str(10 ** 30))
    _refused(rc, err, "--seed", "64 bits")
    latin = os.fsdecode(str(tmp_path).encode() + b"/r\xe9sultat")  # a Latin-1 name, as a shell passes it
    rc, _, err = torchcal_cli(*_base(ur5e_csv, latin))
    _refused(rc, err, "is not UTF-8", "rename it")


def _sub(args, **env):
    return subprocess.run([sys.executable, "-m", "torchcal", *map(str, args)], capture_output=True, text=True,
                          env={**os.environ, "PYTHONPATH": str(REPO), **env}, timeout=300)


@pytest.mark.slow
def test_the_environment_gives_refusals_or_works(tmp_path, ur5e_csv):
    r = _sub(_base(ur5e_csv, tmp_path / "a"), TORCHCAL_THREADS="0")
    assert r.returncode == 2 and "TORCHCAL_THREADS='0'" in r.stderr and "Traceback" not in r.stderr, r.stderr
    r = _sub(_base(ur5e_csv, tmp_path / "b"), MPLBACKEND="module://matplotlib_inline.backend_inline_not_here")
    assert r.returncode == 0 and "MPLBACKEND" in r.stderr and "Traceback" not in r.stderr, r.stderr
    assert (tmp_path / "b" / "errors.png").is_file()
    r = _sub(_base(ur5e_csv, tmp_path / "c"), PYTHONWARNINGS="error")
    assert r.returncode == 0 and "Traceback" not in r.stderr, r.stderr


def test_an_option_that_would_be_ignored_is_refused(tmp_path, torchcal_cli, ur5e_csv):
    rc, _, err = torchcal_cli(*_base(ur5e_csv, tmp_path / "o"), "--polish")
    _refused(rc, err, "--polish", "not a swarm method", "ignored")
    rc, _, err = torchcal_cli("fleet", "--robot", UR5E, "--marker", SMR, "--data", tmp_path, "--out", tmp_path / "f",
                              "--shards", "3")
    _refused(rc, err, "--shards without --ray")


def test_a_list_option_given_twice_is_refused():
    # no command keeps a list option of the '--opt A B' form (effects are '--effect A --effect B'), so the
    # rule is checked on a parser that has one: a second '--opt C' would replace the first list
    import argparse
    from torchcal.cli.strict import _repeated
    p = argparse.ArgumentParser(allow_abbrev=False)
    p.add_argument("--names", nargs="+")
    p.add_argument("--each", action="append")
    msg = _repeated(["--names", "a", "b", "--names", "c"], p)
    assert msg is not None and "--names takes its values at once" in msg and "Give it once" in msg
    assert _repeated(["--each", "a", "--each", "b"], p) is None  # append options add up


