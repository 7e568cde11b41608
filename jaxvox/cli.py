"""The ``jaxvox`` command line: ``run`` (the main job), ``render``, ``voxelize``, ``build``, ``info``.

Errors (missing file, unknown or bad option, bad resolution) print one line and exit
with status 2.
"""

from __future__ import annotations

import argparse
import os
import platform
import resource
import sys
import tempfile
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


def _voxelize_timed(mesh, grid, mode):
    import jaxvox as jv

    start = time.perf_counter()
    vox = jv.voxelize(mesh, grid, mode=mode)
    vox.coords.block_until_ready()
    return vox, time.perf_counter() - start


def cmd_voxelize(args) -> int:
    """Voxelizes a mesh and writes the voxels (.binvox, .npz, or their surface as .ply / .obj)."""
    import jaxvox as jv
    from jaxvox.io.voxels import check_save_path

    check_save_path("--out", args.out)  # before the work: an unknown extension or a missing folder
    mesh, name = _load(args.mesh)
    grid = jv.Grid.fit(mesh, resolution=args.resolution)
    vox, seconds = _voxelize_timed(mesh, grid, args.mode)
    jv.save_voxels(args.out, vox)
    print(
        f"{name}: {mesh.num_faces} triangles -> {int(vox.count)} voxels ({args.mode}, {args.resolution}^3) "
        f"in {seconds:.2f} s; wrote {args.out}"
    )
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
    return (
        f"{kind:6s} {tree.num_nodes:>9,d} nodes, {tree.compact_nbytes / 2**20:8.2f} MiB "
        f"({8 * tree.compact_nbytes / max(int(tree.voxel_count), 1):.1f} bits/voxel), built in {seconds:.2f} s"
    )


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
    print(
        f"  traced {width}x{height} primary rays through the DAG in {seconds:.3f} s "
        f"({width * height / seconds / 1e6:.2f} Mrays/s, {hits:,} hits)"
    )
    gap = np.full((height, 8, 3), 255, np.uint8)
    iio.imwrite(path, np.concatenate([hit_image(hit, "depth"), gap, hit_image(hit, "normal")], axis=1))


# Above this resolution `build` writes a DAG region by region (`mesh_to_dag`), so the
# whole voxel list is never held; the file is the same. `_STREAM_REGION`: the regions'
# edge (None: `mesh_to_dag`'s default, 1024, so below it there is one region).
_STREAM_ABOVE = 1024
_STREAM_REGION: int | None = None


def _streamed_dag_timed(mesh, grid, region: int | None, distributed: bool, folder: str):
    """`mesh_to_dag` with its per-voxel attributes spooled to `folder`; returns (tree,
    attributes as read-only memmaps, seconds of voxelization, build and attributes)."""
    import jax

    from jaxvox.octree.stream import dag_with_attributes

    quiet = distributed and jax.process_index() > 0  # one progress bar: process 0's
    start = time.perf_counter()
    tree, attributes = dag_with_attributes(
        mesh, grid, folder, region=region, progress=False if quiet else None, distributed=distributed, caller="build"
    )
    tree.mask.block_until_ready()
    return tree, attributes, time.perf_counter() - start


def _launch_processes(args) -> int:
    """Runs this `build` as `args.processes` local processes coordinated by
    `jax.distributed` (CPU collectives over gloo); process 0 writes the file and reports."""
    import socket
    import subprocess

    with socket.socket() as probe:  # a free port for the coordinator
        probe.bind(("127.0.0.1", 0))
        address = f"127.0.0.1:{probe.getsockname()[1]}"
    command = [sys.executable, "-m", "jaxvox", "build", *([args.mesh] if args.mesh else [])]
    command += ["--resolution", str(args.resolution), "--out", args.out, "--processes", str(args.processes)]
    command += ["--coordinator", address] + (["--region", str(args.region)] if args.region else [])
    workers = [
        subprocess.Popen(command + ["--process-id", str(k)], stdout=None if k == 0 else subprocess.DEVNULL)
        for k in range(args.processes)
    ]
    codes = [w.wait() for w in workers]
    return next((c for c in codes if c), 0)


def cmd_build(args) -> int:
    """Voxelizes a mesh, builds its octree or DAG and saves it with per-voxel attributes.

    DAGs above `_STREAM_ABOVE`^3, or with ``--region`` or ``--processes`` given, are built
    region by region (`mesh_to_dag`; the time reported then includes the voxelization);
    the file is the same. Their attributes go to files beside ``--out`` region by region,
    so they need not fit in memory. ``--processes N`` splits the regions over N local
    processes (`jax.distributed`; the attributes are then gathered in memory); process 0
    writes the file.
    """
    import jaxvox as jv
    from jaxvox._core.checks import check_int, check_output_path, refuse

    check_output_path("--out", args.out)  # before the work
    processes = check_int("--processes", args.processes, minimum=1)
    streamed = args.resolution > _STREAM_ABOVE or args.region is not None or processes > 1
    if processes > 1 and args.kind != "dag":
        raise refuse("--processes", "splits the DAG build only (--kind dag)", processes)
    if processes > 1 and args.process_id is None:
        return _launch_processes(args)
    if args.process_id is not None:
        import jax

        jax.config.update("jax_cpu_collectives_implementation", "gloo")
        jax.distributed.initialize(args.coordinator, num_processes=processes, process_id=args.process_id)
    mesh, name = _load(args.mesh)
    grid = jv.Grid.fit(mesh, resolution=args.resolution)
    with tempfile.TemporaryDirectory(prefix=".jaxvox-attributes-", dir=os.path.dirname(args.out) or ".") as folder:
        if args.kind == "dag" and streamed:
            region = _STREAM_REGION if args.region is None else args.region
            tree, attributes, seconds = _streamed_dag_timed(mesh, grid, region, processes > 1, folder)
        else:
            vox = jv.voxelize(mesh, grid, triangle_ids=True)
            tree, seconds = _build_timed(vox, args.kind)
            attributes = jv.voxel_attributes(mesh, vox)
        if args.process_id:  # not process 0
            return 0
        jv.save(args.out, tree, attributes=attributes)
        names = sorted(attributes)
        del attributes  # the memmaps, before their folder goes
    print(f"{name}: {int(tree.voxel_count):,} voxels at {args.resolution}^3 -> " + _tree_line(tree, seconds))
    if processes > 1:
        print(f"  built by {processes} processes (jax.distributed)")
    print(f"  nodes per level: {list(tree.level_sizes)}")
    print(f"wrote {args.out} (attributes: {', '.join(names)})")
    return 0


def cmd_run(args) -> int:
    """The main job: voxelize a mesh (default: the built-in scene) in both modes, build its
    octree and DAG, report, draw."""
    import jaxvox as jv
    from jaxvox._core.checks import refuse
    from jaxvox.plot import save_projections

    mesh, name = _load(args.mesh)
    grid = jv.Grid.fit(mesh, resolution=args.resolution)
    try:
        os.makedirs(args.out, exist_ok=True)
    except OSError as exc:
        raise refuse("--out", f"cannot create the folder ({exc.strerror or exc})", args.out) from None
    print(f"scene: {name}, {mesh.num_faces} triangles, {mesh.num_vertices} vertices")
    results = {}
    for mode in ("conservative", "6-separating"):
        _voxelize_timed(mesh, grid, mode)  # compile
        vox, seconds = _voxelize_timed(mesh, grid, mode)
        results[mode] = vox.to_numpy()
        print(
            f"  {mode:13s} {args.resolution}^3: {len(results[mode]):>9,d} voxels in {seconds:.3f} s "
            f"(after a warm-up call that compiles)"
        )
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
    jv.save_voxels(npz, vox)  # the conservative voxels
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


def _numbers(text: str, name: str, counts: tuple[int, ...]) -> list[float]:
    """Comma-separated floats, as many as one of `counts`; a `JaxvoxError` otherwise."""
    from jaxvox._core.checks import refuse

    try:
        values = [float(x) for x in text.split(",")]
    except ValueError:
        values = []
    if len(values) not in counts or not np.isfinite(values).all():
        raise refuse(f"--{name}", f"takes {' or '.join(map(str, counts))} comma-separated finite numbers", text)
    return values


def _size(text: str) -> tuple[int, int]:
    """``WIDTHxHEIGHT`` -> (width, height)."""
    from jaxvox._core.checks import refuse

    parts = text.lower().split("x")
    if len(parts) != 2 or not all(p.isdigit() and int(p) > 0 for p in parts):
        raise refuse("--size", "takes WIDTHxHEIGHT in pixels (e.g. 640x360)", text)
    return int(parts[0]), int(parts[1])


def _environment(spec: str):
    """``sky``, ``white``, ``black``, ``uniform:R,G,B`` or an .exr / .npy lat-long file."""
    import jaxvox as jv

    if spec == "sky":
        return jv.sky_environment()
    if spec in ("white", "black"):
        return jv.uniform_environment(rgb=1.0 if spec == "white" else 0.0)
    if spec.startswith("uniform:"):
        return jv.uniform_environment(rgb=_numbers(spec[len("uniform:") :], "env uniform:", (1, 3)))
    return jv.load_environment(spec)


def _upright_default_scene():
    """The default scene, modelled with +z up, turned so that +y is up as the renderer's sky."""
    import jaxvox as jv

    mesh = jv.default_scene()
    v = np.asarray(mesh.vertices)
    return jv.Mesh(np.stack([v[:, 0], v[:, 2], -v[:, 1]], axis=1), mesh.faces, colors=mesh.colors)


def _render_scene(args):
    """(tree, albedo, emission, normals, bounds, name) for `render`: a .jvx tree file, a mesh,
    or the default scene; normals are the per-voxel ones where they exist and are wanted."""
    import jaxvox as jv

    if args.mesh is not None and args.mesh.endswith(".jvx"):
        tree, attributes = jv.load(args.mesh), jv.load_attributes(args.mesh)
        g = tree.grid
        lo = np.asarray(g.origin)
        bounds = (lo, lo + g.resolution * float(g.voxel_size))
        name = os.path.basename(args.mesh)
        vox = jv.expand(tree) if args.emit else None
        print(f"{name}: {int(tree.voxel_count):,} voxels at {g.resolution}^3, {tree.num_nodes:,} nodes")
    else:
        mesh, name = (_upright_default_scene(), "default scene") if args.mesh is None else _load(args.mesh)
        start = time.perf_counter()
        grid = jv.Grid.fit(mesh, resolution=args.resolution)
        if args.voxels == "solid-boundary":
            vox = jv.solid_boundary(mesh, grid, triangle_ids=True)
        else:
            vox = jv.voxelize(mesh, grid, mode=args.voxels, triangle_ids=True)
        tree = jv.build_dag(vox)
        attributes = jv.voxel_attributes(mesh, vox)
        tree.mask.block_until_ready()
        bounds = tuple(np.asarray(b) for b in (mesh.vertices.min(0), mesh.vertices.max(0)))
        print(
            f"{name}: {mesh.num_faces:,} triangles -> {int(tree.voxel_count):,} {args.voxels} voxels at "
            f"{args.resolution}^3, "
            f"DAG of {tree.num_nodes:,} nodes, in {time.perf_counter() - start:.1f} s"
        )
    material = _numbers(args.albedo, "albedo", (1, 3))
    albedo = jv.voxel_albedo(attributes, default=np.broadcast_to(material, 3))
    emission = None
    for lo, hi, rgb in map(_emitter, args.emit or ()):
        box = jv.box_emission(vox, lo, hi, rgb)
        emission = box if emission is None else emission + box
    normals = None if args.face_normals else attributes.get("normal")
    return tree, albedo, emission, normals, bounds, name


def _emitter(text: str):
    """``XMIN,YMIN,ZMIN,XMAX,YMAX,ZMAX:R,G,B`` -> (lo, hi, rgb)."""
    from jaxvox._core.checks import refuse

    box, _, rgb = text.partition(":")
    if not rgb:
        raise refuse("--emit", "takes XMIN,YMIN,ZMIN,XMAX,YMAX,ZMAX:R,G,B", text)
    corners = _numbers(box, "emit box", (6,))
    colour = _numbers(rgb, "emit colour", (1, 3))
    if min(colour) < 0:
        raise refuse("--emit radiance", "must be non-negative", rgb)
    return corners[:3], corners[3:], np.broadcast_to(colour, 3)


def cmd_render(args) -> int:
    """Path-traces a mesh (voxelized into a DAG), a saved tree, or the default scene; writes EXR + PNG."""
    import jaxvox as jv
    from jaxvox._core.checks import check_choice, check_int, check_number, refuse
    from jaxvox.camera import check_view

    # Every option is checked before the scene is voxelized.
    check_choice("--out extension", os.path.splitext(args.out)[1].lower(), (".exr",))  # the PNG goes beside it
    width, height = _size(args.size)
    for name, low in (("spp", 1), ("bounces", 0), ("batch_rays", 1)):
        check_int(f"--{name.replace('_', '-')}", getattr(args, name), minimum=low)
    check_number("--exposure", args.exposure)
    if not all(0.0 <= a <= 1.0 for a in _numbers(args.albedo, "albedo", (1, 3))):
        raise refuse("--albedo", "a reflectance must lie in [0, 1]", args.albedo)
    camera = _numbers(args.camera, "camera", (2, 3, 6)) if args.camera else [35.0, 25.0]
    if len(camera) == 6:
        check_view("--camera", camera[:3], camera[3:], (0.0, 1.0, 0.0), args.fov)
    check_number("--fov", args.fov, above=0.0, below=180.0)
    _numbers(args.albedo, "albedo", (1, 3))
    for text in args.emit or ():
        _emitter(text)
    env = _environment(args.env)
    tree, albedo, emission, normals, bounds, name = _render_scene(args)
    if len(camera) == 6:
        eye, target = camera[:3], camera[3:]
    else:
        eye, target = jv.look_at_view(
            bounds, azimuth=camera[0], elevation=camera[1], **({"distance": camera[2]} if len(camera) == 3 else {})
        )
    settings = dict(
        env=env,
        albedo=albedo,
        emission=emission,
        normals=normals,
        width=width,
        height=height,
        fov=args.fov,
        spp=args.spp,
        bounces=args.bounces,
        key=args.seed,
        batch_rays=args.batch_rays,
    )
    start = time.perf_counter()
    result = jv.render(tree, eye, target, **settings)
    result.radiance.block_until_ready()
    seconds = time.perf_counter() - start
    out_dir = os.path.dirname(os.path.abspath(args.out))
    os.makedirs(out_dir, exist_ok=True)
    exr, png = jv.save_render(args.out, result, exposure=args.exposure)
    samples = width * height * args.spp
    print(
        f"  rendered {width}x{height} at {args.spp} spp, {args.bounces} bounces, env {args.env}, seed {args.seed}, "
        f"{'face' if normals is None else 'per-voxel'} normals "
        f"in {seconds:.1f} s including compilation ({samples / seconds / 1e6:.3f} Msamples/s)"
    )
    if int(result.stopped):
        print(
            f"  note: {int(result.stopped)} of {samples:,} paths ({100 * int(result.stopped) / samples:.4f}%) ended "
            "before their last bounce (a ray reached the traversal's step cap, or started inside a voxel); "
            "each keeps the light it gathered, so its pixel is at most that fraction darker"
        )
    print(f"  peak memory: {_peak_rss_mib():.0f} MiB")
    print(
        f"wrote {exr} (linear HDR: R, G, B; depth Z, +inf where a pixel sees no surface; coverage A; "
        "normal N.X N.Y N.Z)"
    )
    print(f"wrote {png} (tone-mapped sRGB)")
    return 0


MESH_SUFFIXES = (".obj", ".ply", ".off", ".stl", ".glb", ".gltf")


def cmd_sample(args) -> int:
    """Writes `jaxvox.sample_sdf` samples of each mesh to ``--out``; exit status 1 when a
    mesh was skipped (the others are written)."""
    from jaxvox.points.sample import sample_meshes

    paths = []
    for item in args.meshes:
        if os.path.isdir(item):
            paths += sorted(os.path.join(item, f) for f in os.listdir(item) if f.lower().endswith(MESH_SUFFIXES))
        else:
            paths.append(item)
    near = (1.0 - args.uniform) / 2
    report = sample_meshes(
        paths, args.out, n=args.samples, seed=args.seed, fractions=(near, near, args.uniform), sigmas=tuple(args.sigmas)
    )
    errors = sum(status.startswith("error") for status in report.values())
    done = sum(status == "done" for status in report.values())
    print(f"{len(report) - errors - done} written, {done} done before, {errors} skipped: {args.out}")
    return 1 if errors else 0


def cmd_info(args) -> int:
    """Prints the levels, nodes, bytes and bits per voxel of a saved tree file."""
    import jaxvox as jv

    tree = jv.load(args.file)
    attributes = jv.load_attributes(args.file)
    voxels = int(tree.voxel_count)
    g = tree.grid
    print(f"{args.file}: {'DAG' if tree.dag else 'octree'} ({tree.mode} voxels)")
    print(
        f"  grid: {g.resolution}^3, voxel size {float(g.voxel_size):.6g}, origin "
        f"{', '.join(f'{x:.6g}' for x in np.asarray(g.origin))}"
    )
    print(f"  levels: {tree.depth}, nodes per level: {list(tree.level_sizes)}")
    print(f"  nodes: {tree.num_nodes:,}, voxels: {voxels:,}")
    print(
        f"  bytes: {tree.compact_nbytes:,} ({tree.compact_nbytes / 2**20:.2f} MiB), "
        f"{8 * tree.compact_nbytes / max(voxels, 1):.2f} bits per voxel"
    )
    names = ", ".join(f"{k} {tuple(v.shape)} {v.dtype}" for k, v in sorted(attributes.items()))
    print(f"  attributes: {names or 'none'}")
    return 0


class _Parser(argparse.ArgumentParser):
    """An argument parser whose errors are one line (no usage block), exit status 2."""

    def error(self, message):
        """Prints ``jaxvox: error: message`` and exits with status 2."""
        self.exit(2, f"jaxvox: error: {message} (see jaxvox --help)\n")


def build_parser() -> argparse.ArgumentParser:
    """The argument parser of the ``jaxvox`` command."""
    parser = _Parser(prog="jaxvox", description="Voxel geometry in JAX.")
    sub = parser.add_subparsers(dest="command", metavar="COMMAND")

    def command(name, func, help, resolution, out, out_help):
        """A subcommand taking an optional MESH, --resolution and --out."""
        p = sub.add_parser(name, help=help)
        p.add_argument("mesh", nargs="?", help="mesh file trimesh can read (default: the built-in scene)")
        p.add_argument("--resolution", type=int, default=resolution, help="voxels per axis, a power of two")
        p.add_argument("--out", default=out, help=out_help)
        p.set_defaults(func=func)
        return p

    command(
        "run",
        cmd_run,
        "main job: voxelize the default scene (or MESH), build its octree and DAG, report, write a PNG and the DAG",
        256,
        DEFAULT_OUT,
        "output folder (default: out)",
    )
    vox = command(
        "voxelize",
        cmd_voxelize,
        "voxelize a mesh to a voxel file",
        512,
        "voxels.npz",
        "output file: .binvox, .npz (voxel indices and the grid), or the voxels' surface as "
        ".ply / .obj (default: voxels.npz)",
    )
    vox.add_argument("--mode", choices=["conservative", "6-separating"], default="conservative")
    build = command(
        "build",
        cmd_build,
        "voxelize a mesh and save its DAG (or octree) with attributes",
        512,
        "tree.jvx",
        "output tree file",
    )
    build.add_argument("--kind", choices=["dag", "octree"], default="dag")
    build.add_argument(
        "--region",
        type=int,
        default=None,
        help="build the DAG region by region with regions of this edge, a power of two up to 1024 "
        "(default: 1024 regions above 1024^3, one pass below)",
    )
    build.add_argument(
        "--processes",
        type=int,
        default=1,
        help="split the regions over this many local processes coordinated by jax.distributed (default 1)",
    )
    build.add_argument("--process-id", type=int, default=None, help=argparse.SUPPRESS)
    build.add_argument("--coordinator", default=None, help=argparse.SUPPRESS)
    render = command(
        "render",
        cmd_render,
        "path-trace the default scene (or MESH, or a .jvx tree file) to an EXR and a PNG",
        256,
        "render.exr",
        "output .exr file; the PNG is written beside it",
    )
    render.add_argument("--size", default="640x360", help="image WIDTHxHEIGHT in pixels (default 640x360)")
    render.add_argument("--spp", type=int, default=16, help="samples per pixel (default 16)")
    render.add_argument("--bounces", type=int, default=8, help="diffuse bounces (default 8)")
    render.add_argument(
        "--env",
        default="sky",
        help="lighting: sky (procedural, with a sun), white, black, uniform:R,G,B, or a lat-long .exr/.npy file",
    )
    render.add_argument(
        "--camera",
        default=None,
        help="AZIMUTH,ELEVATION[,DISTANCE] in degrees around the scene "
        "(default 35,25), or EYE_X,EYE_Y,EYE_Z,TARGET_X,TARGET_Y,TARGET_Z",
    )
    render.add_argument("--fov", type=float, default=40.0, help="vertical field of view in degrees")
    render.add_argument("--albedo", default="0.7", help="material colour where the mesh has no vertex colours")
    render.add_argument(
        "--emit",
        action="append",
        metavar="XMIN,YMIN,ZMIN,XMAX,YMAX,ZMAX:R,G,B",
        help="voxels whose centres lie in this world box emit this linear radiance "
        "(repeatable; write --emit=-1,... when the box starts with a minus sign)",
    )
    render.add_argument(
        "--face-normals",
        action="store_true",
        help="shade with the normal of the voxel face a ray enters, not the per-voxel normals of the mesh (the default "
        "where they exist: a mesh, or a .jvx file saved with them)",
    )
    render.add_argument(
        "--voxels",
        choices=["conservative", "6-separating", "solid-boundary"],
        default="conservative",
        help="which voxels of a mesh: voxelize's modes, or solid-boundary (jaxvox.solid_boundary: voxels whose centres "
        "are inside, exposed to the outside; the images closest to the mesh's, most of all at low resolutions, "
        "and a slower build)",
    )
    render.add_argument("--seed", type=int, default=0)
    render.add_argument("--exposure", type=float, default=0.0, help="PNG exposure in stops")
    render.add_argument("--batch-rays", type=int, default=1 << 18, help="paths traced per batch (memory)")
    sample = sub.add_parser(
        "sample",
        help="signed-distance training samples of mesh files: one .npz each in --out (resumable; bad meshes skipped)",
    )
    sample.add_argument("meshes", nargs="+", help="mesh files, or folders (their .obj .ply .off .stl .glb files)")
    sample.add_argument("--out", required=True, help="output folder")
    sample.add_argument("--samples", type=int, default=250_000, help="samples per mesh (default 250000)")
    sample.add_argument("--seed", type=int, default=0, help="base seed (each mesh mixes in its file name)")
    sample.add_argument("--uniform", type=float, default=0.2, help="share of points uniform in the padded box")
    sample.add_argument(
        "--sigmas", type=float, nargs=2, default=(0.005, 0.05), help="near-surface offsets, fractions of the diagonal"
    )
    sample.set_defaults(func=cmd_sample)
    info = sub.add_parser("info", help="levels, nodes, bytes and bits per voxel of a saved tree file")
    info.add_argument("file", help="a .jvx file written by jaxvox build or run")
    info.set_defaults(func=cmd_info)
    return parser


def use_every_core() -> None:
    """One JAX CPU device per core (`jax_num_cpu_devices`), so that `trace` shards its rays
    over all of them; a no-op once JAX has started its backend (e.g. the CLI called from a
    Python session) or when ``JAX_NUM_CPU_DEVICES`` is set. A library user adds the same
    line right after ``import jax``:
    ``jax.config.update("jax_num_cpu_devices", os.cpu_count())``."""
    import jax

    if "JAX_NUM_CPU_DEVICES" in os.environ:
        return
    try:
        jax.config.update("jax_num_cpu_devices", os.cpu_count() or 1)
    except RuntimeError:  # the backend is already running
        pass


HUGE_PAGES = "glibc.malloc.hugetlb=1"


def ask_for_huge_pages() -> None:
    """Runs this process again (same command line) with glibc's malloc asking the kernel
    for transparent huge pages for its large blocks (``GLIBC_TUNABLES`` holding
    `HUGE_PAGES`, glibc 2.35 and later). XLA's CPU runtime allocates a fresh temporary
    buffer of tens of MiB for every run of a large program, and the kernel fills it in
    4 KiB pages on first touch, one page fault per page; huge pages take a few hundred
    times fewer faults. A no-op once the tunable is set or off glibc; a
    library user starts Python with ``GLIBC_TUNABLES=glibc.malloc.hugetlb=1``."""
    tunables = os.environ.get("GLIBC_TUNABLES", "")
    if HUGE_PAGES in tunables or platform.libc_ver()[0] != "glibc":
        return
    env = dict(os.environ, GLIBC_TUNABLES=":".join(filter(None, [tunables, HUGE_PAGES])))
    sys.stdout.flush()
    sys.stderr.flush()
    os.execve(sys.executable, [sys.executable, *sys.orig_argv[1:]], env)


def main(argv: list[str] | None = None) -> int:
    """Entry point of the ``jaxvox`` console command; returns the exit status. Called with
    no `argv` (as the command), it first runs itself again with huge pages
    (`ask_for_huge_pages`)."""
    if argv is None:
        ask_for_huge_pages()
    parser = build_parser()
    args = parser.parse_args(argv)
    if args.command is None:
        parser.print_help()
        return 0
    from jaxvox._core.compilation_cache import enable_compilation_cache
    from jaxvox._core.errors import JaxvoxError
    from jaxvox.grid import check_resolution

    try:
        use_every_core()
        enable_compilation_cache()  # $JAXVOX_CACHE_DIR, ~/.cache/jaxvox/xla by default
        if getattr(args, "resolution", None) is not None:
            check_resolution(args.resolution)
        return args.func(args)
    except (JaxvoxError, OSError) as exc:
        print(f"jaxvox: error: {exc}", file=sys.stderr)
        return 2
