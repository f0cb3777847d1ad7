"""The ``argen`` command line (typer): :mod:`argen.cli.app` builds it from one module per command group, with the
helpers they share in :mod:`argen.cli.common`. Commands only parse, call the pipeline and print."""
