"""One module per group of ``mimucal`` subcommands.

Each module defines ``register(subparsers)`` that adds its subcommands, each with a
``func(args) -> int`` default. :mod:`flows.cli` discovers the modules, so adding a command
never edits a shared list.
"""
