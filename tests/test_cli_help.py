"""``--help`` of every command reads as plain text: no reST markup, defaults shown, examples on their lines."""

import argparse

import pytest

from linereg.cli import build_parser, main


def commands(parser: argparse.ArgumentParser, prefix: tuple[str, ...] = ()) -> list[tuple[str, ...]]:
    """Returns every command path of ``parser`` (``()``, ``("map",)``, ``("map", "build")``, ...)."""
    found = [prefix]
    for action in parser._actions:
        if isinstance(action, argparse._SubParsersAction):
            for name, sub in action.choices.items():
                found += commands(sub, (*prefix, name))
    return found


COMMANDS = commands(build_parser())


def help_of(capsys, command: tuple[str, ...]) -> str:
    with pytest.raises(SystemExit) as exit_:
        main([*command, "--help"])
    assert exit_.value.code == 0
    return capsys.readouterr().out


def test_every_command_is_listed():
    names = {" ".join(c) for c in COMMANDS}
    assert {"demo", "localize", "map build", "map info", "serve", "query", "bench demo"} <= names
    assert len([c for c in COMMANDS if c[:1] == ("bench",)]) > 3  # bench and its benchmarks


@pytest.mark.parametrize("command", COMMANDS, ids=lambda c: " ".join(c) or "linereg")
def test_help_has_no_rest_markup(capsys, monkeypatch, command):
    monkeypatch.setenv("COLUMNS", "100")
    text = help_of(capsys, command)
    assert "usage: linereg" in text
    assert "``" not in text


def test_serve_help_shows_every_default(capsys):
    text = " ".join(help_of(capsys, ("serve",)).split())  # wrapping aside
    parser = next(a for a in build_parser()._actions if isinstance(a, argparse._SubParsersAction)).choices[
        "serve"
    ]
    for action in parser._actions:
        if action.required or action.help in (None, argparse.SUPPRESS) or action.dest == "help":
            continue
        shown = " ".join((action.help % vars(action)).split())
        assert shown in text and "default" in shown, action.option_strings
        if isinstance(action.default, int | float) and not isinstance(action.default, bool):
            assert str(action.default) in shown, shown  # the value itself
    assert "(default 2)" in text and "(default 10000)" in text


def test_map_help_examples_on_their_own_lines(capsys):
    lines = help_of(capsys, ("map",)).splitlines()
    build = [line for line in lines if line.strip().startswith("linereg map build ")]
    info = [line for line in lines if line.strip().startswith("linereg map info ")]
    assert len(build) == 2 and len(info) == 1  # a scan; a sweep with its road markings
    assert all(".linemap" in line for line in build) and info[0].split()[-1].endswith(".linemap")
