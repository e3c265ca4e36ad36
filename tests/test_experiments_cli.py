"""The experiments command line (issue 24): every argument and the output path are checked before
any training, the results file is written atomically, a committed results file is only replaced
with --force, and a single-model study runs to the end."""

from __future__ import annotations

import json
import pathlib
from pathlib import Path

import pytest

from pgm_wm.experiments import __main__ as cli
from pgm_wm.experiments import results as res_mod
from pgm_wm.experiments.results import load_results, results_path, save_results

SMOKE = ["ch4", "--models", "repeat last", "--seeds", "1", "--budget", "1"]


@pytest.fixture
def no_training(monkeypatch):
    """Fail the test if the command gets as far as training."""
    def refuse(*args, **kwargs):
        raise AssertionError("training started although an argument was bad")

    monkeypatch.setattr(cli, "run_experiment", refuse)


@pytest.mark.parametrize("bad", [["--budget", "0"], ["--budget", "-5"], ["--budget", "nan"], ["--budget", "inf"],
                                 ["--jobs", "0"], ["--jobs", "-3"], ["--jobs", "100000"], ["--seeds", "0"],
                                 ["--models", "no such model"], ["--models", "repeat last", "repeat last"]])
def test_bad_arguments_stop_before_training(bad, no_training, capsys, tmp_path):
    with pytest.raises(SystemExit) as stop:
        cli.main(["ch4", *bad, "--out", str(tmp_path / "r.json")])
    assert stop.value.code == 2
    assert "Traceback" not in capsys.readouterr().err


def test_unwritable_out_stops_before_training(no_training, capsys, tmp_path):
    blocker = tmp_path / "a_file"
    blocker.write_text("")
    with pytest.raises(SystemExit):
        cli.main([*SMOKE, "--out", str(blocker / "r.json")])   # its folder would be a file
    assert "argument --out: out: cannot write" in capsys.readouterr().err
    with pytest.raises(SystemExit):
        cli.main([*SMOKE, "--out", str(tmp_path)])              # a folder
    assert "is a folder" in capsys.readouterr().err


def test_committed_results_file_is_not_replaced_without_force(no_training, capsys):
    committed = results_path("ch4_memory_arm")
    if not res_mod.is_committed(committed):
        pytest.skip("not inside a git clone with the committed results")
    before = committed.read_bytes()
    with pytest.raises(SystemExit):
        cli.main(SMOKE)                                         # default --out: the committed file
    assert "committed results file; pass --force" in capsys.readouterr().err
    assert committed.read_bytes() == before


def test_single_model_study_writes_its_file_and_exits_0(tmp_path, capsys):
    out = tmp_path / "one.json"
    assert cli.main([*SMOKE, "--out", str(out)]) == 0
    printed = capsys.readouterr().out
    assert "one model only" in printed and f"written: {out}" in printed
    assert list(load_results(out)["models"]) == ["repeat last"]


def test_results_are_written_atomically(tmp_path, monkeypatch):
    path = tmp_path / "r.json"
    good = {"provenance": {}, "horizons": [1], "models": {"a": {"sq_err": [[[1.0]]]}}}
    save_results(path, good)
    before = path.read_text()
    real = pathlib.Path.write_text

    def half_then_disk_full(self, text, *args, **kwargs):
        real(self, text[: len(text) // 2], *args, **kwargs)
        raise OSError(28, "No space left on device")

    monkeypatch.setattr(pathlib.Path, "write_text", half_then_disk_full)
    with pytest.raises(OSError):
        save_results(path, {**good, "horizons": [2], "models": {"a": {"sq_err": [[[2.0]]]}}})
    monkeypatch.undo()
    assert path.read_text() == before and json.loads(before)["horizons"] == [1]
    assert [p.name for p in Path(tmp_path).iterdir()] == ["r.json"]     # no temporary file left
