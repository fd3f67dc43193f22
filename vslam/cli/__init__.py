"""The ``vslam`` command: argparse over the library's functions (``app``: run, demo, eval, synth, bench, presets;
``train``, ``dynamic``, ``features``, ``fusion``: the other subcommands). Library modules never print; a user's
error becomes one line here."""

from vslam.cli.app import build_parser, main

__all__ = ["build_parser", "main"]
