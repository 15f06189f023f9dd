"""Command modules of the `sgde` command line, one per sub-command."""
