"""The ``argen models`` commands: bring your own meshes (registered by argen.cli.app)."""

from __future__ import annotations

from pathlib import Path
from typing import Optional

import typer

from argen.cli.common import user_errors
from argen.models.symmetry import DEFAULT_TOL


def register(app: typer.Typer) -> None:
    """Add the ``models`` command group (``argen models import``) to ``app``."""

    models_app = typer.Typer(add_completion=False, no_args_is_help=True,
                             help="Your own objects: import meshes as a BOP models folder.")
    app.add_typer(models_app, name="models")

    @models_app.command("import")
    @user_errors
    def import_cmd(
        meshes: list[Path] = typer.Argument(..., help="mesh files or folders of them (OBJ+MTL, STL, PLY, GLB/GLTF, OFF)"),
        out: Path = typer.Option(..., "--out", help="BOP models folder to write or extend"),
        units: str = typer.Option("auto", "--units", help="auto, mm, cm or m: the files' length unit"),
        origin: str = typer.Option("keep", "--origin", help="keep the file's origin, or centre (box centre)"),
        up: Optional[str] = typer.Option(None, "--up", help="the file's axis pointing up when the object rests "
                                         "(x, y, z, -x, -y, -z); it becomes +z. Default: keep the axes"),
        symmetry: str = typer.Option("auto", "--symmetry", help="auto (search), none, or a JSON file of BOP "
                                     "symmetries keyed by file stem or id"),
        symmetry_tol: float = typer.Option(DEFAULT_TOL, "--symmetry-tol", help="fraction of the diameter a "
                                           "symmetry may move the surface by"),
    ):
        """Import meshes into a BOP models folder (PLY in mm, models_info.json with symmetries, names.json,
        models_eval/) that capture-sim, capture and replace take with --models."""
        # lazy: pyrender, open3d and trimesh take seconds to load; --help and the other commands need none
        from argen.models.meshimport import ImportOptions, import_to_folder

        opts = ImportOptions(units=units, origin=origin, up=up, symmetry=symmetry, symmetry_tol=symmetry_tol)
        imported = import_to_folder(meshes, out, opts)
        for o in imported:
            for line in o.lines():
                typer.echo(line)
        typer.echo(f"{out}: {len(imported)} object(s) imported; use --models {out} (names: "
                   f"{', '.join(o.model.name for o in imported)})")
