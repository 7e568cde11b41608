"""Distance fields: time and error of each method against exact references.

For each mesh and resolution R, on `jv.Grid.fit(mesh, resolution=R, padding=0.1)`:

* methods: "jfa", "jfa-separable", "sweep" with 1, 2 and 3 iterations, "jfa+sweep"
  (one separable 3x3x3 band pass, then 3 sweep iterations); unsigned fields are timed
  (median of repeats after a warm-up; the first call's extra time is `compile_s`).
  Above ``--all-methods-max`` (128) only "jfa-separable" and "jfa+sweep" run, once,
  so their time includes compilation (seconds, against minutes of work);
* reference (a): scipy's exact EDT of the conservative surface voxels (voxel
  centres to the nearest surface-voxel centre; itself within sqrt(3)/2 voxel of the
  true distance);
* reference (b): the exact point-to-mesh distance, Open3D's `RaycastingScene.
  compute_distance` (float32 BVH) at every voxel centre, checked against a float64
  brute force on a random subsample (the largest disagreement is reported);
* errors in voxels: max, mean and 99th percentile of |field - reference|;
* sign: the solid voxelization jaxvox uses (parity for watertight meshes, the fast
  winding number otherwise), timed; watertight meshes are checked against Open3D's
  ray-parity inside test (`compute_occupancy`) at voxel centres more than 0.01 voxel
  from the surface, open ones against the float64 brute-force winding number on the
  random subsample (centres where it is within 0.01 of 1/2 are left out); "sign
  errors" counts disagreements. Above ``--winding-max`` the open meshes' sign is not
  run. The 16-bit formats' extra error is reported too.

Each (mesh, R) case runs in a fresh process. Outputs distance_fields[_smoke].json,
.md (table) and .png (time vs error, one point per method and resolution) plus
distance_fields[_smoke]_slices.png (error slices) in experiments/results/.

Examples:
  python experiments/distance_fields.py --smoke        # R = 32, 64 on spot (a few minutes)
  python experiments/distance_fields.py                # R = 64 .. 512, spot and bunny
"""

from __future__ import annotations

import argparse
import json
import os
import sys
from pathlib import Path

import _common
import numpy as np

METHODS = [
    ("jfa", "jfa", {}),
    ("jfa-separable", "jfa-separable", {}),
    ("sweep x1", "sweep", dict(sweeps=1)),
    ("sweep x2", "sweep", dict(sweeps=2)),
    ("sweep x3", "sweep", dict(sweeps=3)),
    ("jfa+sweep", "jfa+sweep", dict(sweeps=3)),
]
LARGE_METHODS = ("jfa-separable", "jfa+sweep")  # above --all-methods-max (the others take minutes)


def _errors(field: np.ndarray, ref: np.ndarray) -> dict:
    e = np.abs(field - ref).reshape(-1)
    return dict(max=float(e.max()), mean=float(e.mean()), p99=float(np.percentile(e, 99)))


def worker(spec: dict) -> dict:
    """One (mesh, R) case: every method, both references, sign and 16-bit errors."""
    import jax
    import open3d as o3d
    from scipy import ndimage

    sys.path.insert(0, str(_common.REPO_ROOT))
    import jaxvox as jv
    from tests.reference import mesh_distance

    mesh = jv.load_mesh(spec["path"])
    r = spec["resolution"]
    grid = jv.Grid.fit(mesh, resolution=r, padding=0.1)
    h = float(grid.voxel_size)
    origin = np.asarray(grid.origin, np.float64)

    def centres(flat):  # world centres [n, 3] of C-order voxel numbers
        return (np.stack(np.unravel_index(flat, (r, r, r)), -1) + 0.5) * h + origin

    def per_slab(fn):  # fn(float32 centres [r*r, 3]) -> [r*r], one x slab at a time (memory)
        return np.stack(
            [fn(centres(np.arange(i * r * r, (i + 1) * r * r)).astype(np.float32)).reshape(r, r) for i in range(r)]
        )

    scene = o3d.t.geometry.RaycastingScene()
    scene.add_triangles(np.asarray(mesh.vertices, np.float32), np.asarray(mesh.faces, np.uint32))
    exact = per_slab(lambda c: scene.compute_distance(c).numpy()) / np.float32(h)
    sample = np.random.default_rng(0).choice(r**3, spec["subsample"], replace=False)
    f64 = mesh_distance(mesh.vertices, mesh.faces, centres(sample)) / h
    open3d_vs_f64 = float(np.abs(exact.reshape(-1)[sample] - f64).max())
    surface = np.ones((r, r, r), bool)
    surface[tuple(jv.voxelize(mesh, grid).to_numpy().T)] = False
    edt = ndimage.distance_transform_edt(surface).astype(np.float32)
    del surface

    watertight = jv.open_edges(mesh) == 0
    sign = dict(method="parity" if watertight else "winding")
    if watertight or r <= spec["winding_max"]:
        timing, solid = _common.time_calls(lambda: jax.block_until_ready(jv.solid_voxelize(mesh, grid)), 1)
        sign.update(time_s=timing["median_s"], compile_s=timing["compile_s"])
    if not watertight and "time_s" in sign:
        from tests.reference import winding_number

        w = winding_number(mesh.vertices, mesh.faces, centres(sample))
        firm = np.abs(w - 0.5) > 0.01
        sign.update(
            errors=int((np.asarray(solid).reshape(-1)[sample] != (w > 0.5))[firm].sum()),
            checked=int(firm.sum()),
            reference="float64 winding number, subsample",
        )
        del solid
    if watertight:
        solid = np.asarray(solid)
        inside = per_slab(lambda c: scene.compute_occupancy(c).numpy()) > 0.5
        firm = exact > 0.01
        sign.update(errors=int((solid != inside)[firm].sum()), checked=int(firm.sum()))
        del solid, inside, firm

    rows, slices = [], {}
    methods = METHODS if r <= spec["all_methods_max"] else [m for m in METHODS if m[0] in LARGE_METHODS]
    repeats = spec["repeats"] if r <= spec["all_methods_max"] else 0
    for label, method, kw in methods:
        need = jv.distance_field_bytes(r, method=method, signed=False)
        if spec.get("max_bytes") and need > spec["max_bytes"]:  # refused by distance_field: record why
            rows.append(dict(method=label, refused=f"needs {need / 2**30:.1f} GiB"))
            continue
        call = lambda: jax.block_until_ready(
            jv.distance_field(mesh, grid, method=method, signed=False, max_bytes=spec.get("max_bytes"), **kw)
        )
        timing, field = _common.time_calls(call, repeats)
        field = np.asarray(field) / h
        row = dict(
            method=label,
            **{k: timing[k] for k in ("median_s", "compile_s", "first_s")},
            vs_exact=_errors(field, exact),
            vs_edt=_errors(field, edt),
        )
        if label == "jfa+sweep":
            for fmt in jv.distance.FORMATS:
                q = jv.quantize_field(jax.numpy.asarray(field * h), grid, format=fmt)
                row[f"{fmt}_extra"] = _errors(np.asarray(q.decode()) / h, field)
        rows.append(row)
        stride = max(1, r // 128)  # keep the JSON small
        slices[label] = (field - exact)[::stride, ::stride, r // 2].round(4).tolist()
    return dict(
        resolution=r,
        voxel_size=h,
        faces=mesh.num_faces,
        watertight=bool(watertight),
        open3d_vs_float64_max=open3d_vs_f64,
        subsample=spec["subsample"],
        sign=sign,
        rows=rows,
        slices=slices,
        peak_rss_mib=_common.peak_rss_mib(),
    )


def table(cases: list[dict]) -> str:
    def rows_of(case):
        sign = case["sign"]
        if "errors" in sign:
            sign_text = f"{sign['errors']} / {sign['checked']:,} in {sign['time_s']:.3g} s"
        else:
            sign_text = "not run"
        rows = []
        for row in case["rows"]:
            if "refused" in row:
                rows.append(
                    dict(
                        mesh=case["mesh"],
                        R=case["resolution"],
                        method=row["method"],
                        time=f"refused ({row['refused']})",
                    )
                )
                continue
            a, b = row["vs_exact"], row["vs_edt"]
            rows.append(
                dict(
                    mesh=case["mesh"],
                    R=case["resolution"],
                    method=row["method"],
                    time=f"{row['median_s']:.3g}",
                    compile=f"{row['compile_s']:.2g}",
                    exact=f"{a['max']:.3f} / {a['mean']:.4f} / {a['p99']:.3f}",
                    edt=f"{b['max']:.3f} / {b['mean']:.3f} / {b['p99']:.3f}",
                    sign=f"{sign['method']}: {sign_text}",
                )
            )
        return rows

    out = _common.case_rows(cases, rows_of)
    columns = [
        ("mesh", "mesh"),
        ("R", "R"),
        ("method", "method"),
        ("time", "time (s)"),
        ("compile", "compile (s)"),
        ("exact", "vs exact: max / mean / p99 (voxels)"),
        ("edt", "vs EDT of surface voxels: max / mean / p99"),
        ("sign", "sign errors"),
    ]
    return _common.markdown_table(out, columns)


def plot(cases: list[dict], stem: Path) -> None:
    fig, (ax_max, ax_mean) = _common.new_figure(2)
    labels = [m[0] for m in METHODS]
    for n, label in enumerate(labels):
        pts = [
            (row["median_s"], row["vs_exact"], case["resolution"], case["mesh"])
            for case in cases
            if "rows" in case
            for row in case["rows"]
            if row["method"] == label and "refused" not in row
        ]
        for ax, key in ((ax_max, "max"), (ax_mean, "mean")):
            ax.scatter([p[0] for p in pts], [p[1][key] for p in pts], color=f"C{n}", label=label)
            for p in pts:
                ax.annotate(f"{p[3][:5]} {p[2]}", (p[0], p[1][key]), fontsize=6)
    for ax, key in ((ax_max, "max"), (ax_mean, "mean")):
        ax.set(
            xscale="log",
            yscale="log",
            xlabel="median time per field (s)",
            ylabel=f"{key} |error| vs exact distance (voxels)",
            title=f"Time vs {key} error",
        )
        ax.grid(True, alpha=0.3)
        ax.legend(fontsize="small")
    _common.save_figure(fig, stem.with_suffix(".png"))
    case = next((c for c in reversed(cases) if "slices" in c), None)
    if case:
        fig, axes = _common.new_figure(len(case["slices"]), width=3.2, height=3.0)
        for ax, (label, sl) in zip(np.atleast_1d(axes), case["slices"].items()):
            im = ax.imshow(np.asarray(sl).T, origin="lower", cmap="RdBu_r", vmin=-1.5, vmax=1.5)
            ax.set_title(f"{label}\n{case['mesh']} {case['resolution']}^3, z = R/2", fontsize=8)
        fig.colorbar(im, ax=axes, label="field - exact (voxels)")
        _common.save_figure(fig, stem.parent / f"{stem.name}_slices.png")


def main(argv=None) -> None:
    parser = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    parser.add_argument("--meshes", nargs="+", default=["spot", "stanford-bunny"])
    parser.add_argument("--resolutions", nargs="+", type=int, default=[64, 128, 256, 512])
    parser.add_argument("--repeats", type=int, default=3)
    parser.add_argument("--subsample", type=int, default=2000, help="float64 check points")
    parser.add_argument("--timeout", type=float, default=7200)
    parser.add_argument(
        "--all-methods-max", type=int, default=128, help=f"larger R run only {', '.join(LARGE_METHODS)}"
    )
    parser.add_argument(
        "--winding-max", type=int, default=512, help="largest R at which the winding-number sign of open meshes is run"
    )
    parser.add_argument(
        "--max-bytes", type=float, default=0.75, help="memory a field may use, as a fraction of physical memory"
    )
    parser.add_argument(
        "--update", action="store_true", help="merge into the existing JSON (replacing the same mesh and R)"
    )
    parser.add_argument("--smoke", action="store_true", help="spot at R = 32, 64, one repeat")
    parser.add_argument("--worker", help=argparse.SUPPRESS)
    args = parser.parse_args(argv)
    if _common.answer_as_worker(args, worker):
        return
    if args.smoke:
        args.meshes, args.resolutions, args.repeats, args.subsample = ["spot"], [32, 64], 1, 300
    stem = _common.RESULTS_DIR / ("distance_fields_smoke" if args.smoke else "distance_fields")
    path = stem.with_suffix(".json")
    cases = json.loads(path.read_text())["cases"] if args.update and path.exists() else []
    for mesh in args.meshes:
        for r in _common.progress(args.resolutions, desc=mesh):
            spec = dict(
                path=str(_common.MESH_DIR / f"{mesh}.obj"),
                resolution=r,
                repeats=args.repeats,
                subsample=args.subsample,
                all_methods_max=args.all_methods_max,
                winding_max=args.winding_max,
                max_bytes=int(args.max_bytes * os.sysconf("SC_PAGE_SIZE") * os.sysconf("SC_PHYS_PAGES")),
            )
            case = dict(_common.run_worker(__file__, spec, timeout=args.timeout), mesh=mesh, resolution=r)
            cases = [c for c in cases if (c["mesh"], c["resolution"]) != (mesh, r)] + [case]
            print(f"{mesh} R={r}: {case.get('error', 'done')}", file=sys.stderr)
    order = {m: n for n, m in enumerate(args.meshes)}
    cases.sort(key=lambda c: (order.get(c["mesh"], len(order)), c["mesh"], c["resolution"]))
    report = table(cases)
    _common.write_json(
        stem.with_suffix(".json"),
        dict(
            machine=_common.machine_info(["jax", "jaxlib", "open3d", "scipy", "numpy"]),
            settings=vars(args) | dict(mesh_dir=None),
            cases=cases,
        ),
    )
    stem.with_suffix(".md").write_text(report)
    plot(cases, stem)
    print(report)


if __name__ == "__main__":
    main()
