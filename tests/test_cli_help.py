"""Every flag, positional and subcommand of `vslam` says what it is for in --help, and every --help works."""

from __future__ import annotations

import argparse
import re

import pytest

from vslam.cli import build_parser, main


def _commands(parser: argparse.ArgumentParser, path: tuple[str, ...] = ()):
    """(path, parser, subcommand help) of the top level and every subcommand below it, depth first."""
    yield path, parser, None
    for action in parser._actions:
        if isinstance(action, argparse._SubParsersAction):
            helps = {a.dest: a.help for a in action._choices_actions}
            for name, sub in action.choices.items():
                for p, parser_, h in _commands(sub, path + (name,)):
                    yield p, parser_, helps.get(name) if p == path + (name,) else h


COMMANDS = list(_commands(build_parser()))
ISSUE = re.compile(r"\bissues? ?#?\d+", re.IGNORECASE)  # the tracker's numbers mean nothing to a user


def test_the_walk_reaches_every_subcommand():
    paths = {" ".join(p) for p, _, _ in COMMANDS}
    assert {"run", "demo", "bench", "train detector", "train place", "train keypoints", "make-dynamic",
            "eval-detector", "eval-features", "quantize keypoints", "fusion"} <= paths


@pytest.mark.parametrize("path,parser,sub_help", [pytest.param(*c, id=" ".join(c[0]) or "vslam") for c in COMMANDS])
def test_every_argument_has_help(path, parser, sub_help):
    if path:
        assert sub_help, f"`vslam {' '.join(path)}` has no help line in its parent's list"
        assert not ISSUE.search(sub_help), sub_help
    for action in parser._actions:
        if isinstance(action, (argparse._HelpAction, argparse._SubParsersAction)):
            continue
        name = "/".join(action.option_strings) or action.dest
        assert action.help and action.help != argparse.SUPPRESS and action.help.strip(), \
            f"vslam {' '.join(path)}: {name} has no help text"
        assert not ISSUE.search(action.help), f"vslam {' '.join(path)}: {name}: {action.help}"


@pytest.mark.parametrize("path", [p for p, _, _ in COMMANDS], ids=lambda p: " ".join(p) or "vslam")
def test_help_exits_0_with_usage(path, capsys):
    with pytest.raises(SystemExit) as e:
        main([*path, "--help"])
    assert e.value.code == 0
    out = capsys.readouterr().out
    assert out.startswith(f"usage: vslam {' '.join(path)}".rstrip()), out[:200]
    assert "-q, --quiet" in out  # accepted at every level (vslam -q run, vslam run -q)
    assert not ISSUE.search(out), out
