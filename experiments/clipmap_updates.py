"""Cascaded clipmaps: time per camera move and error of each method, against Open3D.

For each mesh, N cascades of R^3 voxels (finest voxel: the mesh's largest extent / R, so
the finest window is about the mesh's size) follow a camera flying through the mesh along
(1, 1/2, 1/4), `--step` finest voxels per frame, for `--frames` frames. Every cascade is
updated every frame, so each frame exposes slabs of one to three voxels in the finest
cascade and fewer in the coarser ones.

* methods: `update_clipmap` with "band", "jfa", "jfa+sweep" (the thread's pipeline, on
  scissor volumes: each exposed slab grown by the truncation plus one voxel) and "exact"
  (the default: exact point-triangle distances over the triangles within the truncation
  of each exposed voxel, one batch per frame; see `jaxvox.Clipmap`);
* peer: Open3D's `RaycastingScene.compute_signed_distance` (float32 BVH, exact distance,
  sign by ray parity) at exactly the exposed voxel centres, clamped and written into a
  toroidal numpy array: the work a move needs done by a real library;
* rebuild: `build_clipmap` at the last position (every voxel of every cascade), median
  of 2 calls after a warm-up;
* time: the path is flown twice; the second flight is timed (median seconds per frame)
  and the first flight's extra time is reported as compilation (new slab shapes; the
  first method also pays for the sign code the others reuse), with the number of XLA
  compilations in each flight (`jax.monitoring`; 0 in the timed one: moves run programs
  already compiled);
* error: the clipmap after the flight against the clamped exact signed distance at
  every voxel (Open3D's distance and parity occupancy), in voxels of each cascade: max,
  mean and 99th percentile of |field - exact| over all cascades; sign errors counted
  where the exact distance exceeds half a voxel.

Watertight meshes only (the reference sign is ray parity). Writes
clipmap_updates[_smoke].json, .md and .png (time per frame vs max error) in
experiments/results/.

Examples:
  python experiments/clipmap_updates.py --smoke     # spot, R = 16, a few frames
  python experiments/clipmap_updates.py             # spot, R = 32 and 64, 8 frames (about 15 minutes)
  python experiments/clipmap_updates.py --resolutions 64 --methods band exact --out /tmp/x
                                                    # 64^3 x 3 only, two methods, results in /tmp/x.*
"""

from __future__ import annotations

import argparse
import sys
import time

import _common
import numpy as np

METHODS = ("band", "jfa", "jfa+sweep", "exact")


def _flight(start, step, frames):
    direction = np.array([1.0, 0.5, 0.25]) / np.linalg.norm([1.0, 0.5, 0.25])
    return [start + direction * step * f for f in range(1, frames + 1)]


def worker(spec: dict) -> dict:
    """One (mesh, R) case: every method and the Open3D peer over the same flight."""
    import jax
    import open3d as o3d

    sys.path.insert(0, str(_common.REPO_ROOT))
    import jaxvox as jv
    from jaxvox.distance.clipmap import _exposed_boxes

    mesh = jv.load_mesh(spec["path"])
    v = np.asarray(mesh.vertices, np.float64)
    compiles: list[float] = []
    jax.monitoring.register_event_duration_secs_listener(
        lambda name, secs, **kw: compiles.append(secs) if name == "/jax/core/compile/backend_compile_duration" else None
    )
    r, n, trunc = spec["resolution"], spec["cascades"], spec["truncation"]
    h0 = float((v.max(0) - v.min(0)).max()) / r
    centre = (v.max(0) + v.min(0)) / 2
    start = centre - np.array([1.0, 0.5, 0.25]) * 0.6 * r * h0
    path = _flight(start, spec["step"] * h0, spec["frames"])
    settings = dict(resolution=r, num_cascades=n, voxel_size=h0, truncation=trunc)
    scene = o3d.t.geometry.RaycastingScene()
    scene.add_triangles(np.asarray(mesh.vertices, np.float32), np.asarray(mesh.faces, np.uint32))

    def fly_jaxvox(method):
        clip = jv.build_clipmap(mesh, start, method=method, **settings)
        jax.block_until_ready(clip.fields)
        times = []
        for camera in path:
            t0 = time.perf_counter()
            clip = jv.update_clipmap(clip, mesh, camera)
            jax.block_until_ready(clip.fields)
            times.append(time.perf_counter() - t0)
        return clip, times

    def fly_open3d():
        fields = np.zeros((n, r, r, r), np.float32)
        corner = np.full((n, 3), np.iinfo(np.int32).min // 2, np.int64)
        times = []
        for camera in [start] + path:
            t0 = time.perf_counter()
            new = jv.clipmap_corners(camera, (0.0, 0.0, 0.0), h0, r, n).astype(np.int64)
            for c in range(n):
                h = h0 * 2.0**c
                for lo, hi in _exposed_boxes(corner[c], new[c], r):
                    g = np.stack(np.meshgrid(*(np.arange(a, b) for a, b in zip(lo, hi)), indexing="ij"), -1)
                    d = scene.compute_signed_distance(((g + 0.5) * h).reshape(-1, 3).astype(np.float32)).numpy()
                    fields[(c,) + np.ix_(*(np.mod(np.arange(a, b), r) for a, b in zip(lo, hi)))] = np.clip(
                        d, -trunc * h, trunc * h
                    ).reshape(hi - lo)
            corner = new
            times.append(time.perf_counter() - t0)
        return fields, corner, times[1:]

    exact_fields = None
    rows = []
    for method in tuple(spec["methods"]) + ("open3d",):
        flights = []
        for _ in range(2):  # the first flight compiles every slab shape; the second is timed
            before = len(compiles)
            t0 = time.perf_counter()
            if method == "open3d":
                fields, corner, times = fly_open3d()
            else:
                clip, times = fly_jaxvox(method)
                fields, corner = np.asarray(clip.fields), np.asarray(clip.corner)
            flights.append((time.perf_counter() - t0, times, len(compiles) - before))
        if exact_fields is None:
            exact_fields = _reference(scene, corner, h0, r, trunc)
        h = h0 * 2.0 ** np.arange(n)[:, None, None, None]
        got, ref = fields / h, exact_fields / h
        err = np.abs(got - ref).reshape(-1)
        firm = np.abs(ref) > 0.5
        row = dict(
            method=method,
            frame_median_s=float(np.median(flights[1][1])),
            frame_max_s=float(np.max(flights[1][1])),
            compile_s=max(flights[0][0] - flights[1][0], 0.0),
            compiles=flights[0][2],  # XLA compilations in the first flight (build included)
            compiles_timed=flights[1][2],  # ... and in the timed one (0: no new program per move)
            max=float(err.max()),
            mean=float(err.mean()),
            p99=float(np.percentile(err, 99)),
            sign_errors=int((np.sign(got) != np.sign(ref))[firm].sum()),
            sign_checked=int(firm.sum()),
        )
        if method != "open3d":
            call = lambda: jax.block_until_ready(jv.build_clipmap(mesh, path[-1], method=method, **settings).fields)
            timing, _ = _common.time_calls(call, 2)
            row.update(rebuild_s=timing["median_s"])
        rows.append(row)
    exposed = _exposed_per_frame(path, start, h0, r, n)
    return dict(
        resolution=r,
        cascades=n,
        truncation=trunc,
        voxel_size=h0,
        faces=mesh.num_faces,
        frames=len(path),
        step_voxels=spec["step"],
        exposed_voxels_per_frame=exposed,
        rows=rows,
        peak_rss_mib=_common.peak_rss_mib(),
    )


def _reference(scene, corner, h0, r, trunc):
    """Clamped exact signed distances [N, R, R, R] in toroidal slots for the given corners."""
    n = len(corner)
    out = np.zeros((n, r, r, r), np.float32)
    idx = np.stack(np.meshgrid(*(np.arange(r),) * 3, indexing="ij"), -1).reshape(-1, 3)
    for c in range(n):
        h = h0 * 2.0**c
        g = corner[c] + idx
        d = scene.compute_signed_distance(((g + 0.5) * h).astype(np.float32)).numpy()
        slots = np.mod(g, r)
        out[c][tuple(slots.T)] = np.clip(d, -trunc * h, trunc * h)
    return out


def _exposed_per_frame(path, start, h0, r, n) -> float:
    import jaxvox as jv
    from jaxvox.distance.clipmap import _exposed_boxes

    corner = jv.clipmap_corners(start, (0.0, 0.0, 0.0), h0, r, n)
    total = 0
    for camera in path:
        new = jv.clipmap_corners(camera, (0.0, 0.0, 0.0), h0, r, n)
        for c in range(n):
            total += sum(int(np.prod(hi - lo)) for lo, hi in _exposed_boxes(corner[c], new[c], r))
        corner = new
    return total / len(path)


def table(cases: list[dict]) -> str:
    def rows_of(case):
        return [
            dict(
                mesh=case["mesh"],
                R=f"{case['resolution']} x {case['cascades']}",
                method=row["method"],
                frame=f"{row['frame_median_s'] * 1e3:.3g} / {row['frame_max_s'] * 1e3:.3g}",
                rebuild=f"{row['rebuild_s']:.3g}" if "rebuild_s" in row else "-",
                compile=f"{row['compile_s']:.2g}"
                + (f" ({row['compiles']} / {row['compiles_timed']})" if "compiles" in row else ""),
                err=f"{row['max']:.3f} / {row['mean']:.4f} / {row['p99']:.3f}",
                sign=f"{row['sign_errors']} / {row['sign_checked']:,}",
                exposed=f"{case['exposed_voxels_per_frame']:,.0f}",
            )
            for row in case["rows"]
        ]

    out = _common.case_rows(cases, rows_of)
    columns = [
        ("mesh", "mesh"),
        ("R", "R x cascades"),
        ("method", "method"),
        ("exposed", "exposed voxels / frame"),
        ("frame", "frame: median / max (ms)"),
        ("rebuild", "rebuild (s)"),
        ("compile", "compile (s) (programs: first / timed flight)"),
        ("err", "vs exact: max / mean / p99 (voxels)"),
        ("sign", "sign errors"),
    ]
    return _common.markdown_table(out, columns)


def plot(cases: list[dict], stem) -> None:
    fig, ax = _common.new_figure(1, width=7.0)
    for k, method in enumerate(METHODS + ("open3d",)):  # fixed colours whatever --methods ran
        pts = [
            (row["frame_median_s"], max(row["max"], 1e-4), case)
            for case in cases
            if "rows" in case
            for row in case["rows"]
            if row["method"] == method
        ]
        ax.scatter([p[0] for p in pts], [p[1] for p in pts], color=f"C{k}", label=method)
        for p in pts:
            ax.annotate(f"{p[2]['mesh'][:5]} {p[2]['resolution']}", (p[0], p[1]), fontsize=6)
    ax.set(
        xscale="log",
        yscale="log",
        xlabel="median time per frame (s), every cascade updated",
        ylabel="max |error| vs exact clamped SDF (voxels; 1e-4 = exact)",
        title="Clipmap updates: time vs error",
    )
    ax.grid(True, alpha=0.3)
    ax.legend(fontsize="small")
    _common.save_figure(fig, stem.with_suffix(".png"))


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    parser.add_argument("--meshes", nargs="+", default=["spot"])
    parser.add_argument("--methods", nargs="+", default=list(METHODS), choices=METHODS)
    parser.add_argument("--out", default="clipmap_updates", help="results stem in experiments/results (or a path)")
    parser.add_argument("--resolutions", nargs="+", type=int, default=[32, 64])
    parser.add_argument("--cascades", type=int, default=3)
    parser.add_argument("--truncation", type=float, default=8.0)
    parser.add_argument("--frames", type=int, default=8)
    parser.add_argument("--step", type=float, default=1.5, help="camera move per frame, finest voxels")
    parser.add_argument("--timeout", type=float, default=3600)
    parser.add_argument("--smoke", action="store_true", help="spot at R = 16, 4 frames")
    parser.add_argument("--worker", help=argparse.SUPPRESS)
    args = parser.parse_args()
    if _common.answer_as_worker(args, worker):
        return
    if args.smoke:
        args.meshes, args.resolutions, args.frames = ["spot"], [16], 4
    stem = _common.RESULTS_DIR / (args.out + "_smoke" if args.smoke else args.out)
    cases = []
    for name in args.meshes:
        for r in args.resolutions:
            spec = dict(
                path=str(_common.MESH_DIR / f"{name}.obj"),
                resolution=r,
                cascades=args.cascades,
                truncation=args.truncation,
                frames=args.frames,
                step=args.step,
                methods=args.methods,
            )
            case = dict(_common.run_worker(__file__, spec, timeout=args.timeout), mesh=name, resolution=r)
            cases.append(case)
            print(table([case]), flush=True)
    _common.write_json(
        stem.with_suffix(".json"),
        dict(machine=_common.machine_info(["jax", "open3d"]), settings=vars(args), cases=cases),
    )
    stem.with_suffix(".md").write_text(table(cases) + "\n")
    plot(cases, stem)
    print(table(cases))


if __name__ == "__main__":
    main()
