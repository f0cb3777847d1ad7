"""The ``detector`` command line (typer): :mod:`detector.cli.app` builds it from one module per command group,
with the helpers they share in :mod:`detector.cli.common`. Commands only parse, call and print."""
