"""Every command's --help reads alike and names the exit codes; the messages that point a
new user the right way (issue 27)."""
from __future__ import annotations

import argparse

import pytest

from gearbench.cli import EXIT_CODES, build_parser, main


def _subparsers():
    parser = build_parser()
    action = next(a for a in parser._actions if isinstance(a, argparse._SubParsersAction))
    return parser, action


def test_every_command_help_is_a_sentence_and_names_the_exit_codes():
    parser, action = _subparsers()
    assert "exit codes" in parser.format_help()
    for name, sub in action.choices.items():
        text = sub.format_help()
        assert "exit codes:" in text and "3  bench fault" in text, name
        assert sub.description[0].isupper() and sub.description.endswith("."), (name, sub.description)
    for choice in action._choices_actions:
        assert choice.help[0].isupper() and choice.help.endswith("."), choice.dest


def test_methods_are_described_in_the_same_words():
    _, action = _subparsers()
    seen = {}
    for name in ("run", "identify", "calibrate", "reanalyze"):
        for a in action.choices[name]._actions:
            if a.dest == "method":
                seen[name] = a.help
    assert all("default (bias-reduced)" in h and "paper (as published" in h for h in seen.values()), seen
    assert not any("bias-corrected" in h for h in seen.values())


def test_run_help_says_serial_is_required_without_sim_and_identify_lists_columns():
    _, action = _subparsers()
    run_help = action.choices["run"].format_help()
    assert "required without" in run_help and "--sim" in run_help
    ident = action.choices["identify"].format_help()
    assert "position_rad" in ident and "current_a" in ident and "--motor" in ident


def test_misspelled_shipped_profile_gets_did_you_mean(capsys):
    assert main(["validate", "cvtt"]) == 2
    err = capsys.readouterr().err
    assert "did you mean 'cvt'?" in err and len(err.strip().splitlines()) == 1


def test_connect_without_scheme_is_refused_with_the_url_to_write(capsys, tmp_path):
    assert main(["run", "cvt", "--sim", "--out", str(tmp_path / "r"), "--connect", "localhost:9876"]) == 2
    err = capsys.readouterr().err
    assert "rerun+http://localhost:9876/proxy" in err
    assert not (tmp_path / "r").exists()             # refused before anything


def test_view_without_display_is_one_clear_line(capsys, tmp_path, monkeypatch):
    import json

    run = tmp_path / "run"
    run.mkdir()
    (run / "result.json").write_text(json.dumps({"run_id": "r", "serial": "S", "profile": "p",
                                                 "status": "passed", "motors": {}, "efficiency": []}))
    monkeypatch.delenv("DISPLAY", raising=False)
    monkeypatch.delenv("WAYLAND_DISPLAY", raising=False)
    code = main(["view", str(run)])
    err = capsys.readouterr().err
    if code == 0:
        pytest.skip("a Rerun viewer is listening on this host")
    assert code == 2 and len(err.strip().splitlines()) == 1, err
    assert "run continues" not in err and "--rrd FILE" in err and "rerun+http://" in err
    assert "gearbench: live view" not in err


def test_exit_code_text_matches_errors():
    from gearbench.errors import DriveError, GearbenchError

    assert f"{GearbenchError.exit_code}  bad input" in EXIT_CODES and f"{DriveError.exit_code}  bench fault" in EXIT_CODES
