"""The ``detector`` command line: parse, call, print. User errors become one line on stderr, exit 2.

Commands: ``train`` (:mod:`detector.cli.train`), ``eval`` and ``predict`` (:mod:`detector.cli.eval`); what they
share is in :mod:`detector.cli.common`.
"""

from __future__ import annotations

import typer

from detector.cli.eval import register as register_eval
from detector.cli.train import register as register_train

HELP = ("detector: 6-DoF object poses from depth (train, eval, predict). The default model has two stages: a "
        "PointNet++ finds the objects and their centres, a crop network their poses; --preset cpu or paper trains "
        "the paper's single multi-task PointNet++ instead.")

app = typer.Typer(add_completion=False, no_args_is_help=True, pretty_exceptions_enable=False, help=HELP)


@app.callback(help=HELP)
def root() -> None:
    """The ``detector`` command group (its help is :data:`HELP`)."""


for _register in (register_train, register_eval):
    _register(app)


def main() -> None:
    """Console script ``detector``."""
    app(prog_name="detector")


if __name__ == "__main__":
    main()
