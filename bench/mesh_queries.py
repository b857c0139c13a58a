"""What one Warp mesh query costs per point: closest point unsigned, signed by pseudo-normals, signed by the
winding number, and a short ray, by how far the closest point may be searched for.

A closed icosphere of 5120 triangles, radius 0.375 m (the sphere of ``bench/contacts.py`` at N = 16);
20,000 query points either near its surface (within 3 cm outside it, where contacts are) or anywhere in the
cube of side 1.6 m around it. One launch per query kind, timed over 5 launches after a warm-up, the device
synchronised before every timer read. Output: a Markdown table of ns per point.

    python bench/mesh_queries.py --device cpu
"""

from __future__ import annotations

import argparse
import datetime
import time

import numpy as np
import warp as wp

POINTS = 20_000
QUERIES = {0: "closest point, unsigned", 1: "closest point, pseudo-normal sign", 2: "closest point, winding number",
           3: "ray of 1 cm"}


@wp.kernel
def query(mesh: wp.uint64, points: wp.array[wp.vec3], kind: int, max_dist: float, out: wp.array[float]):
    i = wp.tid()
    value = float(0.0)
    if kind == 0:
        unsigned = wp.mesh_query_point_no_sign(mesh, points[i], max_dist)
        value = unsigned.u
    elif kind == 1:
        normal = wp.mesh_query_point_sign_normal(mesh, points[i], max_dist)
        value = normal.sign
    elif kind == 2:
        winding = wp.mesh_query_point_sign_winding_number(mesh, points[i], max_dist)
        value = winding.sign
    else:
        ray = wp.mesh_query_ray(mesh, points[i], wp.vec3(0.0, 0.0, -0.01), 1.0)
        value = ray.t
    out[i] = value


def time_query(mesh, points, kind: int, max_dist: float, device) -> float:
    out = wp.zeros(len(points), dtype=float, device=device)
    args = [mesh.id, points, kind, max_dist, out]
    wp.launch(query, dim=len(points), inputs=args, device=device)
    wp.synchronize_device(device)
    start = time.perf_counter()
    for _ in range(5):
        wp.launch(query, dim=len(points), inputs=args, device=device)
    wp.synchronize_device(device)
    return (time.perf_counter() - start) / 5 / len(points) * 1e9


def main():
    import trimesh

    parser = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    parser.add_argument("--device", default=None)
    args = parser.parse_args()
    wp.init()
    device = wp.get_device(args.device)
    sphere = trimesh.creation.icosphere(subdivisions=4, radius=0.375)
    mesh = wp.Mesh(points=wp.array(sphere.vertices, dtype=wp.vec3, device=device),
                   indices=wp.array(sphere.faces.reshape(-1), dtype=wp.int32, device=device),
                   support_winding_number=True)
    rng = np.random.default_rng(0)
    direction = rng.normal(size=(POINTS, 3))
    direction /= np.linalg.norm(direction, axis=1)[:, None]
    clouds = {"near (≤ 3 cm outside)": direction * (0.375 + rng.uniform(0.0, 0.03, (POINTS, 1))),
              "anywhere (1.6 m cube)": rng.uniform(-0.8, 0.8, (POINTS, 3))}
    print(f"Mesh queries on {device.name}, Warp {wp.config.version}, {datetime.date.today()}: ns per point, "
          f"{len(sphere.faces)} triangles\n")
    print("| points | query | searched up to | ns per point |\n|---|---|---|---|")
    for name, cloud in clouds.items():
        points = wp.array(cloud, dtype=wp.vec3, device=device)
        for kind, label in QUERIES.items():
            for max_dist in ((0.05, 3.0) if kind < 3 else (0.0,)):
                ns = time_query(mesh, points, kind, max_dist, device)
                reach = f"{max_dist:g} m" if kind < 3 else "–"
                print(f"| {name} | {label} | {reach} | {ns:.0f} |", flush=True)


if __name__ == "__main__":
    main()
