"""The ``reach`` command line: wires subcommands to library calls (see :mod:`reach.cli`)."""
