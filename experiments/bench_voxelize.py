"""Surface voxelization benchmark: jaxvox against Open3D and trimesh.

For each mesh and resolution R this measures, in the same run:

* jaxvox, ``conservative`` (every voxel the surface touches; the exact reference set)
  and ``6-separating`` modes: `jv.voxelize` on the grid `jv.Grid.fit(mesh, resolution=R)`.
  The first call includes compilation; it is reported separately as ``compile_s``.
* Open3D, `VoxelGrid.create_from_triangle_mesh_within_bounds` on the same grid.
* trimesh, `Trimesh.voxelized(pitch)` (subdivide the mesh, then mark the voxel holding
  each vertex), with the mesh shifted so that trimesh's voxels coincide with ours.

Each (method, mesh, resolution) runs in a fresh subprocess: one warm-up call, then the
median of ``--repeats`` timed calls. Peak memory is that process's resident-set
high-water mark (``ru_maxrss``) read right after the timed calls, so it includes the
libraries' import footprint (also reported, as ``rss_before_mib``) and, for jaxvox,
the compiler. Voxel sets are compared against jaxvox's conservative set as sorted int64
linear indices ``(i * R + j) * R + k``: a false positive is a reported voxel the surface
does not touch, a false negative a touched voxel that was missed.

Index conventions of the peers (checked on single triangles against a float64 SAT test):

* Open3D's ``grid_index`` (i, j, k) is the voxel ``[min_bound + (i, j, k) h, min_bound +
  (i+1, j+1, k+1) h]``, the same as ours. ``max_bound`` is *not* used to clip: a mesh
  that touches the top faces of the box yields indices equal to R; those are dropped here
  and counted in ``outside``.
* trimesh rounds positions to the nearest multiple of the pitch, so its voxels are
  *centred* on ``n * pitch`` in world coordinates, whatever our grid origin is. Voxelizing
  the mesh translated by ``-(origin + h/2)`` puts trimesh's voxel n exactly on our voxel n.

Outputs ``bench_voxelize.json`` (all raw numbers and the machine), ``.png`` (time against
resolution and the peers' error rates) and ``.md`` (the table, also printed) in ``--out``.

Examples:
  python experiments/bench_voxelize.py                  # full sweep
  python experiments/bench_voxelize.py --smoke          # R = 64, 128 (a minute or two)
  python experiments/bench_voxelize.py --methods open3d trimesh --resolutions 64
  python experiments/bench_voxelize.py --resolutions --huge 8192   # only the 8192^3 case
"""

from __future__ import annotations

import argparse
import sys
import tempfile
from pathlib import Path

import _common
import numpy as np

METHODS = ("jaxvox-conservative", "jaxvox-6-separating", "open3d", "trimesh")
REFERENCE = "jaxvox-conservative"
PEERS = ("open3d", "trimesh")
DEFAULT_MESHES = ("stanford-bunny", "spot")
# trimesh subdivides the whole mesh below half a voxel: on the bunny at R=512 that is
# about 50 s and 6 GiB per call, and four times both per doubling of R.
DEFAULT_MAX_RESOLUTION = {"trimesh": 512}


# --------------------------------------------------------------------------- worker side


def linear_indices(ijk: np.ndarray, resolution: int) -> tuple[np.ndarray, int]:
    """Voxel indices [N, 3] -> (sorted unique int64 linear indices inside the grid, number outside)."""
    ijk = np.asarray(ijk, np.int64).reshape(-1, 3)
    inside = ((ijk >= 0) & (ijk < resolution)).all(axis=1)
    i, j, k = ijk[inside].T
    return np.unique((i * resolution + j) * resolution + k), int((~inside).sum())


def load_peer_mesh(path: str) -> tuple[np.ndarray, np.ndarray]:
    """Vertices [V, 3] float64 and faces [F, 3] int32 exactly as `jv.load_mesh` reads them.

    jaxvox stores float32 vertices; rounding them the same way keeps a voxel-plane tie
    from counting as a disagreement.
    """
    import trimesh

    mesh = trimesh.load(path, force="mesh", process=False)
    vertices = np.asarray(mesh.vertices, np.float32).astype(np.float64)
    return vertices, np.asarray(mesh.faces, np.int32)


def prepare_jaxvox(spec: dict):
    """jaxvox in the mode named by the method; returns (call, to_ijk, extra info)."""
    import jax

    import jaxvox as jv

    mode = spec["method"].removeprefix("jaxvox-")
    mesh = jv.load_mesh(spec["path"])
    grid = jv.Grid.fit(mesh, resolution=spec["resolution"])

    def call():
        return jax.block_until_ready(jv.voxelize(mesh, grid, mode=mode, progress=False))

    device = jax.devices()[0]
    info = dict(
        grid=dict(origin=np.asarray(grid.origin, np.float64).tolist(), voxel_size=float(grid.voxel_size)),
        backend=jax.default_backend(),
        device=device.device_kind,
    )
    return call, lambda vox: vox.to_numpy(), info


def prepare_open3d(spec: dict):
    """Open3D on the given grid; returns (call, to_ijk, extra info)."""
    import open3d as o3d

    vertices, faces = load_peer_mesh(spec["path"])
    mesh = o3d.geometry.TriangleMesh(o3d.utility.Vector3dVector(vertices), o3d.utility.Vector3iVector(faces))
    origin = np.asarray(spec["grid"]["origin"])
    h = spec["grid"]["voxel_size"]
    max_bound = origin + spec["resolution"] * h
    create = o3d.geometry.VoxelGrid.create_from_triangle_mesh_within_bounds

    def to_ijk(voxel_grid):
        return np.array([v.grid_index for v in voxel_grid.get_voxels()], np.int64)

    return lambda: create(mesh, h, origin, max_bound), to_ijk, {}


def prepare_trimesh(spec: dict):
    """trimesh on a mesh shifted so that its voxels are ours; returns (call, to_ijk, extra info)."""
    import trimesh

    vertices, faces = load_peer_mesh(spec["path"])
    origin = np.asarray(spec["grid"]["origin"])
    h = spec["grid"]["voxel_size"]
    shift = origin + h / 2  # trimesh centres voxel n on n * pitch
    mesh = trimesh.Trimesh(vertices - shift, faces, process=False)

    def to_ijk(voxel_grid):
        return np.floor((voxel_grid.points + shift - origin) / h)

    return lambda: mesh.voxelized(h), to_ijk, {}


PREPARE = {
    "jaxvox-conservative": prepare_jaxvox,
    "jaxvox-6-separating": prepare_jaxvox,
    "open3d": prepare_open3d,
    "trimesh": prepare_trimesh,
}


def device_peak_bytes() -> int | None:
    """Peak accelerator memory in bytes when JAX is loaded and reports it (GPU), else None."""
    if "jax" not in sys.modules:
        return None
    stats = sys.modules["jax"].devices()[0].memory_stats() or {}
    return stats.get("peak_bytes_in_use")


def worker(spec: dict) -> dict:
    """Measures one (method, mesh, resolution) case; writes the voxel set to spec["save"] if given.

    spec: method, path, resolution, repeats, grid (peers only: origin, voxel_size) and
    save (a .npy path for the sorted linear indices, or None to skip the conversion).
    """
    call, to_ijk, info = PREPARE[spec["method"]](spec)
    rss_before = _common.peak_rss_mib()
    timing, result = _common.time_calls(call, spec["repeats"])
    rss_peak = _common.peak_rss_mib()
    out = dict(timing, rss_before_mib=rss_before, rss_peak_mib=rss_peak, device_peak_bytes=device_peak_bytes(), **info)
    if spec["method"].startswith("jaxvox"):
        out["count"] = int(result.count)
    if spec["save"]:
        indices, out["outside"] = linear_indices(to_ijk(result), spec["resolution"])
        np.save(spec["save"], indices)
        out["set_size"] = len(indices)  # distinct voxels inside the grid
        out.setdefault("count", len(indices))
    return out


# --------------------------------------------------------------------------- driver side


def bounding_cube_grid(path: Path, resolution: int, padding: float = 0.01) -> dict:
    """The placement `jv.Grid.fit` uses (a padded cube centred on the bounding box).

    Only used when jaxvox is not among the methods, e.g. to try the peers on their own;
    otherwise the peers get the grid that the jaxvox worker reports.
    """
    vertices, _ = load_peer_mesh(str(path))
    lo, hi = vertices.min(0), vertices.max(0)
    extent = (hi - lo).max() * (1 + 2 * padding)
    h = float(np.float32(extent / resolution))
    origin = ((lo + hi) / 2 - extent / 2).astype(np.float32).astype(np.float64)
    return dict(origin=origin.tolist(), voxel_size=h)


def compare(indices: np.ndarray, exact: np.ndarray) -> dict:
    """False positives and negatives of a sorted voxel set against the exact conservative set."""
    fp = len(np.setdiff1d(indices, exact, assume_unique=True))
    fn = len(np.setdiff1d(exact, indices, assume_unique=True))
    return dict(false_positives=fp, false_negatives=fn, error_rate=(fp + fn) / max(len(exact), 1))


def run_case(mesh: str, resolution: int, methods: list[str], args, tmp: Path) -> list[dict]:
    """Runs every method on one mesh and resolution; returns one row per method."""
    path = args.mesh_dir / f"{mesh}.obj"
    grid = None if REFERENCE in methods else bounding_cube_grid(path, resolution)
    rows, exact = [], None
    for method in methods:
        row = dict(mesh=mesh, resolution=resolution, method=method)
        if resolution > args.max_resolution.get(method, resolution):
            rows.append(dict(row, skipped=f"R > {args.max_resolution[method]}"))
            continue
        save = tmp / f"{method}.npy"
        spec = dict(
            method=method, path=str(path), resolution=resolution, repeats=args.repeats, grid=grid, save=str(save)
        )
        row.update(_common.run_worker(__file__, spec, timeout=args.timeout))
        if "error" not in row:
            grid = grid or row.get("grid")
            indices = np.load(save)
            if method == REFERENCE:
                exact = indices
            elif exact is not None:
                row.update(compare(indices, exact))
        rows.append(row)
        print(f"{mesh} R={resolution} {method}: {summary(row)}", file=sys.stderr)
    return rows


def run_huge(resolution: int, args) -> dict:
    """jaxvox conservative on the bunny at a resolution too large for the peers (one repeat)."""
    spec = dict(
        method=REFERENCE,
        path=str(args.mesh_dir / "stanford-bunny.obj"),
        resolution=resolution,
        repeats=1,
        grid=None,
        save=None,
    )
    row = dict(mesh="stanford-bunny", resolution=resolution, method=REFERENCE)
    row.update(_common.run_worker(__file__, spec, timeout=args.timeout))
    print(f"stanford-bunny R={resolution} {REFERENCE}: {summary(row)}", file=sys.stderr)
    return row


def summary(row: dict) -> str:
    """One line about a result row for the log."""
    if "error" in row or "skipped" in row:
        return row.get("error") or f"skipped ({row['skipped']})"
    text = (
        f"{row['median_s']:.3g} s (first call {row['first_s']:.3g} s), "
        f"peak RSS {row['rss_peak_mib']:.0f} MiB, {row['count']} voxels"
    )
    if "error_rate" in row:
        text += f", FP {row['false_positives']}, FN {row['false_negatives']}"
    return text


def table(rows: list[dict]) -> str:
    """The results as a markdown table (times in seconds, memory in MiB)."""
    formatted = []
    for row in rows:
        cells = dict(mesh=row["mesh"], resolution=row["resolution"], method=row["method"])
        if "median_s" in row:
            cells.update(
                time=f"{row['median_s']:.3g}",
                rss=f"{row['rss_peak_mib']:.0f}",
                rss_delta=f"{row['rss_peak_mib'] - row['rss_before_mib']:.0f}",
                count=f"{row['count']:,}",
            )
            if row["method"].startswith("jaxvox"):  # the peers compile nothing
                cells["compile"] = f"{row['compile_s']:.3g}"
        else:
            cells["time"] = row.get("error") or f"skipped ({row['skipped']})"
        if "error_rate" in row:  # jaxvox 6-separating is thinner by design: no error rate
            cells.update(fp=f"{row['false_positives']:,}", fn=f"{row['false_negatives']:,}")
            if row["method"] in PEERS:
                cells["err"] = f"{100 * row['error_rate']:.2f}"
        formatted.append(cells)
    columns = [
        ("mesh", "mesh"),
        ("resolution", "R"),
        ("method", "method"),
        ("time", "time (s)"),
        ("compile", "compile (s)"),
        ("rss", "peak RSS (MiB)"),
        ("rss_delta", "RSS growth (MiB)"),
        ("count", "voxels"),
        ("fp", "false +"),
        ("fn", "false -"),
        ("err", "error (%)"),
    ]
    return _common.markdown_table(formatted, columns)


def plot(rows: list[dict], path: Path) -> None:
    """Left: median time against resolution (log-log); right: the peers' error rates."""
    fig, (ax_time, ax_err) = _common.new_figure(2)
    meshes = sorted({row["mesh"] for row in rows})
    styles = dict(zip(meshes, ["-", "--", ":", "-."] * len(meshes)))
    colors = dict(zip(METHODS, ["C0", "C1", "C2", "C3"]))
    for method in METHODS:
        for mesh in meshes:
            done = [r for r in rows if r["method"] == method and r["mesh"] == mesh and "median_s" in r]
            if not done:
                continue
            res = [r["resolution"] for r in done]
            label = f"{method}, {mesh}"
            ax_time.plot(
                res, [r["median_s"] for r in done], styles[mesh], marker="o", color=colors[method], label=label
            )
            if method in PEERS and all("error_rate" in r for r in done):
                ax_err.plot(
                    res,
                    [100 * r["error_rate"] for r in done],
                    styles[mesh],
                    marker="o",
                    color=colors[method],
                    label=label,
                )
    ax_time.set(
        xscale="log",
        yscale="log",
        xlabel="resolution R (voxels per axis)",
        ylabel="median time per call (s)",
        title="Surface voxelization time",
    )
    ax_err.set(
        xscale="log",
        xlabel="resolution R (voxels per axis)",
        ylabel="(false + and false -) / exact voxels (%)",
        title="Error against the exact conservative set",
    )
    for ax in (ax_time, ax_err):
        ax.set_xticks(sorted({r["resolution"] for r in rows}))
        ax.xaxis.set_major_formatter("{x:.0f}")
        ax.minorticks_off()
        ax.grid(True, alpha=0.3)
        if ax.has_data():
            ax.legend(fontsize="small")
    if not ax_err.has_data():
        ax_err.text(0.5, 0.5, "no jaxvox conservative run to compare with", transform=ax_err.transAxes, ha="center")
    _common.save_figure(fig, path)


def parse_args(argv=None) -> argparse.Namespace:
    """Command-line options; see the module docstring."""
    parser = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    parser.add_argument(
        "--meshes", nargs="+", default=list(DEFAULT_MESHES), help="mesh names in --mesh-dir, without .obj"
    )
    parser.add_argument("--mesh-dir", type=Path, default=_common.MESH_DIR)
    parser.add_argument(
        "--resolutions",
        nargs="*",
        type=int,
        default=[128, 256, 512, 1024, 2048],
        help="voxels per axis (powers of two); may be empty with --huge",
    )
    parser.add_argument("--repeats", type=int, default=3, help="timed calls after the warm-up")
    parser.add_argument("--methods", nargs="+", choices=METHODS, default=list(METHODS))
    parser.add_argument(
        "--max-resolution", nargs="*", default=[], metavar="METHOD=R", help="skip METHOD above R (default: trimesh=512)"
    )
    parser.add_argument(
        "--huge", type=int, metavar="R", help="also run jaxvox conservative alone on the bunny at this R"
    )
    parser.add_argument("--timeout", type=float, default=3600, help="seconds before one case is abandoned")
    parser.add_argument("--out", type=Path, default=_common.RESULTS_DIR)
    parser.add_argument(
        "--smoke", action="store_true", help="R = 64, 128 only; outputs are named bench_voxelize_smoke.*"
    )
    parser.add_argument("--worker", help=argparse.SUPPRESS)
    args = parser.parse_args(argv)
    if args.smoke:
        args.resolutions = [64, 128]
    args.max_resolution = dict(
        DEFAULT_MAX_RESOLUTION, **{method: int(r) for method, r in (item.split("=") for item in args.max_resolution)}
    )
    return args


def main(argv=None) -> None:
    """Runs the sweep (and the --huge case), then writes JSON, PNG and markdown."""
    args = parse_args(argv)
    if _common.answer_as_worker(args, worker):
        return
    methods = [m for m in METHODS if m in args.methods]  # the reference runs first
    cases = [(mesh, r) for mesh in args.meshes for r in args.resolutions]
    rows = []
    for mesh, resolution in _common.progress(cases, desc="cases"):
        with tempfile.TemporaryDirectory() as tmp:
            rows += run_case(mesh, resolution, methods, args, Path(tmp))
    huge = run_huge(args.huge, args) if args.huge else None

    stem = "bench_voxelize_smoke" if args.smoke else "bench_voxelize"
    sections = [("Surface voxelization", rows), ("Streaming (host-side voxelize)", [huge] if huge else [])]
    report = "\n".join(f"## {title}\n\n{table(part)}" for title, part in sections if part)
    data = dict(
        machine=_common.machine_info(["jax", "jaxlib", "open3d", "trimesh", "numpy"]),
        device=next(
            (dict(backend=r["backend"], device=r["device"]) for r in rows + [huge or {}] if "backend" in r), None
        ),
        settings=dict(
            meshes=args.meshes,
            resolutions=args.resolutions,
            repeats=args.repeats,
            methods=methods,
            max_resolution=args.max_resolution,
        ),
        results=rows,
        huge=huge,
    )
    _common.write_json(args.out / f"{stem}.json", data)
    (args.out / f"{stem}.md").write_text(report)
    if rows:
        plot(rows, args.out / f"{stem}.png")
    print(report)


if __name__ == "__main__":
    main()
