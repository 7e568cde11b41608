"""A stream of many distinct meshes through the host API: what compilation costs a user.

The shape policy promises that a new mesh of a familiar size compiles nothing. This
measures it on a stream of 31 distinct meshes (1,000 to 120,000 triangles, in a fixed
random order):

* the 8 shared meshes and 8 randomly rotated and anisotropically scaled copies of them;
* 6 icospheres (1,280 to 81,920 faces) with random radial displacement;
* 5 tori (1,024 to 115,200 faces) of different section counts;
* 4 shared meshes subdivided once or twice (trimesh) to 23,000 to 101,000 faces.

For each resolution R, one fresh worker process warms up on one mesh that is not in the
stream (a torus), then runs the stream through the host API, per mesh: `jv.voxelize`
(conservative) on `jv.Grid.fit(mesh, R)`, `jv.build_dag`, and `jv.trace` of 256x256
primary rays of a pinhole camera framing the mesh. Recorded per mesh: the first call's
time (compilation included), the number of XLA compiles and their seconds
(`jax.monitoring` events "/jax/core/compile/backend_compile_duration"), and the
steady-state time (the same mesh again: median of 2 repeats). In the same worker, if
`import open3d` works, Open3D does the same work on the same stream:
`VoxelGrid.create_from_triangle_mesh_within_bounds` at the same voxel size and bounds,
and `RaycastingScene.cast_rays` of the same rays (scene build included; median of 2, or
one call when it takes over 10 s), in a helper process, so that a call running past
``--open3d-limit`` seconds (default 120) is stopped and counted at the limit: a lower
bound, marked ">=" in the table.

Outputs ``many_meshes.json`` (per-mesh numbers and the machine), ``.md`` (the table,
also printed) and ``.png`` (per resolution: cumulative time against meshes processed) in
``--out``.

Examples:
  python experiments/many_meshes.py                     # R = 128, 256, 512, 1024
  python experiments/many_meshes.py --smoke             # R = 32, 64 on 6 meshes
  python experiments/many_meshes.py --resolutions 256 --meshes 12
  python experiments/many_meshes.py --resolutions 256 --cache /tmp/xla --out /tmp/a   # twice: the
      # second run is a new session with a warm persistent cache
"""

from __future__ import annotations

import argparse
import json
import statistics
import sys
import time
from pathlib import Path

import _common
import numpy as np

COMPILE_EVENT = "/jax/core/compile/backend_compile_duration"
SHARED = ("suzanne", "woody", "beetle", "spot", "cow", "teapot", "fandisk", "stanford-bunny")


# --------------------------------------------------------------------------- the stream


def random_rotation(rng) -> np.ndarray:
    """A uniformly random 3x3 rotation (QR of a Gaussian matrix, signs fixed)."""
    q, r = np.linalg.qr(rng.normal(size=(3, 3)))
    q *= np.sign(np.diag(r))
    return q if np.linalg.det(q) > 0 else -q


def mesh_stream(mesh_dir: Path, count: int, seed: int = 0) -> list[tuple[str, np.ndarray, np.ndarray]]:
    """The first `count` meshes of the stream: (name, vertices [V, 3] float32, faces [F, 3] int32)."""
    import trimesh

    rng = np.random.default_rng(seed)
    shared = {}
    for name in SHARED:
        m = trimesh.load(mesh_dir / f"{name}.obj", force="mesh", process=False)
        shared[name] = (np.asarray(m.vertices, np.float64), np.asarray(m.faces, np.int64))
    items = [(name, *shared[name]) for name in SHARED]
    for name in SHARED:
        v, f = shared[name]
        v = (v - v.mean(0)) @ random_rotation(rng).T * rng.uniform(0.5, 1.5, 3)
        items.append((f"{name}-rotated", v, f))
    for subdivisions, k in ((3, 0), (4, 0), (4, 1), (5, 0), (5, 1), (6, 0)):
        sphere = trimesh.creation.icosphere(subdivisions=subdivisions)
        v = sphere.vertices * (1 + 0.15 * rng.standard_normal((len(sphere.vertices), 1)).clip(-2, 2))
        items.append((f"bumpy-sphere-{subdivisions}-{k}", v, sphere.faces))
    for major, minor in ((32, 16), (64, 32), (128, 64), (256, 96), (384, 150)):
        torus = trimesh.creation.torus(major_radius=1.0, minor_radius=0.3, major_sections=major, minor_sections=minor)
        items.append((f"torus-{major}x{minor}", torus.vertices, torus.faces))
    for name, times in (("spot", 1), ("cow", 1), ("fandisk", 1), ("teapot", 2)):
        v, f = shared[name]
        for _ in range(times):
            v, f = trimesh.remesh.subdivide(v, f)
        items.append((f"{name}-subdivided-{times}", v, f))
    order = rng.permutation(len(items))
    return [
        (items[i][0], np.asarray(items[i][1], np.float32), np.asarray(items[i][2], np.int32)) for i in order[:count]
    ]


# --------------------------------------------------------------------------- worker side


def open3d_call(o3d, vertices, faces, lo, h, resolution, rays):
    """Open3D's voxelization of a mesh within the grid's bounds and its ray casting of
    `rays` [n, 6] float32 (an `o3d.core.Tensor`): (voxels, hits)."""
    mesh = o3d.geometry.TriangleMesh(
        o3d.utility.Vector3dVector(vertices.astype(np.float64)), o3d.utility.Vector3iVector(faces)
    )
    voxels = o3d.geometry.VoxelGrid.create_from_triangle_mesh_within_bounds(mesh, h, lo, lo + resolution * h)
    scene = o3d.t.geometry.RaycastingScene()
    scene.add_triangles(vertices, faces.astype(np.uint32))
    t = scene.cast_rays(rays)["t_hit"].numpy()
    return len(voxels.get_voxels()), int(np.isfinite(t).sum())


def open3d_server(conn) -> None:
    """Runs in a helper process: times `open3d_call` on each request until it gets None."""
    import open3d as o3d

    while (request := conn.recv()) is not None:
        vertices, faces, lo, h, resolution, rays = request
        rays = o3d.core.Tensor(rays)
        start = time.perf_counter()
        result = open3d_call(o3d, vertices, faces, lo, h, resolution, rays)
        conn.send((time.perf_counter() - start, result))


class Open3D:
    """Open3D in a helper process, so that a call running past `limit` seconds can be
    stopped: its time is then reported as `limit`, a lower bound (Open3D's voxelizer takes
    over ten minutes on a bumpy sphere at 1024^3)."""

    def __init__(self, limit: float):
        import multiprocessing

        self.limit, self.context, self.process = limit, multiprocessing.get_context("spawn"), None

    def _start(self) -> None:
        self.conn, child = self.context.Pipe()
        self.process = self.context.Process(target=open3d_server, args=(child,), daemon=True)
        self.process.start()

    def __call__(self, *request) -> tuple[float, tuple | None]:
        """(seconds, (voxels, hits)), or (limit, None) when stopped at the limit."""
        if self.process is None:
            self._start()
        self.conn.send(request)
        if self.conn.poll(self.limit):
            return self.conn.recv()
        self.process.kill()
        self.process.join()
        self.process = None
        return self.limit, None

    def close(self) -> None:
        if self.process is not None:
            self.conn.send(None)
            self.process.join()


def worker(spec: dict) -> dict:
    """Runs the stream at one resolution: jaxvox (first pass and compiled) and Open3D.

    spec: mesh_dir, count, resolution, width, height, cache (a persistent compilation
    cache folder, or None for none: every program is compiled in this process).
    """
    import jax

    sys.path.insert(0, str(_common.REPO_ROOT))
    import jaxvox as jv

    if spec.get("cache"):
        jv.enable_compilation_cache(path=spec["cache"])

    compiles = []
    jax.monitoring.register_event_duration_secs_listener(
        lambda event, seconds, **kw: compiles.append(seconds) if event == COMPILE_EVENT else None
    )
    try:
        import open3d  # noqa: F401  (only checks that the helper process can import it)

        peer = Open3D(spec.get("open3d_limit", 120.0))
    except ImportError as exc:
        peer = None
        print(f"open3d not available ({exc}): jaxvox only", file=sys.stderr)
    resolution, width, height = spec["resolution"], spec["width"], spec["height"]

    def jaxvox_call(mesh, grid, o, d):
        vox = jv.voxelize(mesh, grid, progress=False)
        dag = jv.build_dag(vox)
        hit = jax.block_until_ready(jv.trace(dag, o, d))
        return int(vox.count), dag.num_nodes, int((np.asarray(hit.status) == jv.HIT).sum())

    def prepare(vertices, faces):
        mesh = jv.Mesh(vertices, faces)
        grid = jv.Grid.fit(mesh, resolution=resolution)
        o, d = jv.pinhole_rays(*jv.look_at_view(mesh), width=width, height=height)
        return mesh, grid, o, d

    import trimesh

    warm = trimesh.creation.torus(major_radius=1.0, minor_radius=0.4, major_sections=48, minor_sections=24)
    start = time.perf_counter()
    jaxvox_call(*prepare(np.asarray(warm.vertices, np.float32), np.asarray(warm.faces, np.int32)))
    warmup = dict(seconds=time.perf_counter() - start, compiles=len(compiles), compile_s=sum(compiles))

    rows = []
    for name, vertices, faces in _common.progress(
        mesh_stream(Path(spec["mesh_dir"]), spec["count"]), desc=f"R={resolution}"
    ):
        mesh, grid, o, d = prepare(vertices, faces)
        row = dict(mesh=name, faces=len(faces))
        n, start = len(compiles), time.perf_counter()
        row["voxels"], row["dag_nodes"], row["hits"] = jaxvox_call(mesh, grid, o, d)
        row["first_s"] = time.perf_counter() - start
        row["compiles"], row["compile_s"] = len(compiles) - n, sum(compiles[n:])
        steady = []
        for _ in range(2):
            start = time.perf_counter()
            jaxvox_call(mesh, grid, o, d)
            steady.append(time.perf_counter() - start)
        row["compiled_s"] = statistics.median(steady)
        if peer is not None:
            rays = np.concatenate([np.asarray(o), np.asarray(d)], -1).reshape(-1, 6).astype(np.float32)
            request = (vertices, faces, np.asarray(grid.origin, np.float64), float(grid.voxel_size), resolution, rays)
            times = []
            for _ in range(2):  # a median of 2, or 1 when a call takes over 10 s
                seconds, result = peer(*request)
                times.append(seconds)
                if result is None:
                    row["open3d_stopped"] = True
                    break
                row["open3d_voxels"], row["open3d_hits"] = result
                if seconds > 10:
                    break
            row["open3d_s"] = statistics.median(times)
        rows.append(row)
        print(
            f"R={resolution} {name} ({len(faces):,} faces): first {row['first_s']:.2f} s "
            f"({row['compiles']} compiles), compiled {row['compiled_s']:.3f} s"
            + (f", open3d {row['open3d_s']:.3f} s" if "open3d_s" in row else "")
            + (" (stopped at the limit)" if row.get("open3d_stopped") else ""),
            file=sys.stderr,
        )
    if peer is not None:
        peer.close()
    return dict(
        resolution=resolution,
        warmup=warmup,
        meshes=rows,
        backend=jax.default_backend(),
        device=jax.devices()[0].device_kind,
        open3d=peer is not None,
    )


# --------------------------------------------------------------------------- driver side


def summary_row(case: dict) -> dict:
    """One table row of a resolution's results (or its error)."""
    if "error" in case:
        return dict(resolution=case["resolution"], meshes=case["error"])
    rows = case["meshes"]
    first = sum(r["first_s"] for r in rows)
    compiled = sum(r["compiled_s"] for r in rows)
    compiles = sum(r["compiles"] for r in rows)
    out = dict(
        resolution=case["resolution"],
        meshes=len(rows),
        compiles=compiles,
        per_mesh=f"{compiles / len(rows):.2f}",
        compile_s=f"{sum(r['compile_s'] for r in rows):.2f}",
        first=f"{first:.2f}",
        compiled=f"{compiled:.2f}",
        ratio=f"{first / compiled:.2f}",
        warmup=f"{case['warmup']['seconds']:.1f} ({case['warmup']['compiles']})",
    )
    if case["open3d"]:
        stopped = any(r.get("open3d_stopped") for r in rows)
        out["open3d"] = (">= " if stopped else "") + f"{sum(r['open3d_s'] for r in rows):.2f}"
    return out


def table(cases: list[dict]) -> str:
    """The per-resolution summary as a markdown table (times in seconds)."""
    columns = [
        ("resolution", "R"),
        ("meshes", "meshes"),
        ("warmup", "warm-up s (compiles)"),
        ("compiles", "compiles after warm-up"),
        ("per_mesh", "compiles per mesh"),
        ("compile_s", "compile s"),
        ("first", "first pass s"),
        ("compiled", "compiled s"),
        ("ratio", "first / compiled"),
        ("open3d", "Open3D s"),
    ]
    return _common.markdown_table([summary_row(c) for c in cases], columns)


def plot(cases: list[dict], path: Path) -> None:
    """Per resolution: cumulative seconds against meshes processed."""
    done = [c for c in cases if "error" not in c]
    if not done:
        return
    fig, axes = _common.new_figure(len(done), width=4.5, height=3.8)
    for ax, case in zip(np.atleast_1d(axes), done):
        rows = case["meshes"]
        x = np.arange(1, len(rows) + 1)
        series = [("first_s", "jaxvox, first pass"), ("compiled_s", "jaxvox, compiled"), ("open3d_s", "Open3D")]
        for key, label in series:
            if all(key in r for r in rows):
                ax.plot(x, np.cumsum([r[key] for r in rows]), marker=".", label=label)
        ax.set(xlabel="meshes processed", ylabel="cumulative seconds", yscale="log", title=f"R = {case['resolution']}")
        ax.grid(True, alpha=0.3)
        ax.legend(fontsize="small")
    _common.save_figure(fig, path)


def parse_args(argv=None) -> argparse.Namespace:
    """Command-line options; see the module docstring."""
    parser = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    parser.add_argument("--resolutions", nargs="+", type=int, default=[128, 256, 512, 1024])
    parser.add_argument("--meshes", type=int, default=31, help="meshes of the stream to run (at most 31)")
    parser.add_argument("--mesh-dir", type=Path, default=_common.MESH_DIR)
    parser.add_argument("--image", type=int, nargs=2, default=[256, 256], metavar=("W", "H"))
    parser.add_argument("--timeout", type=float, default=4 * 3600, help="seconds before a resolution is abandoned")
    parser.add_argument("--out", type=Path, default=_common.RESULTS_DIR)
    parser.add_argument("--open3d-limit", type=float, default=120.0, help="seconds before an Open3D call is stopped")
    parser.add_argument(
        "--smoke", action="store_true", help="R = 32, 64 on 6 meshes; outputs are named many_meshes_smoke.*"
    )
    parser.add_argument(
        "--cache",
        help="persistent compilation cache folder for the workers (default: none, "
        "so first calls compile; run twice with a folder to measure a returning session)",
    )
    parser.add_argument(
        "--update",
        action="store_true",
        help="merge into the existing JSON: replace its resolutions that were run, keep the others",
    )
    parser.add_argument("--worker", help=argparse.SUPPRESS)
    args = parser.parse_args(argv)
    if args.smoke:
        args.resolutions, args.meshes = [32, 64], 6
    return args


def main(argv=None) -> None:
    """Runs one worker per resolution, then writes JSON, PNG and markdown."""
    args = parse_args(argv)
    if _common.answer_as_worker(args, worker):
        return
    cases = []
    for resolution in args.resolutions:
        spec = dict(
            mesh_dir=str(args.mesh_dir),
            count=args.meshes,
            resolution=resolution,
            width=args.image[0],
            height=args.image[1],
            cache=args.cache,
            open3d_limit=args.open3d_limit,
        )
        case = _common.run_worker(__file__, spec, timeout=args.timeout)
        cases.append(dict(case, resolution=resolution))
    stem = "many_meshes_smoke" if args.smoke else "many_meshes"
    if args.update and (args.out / f"{stem}.json").exists():
        kept = [
            c
            for c in json.loads((args.out / f"{stem}.json").read_text())["results"]
            if c["resolution"] not in args.resolutions
        ]
        cases = sorted(kept + cases, key=lambda c: c["resolution"])
    report = f"## Many meshes through the host API\n\n{table(cases)}"
    data = dict(
        machine=_common.machine_info(["jax", "jaxlib", "open3d", "trimesh", "numpy"]),
        settings=dict(resolutions=[c["resolution"] for c in cases], meshes=args.meshes, image=args.image),
        results=cases,
    )
    _common.write_json(args.out / f"{stem}.json", data)
    (args.out / f"{stem}.md").write_text(report)
    plot(cases, args.out / f"{stem}.png")
    print(report)


if __name__ == "__main__":
    main()
