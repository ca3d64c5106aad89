"""Write the parametric indenter library to scenes/indenters/*.stl (binary STL, mm).

    .venv/bin/python scripts/make_indenters.py [--out scenes/indenters]
"""

from __future__ import annotations

from pathlib import Path

import typer

from transtac_sim.indenters.library import LIBRARY

REPO = Path(__file__).resolve().parents[1]


def main(out: Path = typer.Option(REPO / "scenes" / "indenters", help="output folder")) -> None:
    out.mkdir(parents=True, exist_ok=True)
    for name, spec in LIBRARY.items():
        mesh = spec.build()
        path = out / f"{name}.stl"
        mesh.export(path)
        print(f"{path.relative_to(REPO) if path.is_relative_to(REPO) else path}: {spec.description}, "
              f"{len(mesh.faces)} faces, volume {mesh.volume:.2f} mm^3 (ideal {spec.volume_mm3:.2f})")


if __name__ == "__main__":
    typer.run(main)
