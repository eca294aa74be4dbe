"""Help texts as people read them: the commands' docstrings are reStructuredText (``code``),
argparse prints them verbatim, so literal markup is turned into plain quotes once, for every
command, after they are registered."""

from __future__ import annotations

import argparse
import re

_LITERAL = re.compile(r"``(.+?)``", re.S)


def plain(text: str | None) -> str | None:
    """``x`` -> 'x' (a reST literal as a quoted word)."""
    return None if text is None else _LITERAL.sub(r"'\1'", text)


def clean_help(parser: argparse.ArgumentParser) -> None:
    """Plain descriptions, epilogs and option helps in ``parser`` and its subcommands."""
    parser.description = plain(parser.description)
    parser.epilog = plain(parser.epilog)
    for action in parser._actions:
        if action.help and action.help is not argparse.SUPPRESS:
            action.help = plain(action.help)
        if isinstance(action, argparse._SubParsersAction):
            for choice in action._choices_actions:
                choice.help = plain(choice.help)
            for sub in action.choices.values():
                clean_help(sub)
