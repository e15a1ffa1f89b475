"""Subcommands of ``skinstretch``: one module per command, each defining ``register(subparsers)``.

``register`` adds a parser to the argparse sub-parsers object and sets ``func`` to a callable taking the parsed
arguments and returning an exit code. :mod:`skinstretch.cli` discovers the modules of this package.
"""
