"""Write the "user's own" mesh for the walk-through: one OBJ file in metres with vertex colours and nothing
else (no BOP naming, no models_info.json), as a CAD export or a scan would arrive.

By default it is LineMOD's duck (../shared/data/lm, BOP LM, CC BY 4.0: Hinterstoisser et al. 2012, BOP
benchmark), converted from millimetres; without that data, argen's procedural drill stand-in.

    python examples/custom_object/make_mesh.py OUT.obj
"""

from __future__ import annotations

import sys
from pathlib import Path

from argen import bop
from argen.models.objects import builtin_objects

REPO = Path(__file__).resolve().parents[2]
LM_DUCK = REPO.parent / "shared" / "data" / "lm" / "models" / "obj_000009.ply"


def main(out: str) -> None:
    out_p = Path(out)
    out_p.parent.mkdir(parents=True, exist_ok=True)
    if LM_DUCK.is_file():
        mesh, what = bop.read_mesh(LM_DUCK), "LineMOD duck"   # metres
    else:
        mesh, what = builtin_objects(["drill"])[0].mesh, "procedural drill"
    mesh.export(out_p)  # OBJ: metres, vertex colours on the 'v' lines
    print(f"{out_p}: {what}, {len(mesh.vertices)} vertices, {mesh.extents.max() * 1000:.0f} mm across (file in metres)")


if __name__ == "__main__":
    main(sys.argv[1] if len(sys.argv) > 1 else "data/custom/mesh/duck.obj")
