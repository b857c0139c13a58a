"""Write examples/meshes/rock.obj: a closed, lumpy rock for the mesh-collider example (an icosphere of 1280
triangles, radius 0.3 m, each vertex pushed out by a smooth random bump of up to ±20 %; seeded, so the file
is reproducible).

    python tools/make_rock.py
"""

from pathlib import Path

import numpy as np
import trimesh


def rock(seed: int = 12) -> trimesh.Trimesh:
    sphere = trimesh.creation.icosphere(subdivisions=3, radius=1.0)
    rng = np.random.default_rng(seed)
    waves = rng.normal(size=(6, 3))  # a sum of six smooth waves over the unit sphere
    phases = rng.uniform(0.0, 2.0 * np.pi, 6)
    bump = np.sin(sphere.vertices @ waves.T * 1.5 + phases).sum(axis=1)
    scale = 0.3 * (1.0 + 0.2 * bump / np.abs(bump).max())
    return trimesh.Trimesh(sphere.vertices * scale[:, None], sphere.faces, process=False)


if __name__ == "__main__":
    path = Path(__file__).parent.parent / "examples" / "meshes" / "rock.obj"
    mesh = rock()
    assert mesh.is_watertight and mesh.is_winding_consistent and mesh.volume > 0.0
    mesh.export(path)
    print(f"wrote {path}: {len(mesh.vertices)} vertices, {len(mesh.faces)} triangles")
