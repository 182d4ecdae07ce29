"""Subcommands of the ``fgnav`` CLI (see fgnav/cli.py)."""
