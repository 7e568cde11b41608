"""The ``jaxvox`` command line: ``run`` (the main job), ``voxelize``, ``build``.

Errors (missing file, bad option, bad resolution) print one line and exit with status 2.
"""

from __future__ import annotations

import argparse
import os
import resource
import sys
import time

import numpy as np

DEFAULT_OUT = "out"


def _peak_rss_mib() -> float:
    return resource.getrusage(resource.RUSAGE_SELF).ru_maxrss / 1024.0


def _load(path: str | None):
    import jaxvox as jv

    if path is None:
        return jv.default_scene(), "default scene"
    return jv.load_mesh(path), os.path.basename(path)


def _voxelize_timed(mesh, grid, mode: str):
    import jaxvox as jv

    start = time.perf_counter()
    vox = jv.voxelize(mesh, grid, mode=mode)
    vox.coords.block_until_ready()
    return vox, time.perf_counter() - start


def _save_npz(path: str, ijk: np.ndarray, grid, mode: str) -> None:
    """Writes voxel indices with the grid that places them."""
    np.savez_compressed(path, ijk=ijk, origin=np.asarray(grid.origin), voxel_size=np.asarray(grid.voxel_size),
                        resolution=grid.resolution, mode=mode)


def cmd_voxelize(args) -> int:
    """Voxelizes a mesh and writes the voxel indices (and the grid) to an .npz file."""
    import jaxvox as jv

    mesh, name = _load(args.mesh)
    grid = jv.Grid.fit(mesh, resolution=args.resolution)
    vox, seconds = _voxelize_timed(mesh, grid, args.mode)
    ijk = vox.to_numpy()
    _save_npz(args.out, ijk, grid, args.mode)
    print(f"{name}: {mesh.num_faces} triangles -> {len(ijk)} voxels ({args.mode}, {args.resolution}^3) "
          f"in {seconds:.2f} s; wrote {args.out}")
    return 0


def _build_timed(vox, kind: str):
    """Builds an octree or DAG of `vox`; returns (tree, seconds)."""
    import jaxvox as jv

    start = time.perf_counter()
    tree = (jv.build_dag if kind == "dag" else jv.build_octree)(vox)
    tree.mask.block_until_ready()
    return tree, time.perf_counter() - start


def _tree_line(tree, seconds: float) -> str:
    kind = "DAG" if tree.dag else "octree"
    return (f"{kind:6s} {tree.num_nodes:>9,d} nodes, {tree.nbytes / 2**20:8.2f} MiB "
            f"({8 * tree.nbytes / max(int(tree.voxel_count), 1):.1f} bits/voxel), built in {seconds:.2f} s")


def _render_dag(tree, mesh, path: str, width: int = 640, height: int = 480) -> None:
    """Traces primary rays through `tree`, reports the speed, writes depth | normal PNG."""
    import imageio.v3 as iio
    import jax

    import jaxvox as jv
    from jaxvox.plot import hit_image

    eye, target = jv.look_at_view(mesh)
    origins, directions = jv.pinhole_rays(eye, target, width=width, height=height)
    jax.block_until_ready(jv.trace(tree, origins, directions))  # compile
    start = time.perf_counter()
    hit = jax.block_until_ready(jv.trace(tree, origins, directions))
    seconds = time.perf_counter() - start
    hits = int((hit.status == jv.HIT).sum())
    print(f"  traced {width}x{height} primary rays through the DAG in {seconds:.3f} s "
          f"({width * height / seconds / 1e6:.2f} Mrays/s, {hits:,} hits)")
    gap = np.full((height, 8, 3), 255, np.uint8)
    iio.imwrite(path, np.concatenate([hit_image(hit, "depth"), gap, hit_image(hit, "normal")], axis=1))


def cmd_build(args) -> int:
    """Voxelizes a mesh, builds its octree or DAG and saves it with per-voxel attributes."""
    import jaxvox as jv

    mesh, name = _load(args.mesh)
    vox = jv.voxelize(mesh, jv.Grid.fit(mesh, resolution=args.resolution), triangle_ids=True)
    tree, seconds = _build_timed(vox, args.kind)
    attributes = jv.voxel_attributes(mesh, vox)
    jv.save(args.out, tree, attributes=attributes)
    print(f"{name}: {int(tree.voxel_count):,} voxels at {args.resolution}^3 -> " + _tree_line(tree, seconds))
    print(f"  nodes per level: {list(tree.level_sizes)}")
    print(f"wrote {args.out} (attributes: {', '.join(sorted(attributes))})")
    return 0


def cmd_run(args) -> int:
    """The main job: voxelize a mesh (default: the built-in scene) in both modes, build its
    octree and DAG, report, draw."""
    import jaxvox as jv
    from jaxvox.plot import save_projections

    mesh, name = _load(args.mesh)
    grid = jv.Grid.fit(mesh, resolution=args.resolution)
    os.makedirs(args.out, exist_ok=True)
    print(f"scene: {name}, {mesh.num_faces} triangles, {mesh.num_vertices} vertices")
    results = {}
    for mode in ("conservative", "6-separating"):
        _voxelize_timed(mesh, grid, mode)  # compile
        vox, seconds = _voxelize_timed(mesh, grid, mode)
        results[mode] = vox.to_numpy()
        print(f"  {mode:13s} {args.resolution}^3: {len(results[mode]):>9,d} voxels in {seconds:.3f} s "
              f"(after a warm-up call that compiles)")
    vox = jv.voxelize(mesh, grid, triangle_ids=True)
    attributes = jv.voxel_attributes(mesh, vox)
    trees = {}
    for kind in ("octree", "dag"):
        _build_timed(vox, kind)  # compile
        trees[kind], seconds = _build_timed(vox, kind)
        print(f"  {_tree_line(trees[kind], seconds)}")
    print(f"  octree/DAG nodes: {trees['octree'].num_nodes / trees['dag'].num_nodes:.1f}x")
    png = os.path.join(args.out, "voxels.png")
    save_projections(png, results, args.resolution)
    npz = os.path.join(args.out, "voxels.npz")
    _save_npz(npz, results["conservative"], grid, "conservative")
    jvx = os.path.join(args.out, "scene.jvx")
    jv.save(jvx, trees["dag"], attributes=attributes)
    render = os.path.join(args.out, "render.png")
    _render_dag(trees["dag"], mesh, render)
    print(f"  peak memory: {_peak_rss_mib():.0f} MiB")
    print(f"wrote {png} (rows: conservative, 6-separating; columns: views along x, y, z)")
    print(f"wrote {npz} (conservative voxel indices and the grid)")
    print(f"wrote {render} (the DAG traced from a pinhole camera: depth, entry-face normals)")
    print(f"wrote {jvx} (the DAG with per-voxel {', '.join(sorted(attributes))}; jaxvox.load / load_attributes)")
    return 0


def _enable_compilation_cache() -> None:
    """Keeps compiled XLA programs on disk so repeated commands skip recompiling.

    The folder is ``$JAXVOX_CACHE_DIR`` or ``~/.cache/jaxvox/xla``; set
    ``JAXVOX_CACHE_DIR=`` (empty) to turn the cache off.
    """
    import jax

    folder = os.environ.get("JAXVOX_CACHE_DIR", os.path.expanduser("~/.cache/jaxvox/xla"))
    if folder:
        jax.config.update("jax_compilation_cache_dir", folder)
        jax.config.update("jax_persistent_cache_min_compile_time_secs", 0.5)


def build_parser() -> argparse.ArgumentParser:
    """The argument parser of the ``jaxvox`` command."""
    parser = argparse.ArgumentParser(prog="jaxvox", description="Voxel geometry in JAX.")
    sub = parser.add_subparsers(dest="command", metavar="COMMAND")

    def command(name, func, help, resolution, out, out_help):
        """A subcommand taking an optional MESH, --resolution and --out."""
        p = sub.add_parser(name, help=help)
        p.add_argument("mesh", nargs="?", help="mesh file trimesh can read (default: the built-in scene)")
        p.add_argument("--resolution", type=int, default=resolution, help="voxels per axis, a power of two")
        p.add_argument("--out", default=out, help=out_help)
        p.set_defaults(func=func)
        return p

    command("run", cmd_run, "main job: voxelize the default scene (or MESH), build its octree and DAG, "
            "report, write a PNG and the DAG", 256, DEFAULT_OUT, "output folder (default: out)")
    vox = command("voxelize", cmd_voxelize, "voxelize a mesh to an .npz of voxel indices", 512, "voxels.npz",
                  "output .npz file")
    vox.add_argument("--mode", choices=["conservative", "6-separating"], default="conservative")
    build = command("build", cmd_build, "voxelize a mesh and save its DAG (or octree) with attributes", 512,
                    "tree.jvx", "output tree file")
    build.add_argument("--kind", choices=["dag", "octree"], default="dag")
    return parser


def main(argv: list[str] | None = None) -> int:
    """Entry point of the ``jaxvox`` console command; returns the exit status."""
    parser = build_parser()
    args = parser.parse_args(argv)
    if args.command is None:
        parser.print_help()
        return 0
    _enable_compilation_cache()
    from jaxvox._errors import JaxvoxError
    from jaxvox.grid import check_resolution

    try:
        check_resolution(args.resolution)
        return args.func(args)
    except (JaxvoxError, OSError) as exc:
        print(f"jaxvox: error: {exc}", file=sys.stderr)
        return 2
