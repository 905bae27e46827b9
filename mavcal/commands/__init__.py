"""CLI subcommands; one module each (see :mod:`mavcal.cli`)."""
