"""What a pixel frame costs against what a CPU ray tracer needs for the same rays.

    python benchmarks/render_bound.py [--tasks hopper humanoid] [--sizes 48 84] [--frames 16]
                                      [--csv FILE]

For each task and image size it times D.Va's renderer (MuJoCo's Warp ray tracer inside
``jax.jit``: forward kinematics, pose upload, BVH refit, one ray per pixel, shading) on ``--frames``
envs at the task's initial pose, and Intel Embree (through the ``embreex`` package: ``pip install
embreex``) casting the same camera's rays at the same geoms, tessellated into triangles, closest hit
only, on a scene built once. That is the visibility a frame cannot do without; shading one hit per
pixel adds a few dozen operations, and a moving robot needs its scene updated every frame, which
the last column bounds from above: ``embreex`` can only rebuild one flat triangle BVH per scene
(no instancing, no refit), where Warp refits its BVH. Pin it to one core (``taskset -c 0``) for a
one-core comparison.
"""

from __future__ import annotations

import argparse
from pathlib import Path


def geom_triangles(model, data):
    """The model's geoms at ``data``'s pose as one (T, 3, 3) float32 array of world-space
    triangles (capsules and spheres tessellated at 16 segments, the ground plane a thin box)."""
    import mujoco
    import numpy as np
    import trimesh

    geom = mujoco.mjtGeom
    shapes = {
        int(geom.mjGEOM_PLANE): lambda s: trimesh.creation.box(extents=(60.0, 60.0, 1e-3)),
        int(geom.mjGEOM_CAPSULE): lambda s: trimesh.creation.capsule(height=2 * s[1], radius=s[0], count=[16, 16]),
        int(geom.mjGEOM_SPHERE): lambda s: trimesh.creation.uv_sphere(radius=s[0], count=[16, 16]),
        int(geom.mjGEOM_BOX): lambda s: trimesh.creation.box(extents=2 * s),
        int(geom.mjGEOM_CYLINDER): lambda s: trimesh.creation.cylinder(radius=s[0], height=2 * s[1], sections=16),
        int(geom.mjGEOM_ELLIPSOID): lambda s: trimesh.creation.uv_sphere(radius=1.0, count=[16, 16]).apply_scale(s),
    }
    triangles = []
    for g in range(model.ngeom):
        if model.geom_rgba[g, 3] == 0:  # invisible: no ray hits it
            continue
        if int(model.geom_type[g]) not in shapes:
            raise SystemExit(f"geom {g} is of type {model.geom_type[g]}, which this benchmark does not tessellate")
        mesh = shapes[int(model.geom_type[g])](model.geom_size[g])
        pose = np.eye(4)
        pose[:3, :3], pose[:3, 3] = data.geom_xmat[g].reshape(3, 3), data.geom_xpos[g]
        triangles.append(mesh.apply_transform(pose).triangles)
    return np.concatenate(triangles).astype(np.float32)


def camera_rays(model, data, camera: int, size: int):
    """(origins, unit directions), each (size², 3) float32: one ray through each pixel centre of
    the camera's ``size`` × ``size`` image."""
    import numpy as np

    position, frame = data.cam_xpos[camera], data.cam_xmat[camera].reshape(3, 3)
    half = np.tan(np.deg2rad(model.cam_fovy[camera]) / 2)
    u = ((np.arange(size) + 0.5) / size * 2 - 1) * half
    x, y = np.meshgrid(u, -u)
    directions = (x[..., None] * frame[:, 0] + y[..., None] * frame[:, 1] - frame[:, 2]).reshape(-1, 3)
    directions /= np.linalg.norm(directions, axis=1, keepdims=True)
    return np.broadcast_to(position, directions.shape).astype(np.float32), directions.astype(np.float32)


def measure(task_name: str, size: int, frames: int) -> dict:
    """Warp's and Embree's seconds per frame for one task and image size."""
    import jax
    import jax.numpy as jnp
    import mujoco
    import numpy as np

    try:
        from embreex import rtcore, rtcore_scene
        from embreex.mesh_construction import TriangleMesh
    except ImportError:
        raise SystemExit("this benchmark needs Embree's Python bindings: pip install embreex") from None
    from dva.analysis.bench import timed
    from dva.envs.rendering import PixelRenderer
    from dva.tasks import make_task

    task = make_task(task_name)
    model = task.mj_model
    qpos = jnp.tile(jnp.asarray(model.qpos0, jnp.float32), (frames, 1))
    warp_s = timed(jax.jit(PixelRenderer(task, frames, size)), qpos, repeats=10)[1]

    data = mujoco.MjData(model)
    mujoco.mj_forward(model, data)
    triangles = geom_triangles(model, data)
    origins, directions = camera_rays(model, data, model.camera(task.camera).id, size)
    origins, directions = np.tile(origins, (frames, 1)), np.tile(directions, (frames, 1))

    device = rtcore.EmbreeDevice()  # one per process, as a renderer would keep it

    def build():
        scene = rtcore_scene.EmbreeScene(device)
        TriangleMesh(scene, triangles)
        return scene

    scene = build()
    _, trace_s, hits = timed(lambda: scene.run(origins, directions, output=1), repeats=10)
    build_s = timed(build, repeats=10)[1]
    rays = frames * size * size
    return dict(
        setting=f"{task_name} {size}",
        task=task_name,
        image_size=size,
        frames=frames,
        triangles=len(triangles),
        hit_share=float((hits["geomID"] >= 0).mean()),
        warp_ms_per_frame=1e3 * warp_s / frames,
        warp_mrays_per_s=rays / warp_s / 1e6,
        embree_trace_ms_per_frame=1e3 * trace_s / frames,
        embree_mrays_per_s=rays / trace_s / 1e6,
        embree_build_ms=1e3 * build_s,
        ratio=trace_s / warp_s,
    )


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("--tasks", nargs="+", default=["hopper", "humanoid"])
    parser.add_argument("--sizes", nargs="+", type=int, default=[48, 84])
    parser.add_argument("--frames", type=int, default=16, help="envs rendered per call (the CPU preset's 16)")
    parser.add_argument("--csv", type=Path, help="also write the measurements to this CSV file")
    args = parser.parse_args()

    from dva.analysis.bench import machine_description, markdown_table, write_csv

    rows = [measure(task, size, args.frames) for task in args.tasks for size in args.sizes]
    print(machine_description())
    print(
        markdown_table(
            [
                "task",
                "image",
                "Warp (ms/frame)",
                "Warp (Mrays/s)",
                "Embree trace (ms/frame)",
                "Embree (Mrays/s)",
                "Embree trace ÷ Warp",
                "Embree scene rebuild (ms)",
            ],
            [
                (
                    r["task"],
                    r["image_size"],
                    f"{r['warp_ms_per_frame']:.3f}",
                    f"{r['warp_mrays_per_s']:.1f}",
                    f"{r['embree_trace_ms_per_frame']:.3f}",
                    f"{r['embree_mrays_per_s']:.1f}",
                    f"{r['ratio']:.2f}",
                    f"{r['embree_build_ms']:.1f}",
                )
                for r in rows
            ],
        )
    )
    if args.csv:
        write_csv(args.csv, [dict(row, device=machine_description()) for row in rows])


if __name__ == "__main__":
    import dva

    dva.configure()  # before JAX computes: the CPU convolution flags, compile caches
    main()
