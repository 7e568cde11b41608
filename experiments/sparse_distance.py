"""Sparse narrow-band distance fields: jaxvox against OpenVDB's meshToLevelSet and Open3D.

For each mesh and resolution R (default the bunny at 256 and 1024), on
``jv.Grid.fit(mesh, resolution=R)`` with half width ``--band`` (3) voxels:

* jaxvox: `jv.sparse_distance_field` (signed; ``--unsigned`` for the unsigned field): the
  first call in a fresh process (compilation included, with its number of XLA
  compilations), then the median of ``--repeats`` warmed-up calls; band voxels, bytes of
  the values and of the whole `SparseField` (voxels, values, triangles, tree), peak
  resident memory; each for the default field and for a compact one (``compact=True``:
  values and tree only; ``--layouts``), each in a fresh process; the default field again
  in a plain process (``plain``: no huge pages, as a user's `python` or notebook starts;
  every other worker asks for them, `_common`). Resolutions listed in
  ``--stream`` take `jv.sparse_field_regions` instead (each region's field counted and
  dropped: fields larger than memory). The
  bunny is open, so its sign takes components of mesh plus caps (`jaxvox.distance.band_sign`);
* OpenVDB: ``FloatGrid.createLevelSetFromPolygons`` (meshToLevelSet, multi-threaded) with
  the same voxel size and half width, run by the system ``/usr/bin/python3`` (Debian
  ``python3-openvdb``) in a subprocess, timed there (first call and median of repeats);
  its sign is a flood fill from the outside, not a winding number; its bytes
  (``memUsage``) and the subprocess's peak resident memory. Up to R = `COMPARE_MAX` its
  values are compared with jaxvox's exact ones at jaxvox's band voxels (the mesh is
  shifted so that OpenVDB's voxel centres are jaxvox's): the largest and 99th-percentile
  error of its unsigned distance, the share of voxels off by more than 0.1 voxel, and the
  voxels whose sign differs from the winding number's;
* Open3D: ``RaycastingScene.compute_distance`` (exact unsigned distance through a BVH,
  multi-threaded) and ``compute_signed_distance`` at jaxvox's band voxel centres (the same
  set of points), scene construction included; the largest difference from jaxvox's
  values (voxels) is reported as a cross-check.

Each case runs in a fresh process. Writes experiments/results/sparse_distance[_unsigned][_smoke].json,
.md and .png (time against resolution, log-log).

Examples:
  python experiments/sparse_distance.py --smoke      # R = 64
  python experiments/sparse_distance.py              # R = 256, 1024
  python experiments/sparse_distance.py --resolutions 4096 --repeats 0 --skip-open3d --update
  python experiments/sparse_distance.py --resolutions 8192 --stream 8192 --repeats 0 --update
"""

from __future__ import annotations

import argparse
import json
import os
import subprocess
import tempfile
import textwrap
import time

import _common

SYSTEM_PYTHON = "/usr/bin/python3"
COMPARE_MAX = 256  # largest R whose OpenVDB values are compared with jaxvox's (a dense R^3 copy)
_OPENVDB = textwrap.dedent(
    """
    import json, resource, sys, time
    import numpy as np
    try:
        import pyopenvdb as vdb
    except ImportError:
        import openvdb as vdb
    spec = json.loads(sys.argv[1])
    v, f = [], []
    for line in open(spec["mesh"]):
        p = line.split()
        if p and p[0] == "v":
            v.append([float(x) for x in p[1:4]])
        elif p and p[0] == "f":
            idx = [int(x.split("/")[0]) for x in p[1:]]
            idx = [i - 1 if i > 0 else len(v) + i for i in idx]
            f += [[idx[0], idx[k], idx[k + 1]] for k in range(1, len(idx) - 1)]
    v = np.asarray(np.asarray(v) - spec["shift"], np.float32)  # jaxvox's voxel centres on OpenVDB's
    f = np.asarray(f, np.int32)
    xform = vdb.createLinearTransform(voxelSize=spec["voxel_size"])
    times = []
    for _ in range(spec["repeats"] + 1):
        t = time.perf_counter()
        grid = vdb.FloatGrid.createLevelSetFromPolygons(v, triangles=f, transform=xform, halfWidth=spec["band"])
        times.append(time.perf_counter() - t)
    median = float(np.median(times[1:])) if len(times) > 1 else times[0]
    voxels, nbytes = int(grid.activeVoxelCount()), int(grid.memUsage())
    peak = resource.getrusage(resource.RUSAGE_SELF).ru_maxrss / 1024
    out = dict(first_s=times[0], median_s=median, voxels=voxels, bytes=nbytes, peak_rss_mib=peak)
    if spec.get("compare"):  # jaxvox's band voxels and exact values (voxels), from its worker
        want = np.load(spec["compare"])
        ijk, exact = want["ijk"], want["values"].astype(np.float64)
        dense = np.zeros((spec["resolution"],) * 3, np.float32)
        grid.copyToArray(dense, ijk=(0, 0, 0))
        got = dense[tuple(ijk.T)].astype(np.float64) / spec["voxel_size"]
        active = np.abs(got) < spec["band"] * (1 - 1e-6)  # inactive voxels hold the background, +-band
        error = np.abs(np.abs(got) - np.abs(exact))[active]
        wrong = active & (np.abs(exact) > 1e-3) & ((got < 0) != (exact < 0))
        out["compared"] = dict(
            voxels=int(active.sum()),
            missing=int((~active).sum()),
            max_error_voxels=float(error.max(initial=0.0)),
            p99_error_voxels=float(np.percentile(error, 99)) if error.size else 0.0,
            share_over_tenth=float(np.mean(error > 0.1)) if error.size else 0.0,
            sign_disagreements=int(wrong.sum()) if spec["signed"] else None,
        )
    print(json.dumps(out))
    """
)


def _openvdb(spec: dict, timeout: float) -> dict:
    try:
        proc = subprocess.run(
            [SYSTEM_PYTHON, "-c", _OPENVDB, json.dumps(spec)], capture_output=True, text=True, timeout=timeout
        )
    except (OSError, subprocess.TimeoutExpired) as e:
        return {"error": str(e)}
    if proc.returncode != 0:
        return {"error": (proc.stderr.strip().splitlines() or [f"exit status {proc.returncode}"])[-1]}
    return json.loads(proc.stdout.strip().splitlines()[-1])


def worker(spec: dict) -> dict:
    import jax
    import numpy as np

    import jaxvox as jv

    compiles: list[float] = []
    jax.monitoring.register_event_duration_secs_listener(
        lambda name, secs, **kw: compiles.append(secs) if name == "/jax/core/compile/backend_compile_duration" else None
    )
    mesh = jv.load_mesh(spec["mesh"])
    grid = jv.Grid.fit(mesh, resolution=spec["resolution"])
    kw = dict(band=spec["band"], signed=spec["signed"], compact=spec["compact"])
    field_bytes = lambda f: f.memory()["total"]
    if spec["stream"]:  # region by region, each region's field dropped once counted

        def run():
            voxels = total = 0
            for part in jv.sparse_field_regions(mesh, grid, **kw):
                voxels, total = voxels + int(part.count), total + field_bytes(part)
            return voxels, total

        timing, (n, total) = _common.time_calls(run, spec["repeats"])
        field = None
    else:
        run = lambda: jax.block_until_ready(jv.sparse_distance_field(mesh, grid, **kw))
        timing, field = _common.time_calls(run, spec["repeats"])
        n, total = int(field.count), field_bytes(field)
    out = dict(
        jaxvox=dict(
            timing,
            compiles=len(compiles),
            voxels=n,
            value_bytes=4 * n,
            field_mib=total / 2**20,
            memory=None if field is None else field.memory(),  # bytes by part (SparseField.memory)
            peak_rss_mib=_common.peak_rss_mib(),
            streamed=spec["stream"],
            environment=_common.environment(),
        ),
        voxel_size=float(grid.voxel_size),
        shift=(np.asarray(grid.origin, np.float64) + 0.5 * float(grid.voxel_size)).tolist(),  # voxel 0's centre
    )
    h = float(grid.voxel_size)
    if field is not None and spec.get("compare"):  # band voxels and values (voxels) for OpenVDB's comparison
        np.savez(spec["compare"], ijk=np.asarray(field.voxel_coords()), values=np.asarray(field.values[:n]) / h)
    if field is None or spec["skip_open3d"] or spec["compact"]:  # (a compact field has the same values)
        return out
    try:
        import open3d as o3d
    except ImportError as e:
        out["open3d"] = {"error": str(e)}
        return out
    ijk = np.asarray(field.voxel_coords(), np.float64)
    points = (np.asarray(grid.origin, np.float64) + (ijk + 0.5) * h).astype(np.float32)
    values = np.asarray(field.values[:n], np.float64)
    del field
    vertices = o3d.core.Tensor(np.asarray(mesh.vertices, np.float32))
    faces = o3d.core.Tensor(np.asarray(mesh.faces, np.uint32))
    peer = {}
    for name, method in (("unsigned", "compute_distance"), ("signed", "compute_signed_distance")):
        times, d = [], None
        for _ in range(spec["repeats"] + 1):
            t = time.perf_counter()
            scene = o3d.t.geometry.RaycastingScene()
            scene.add_triangles(vertices, faces)
            d = getattr(scene, method)(o3d.core.Tensor(points)).numpy()
            times.append(time.perf_counter() - t)
        entry = dict(first_s=times[0], median_s=float(np.median(times[1:])))
        if name == "unsigned":
            entry["max_diff_voxels"] = float(np.max(np.abs(np.abs(d) - np.abs(values)), initial=0.0) / h)
        elif spec["signed"]:  # Open3D's inside test is its own (ray parity), not a winding number
            entry["sign_disagreements"] = int(np.sum((d < 0) != (values < 0)))
        peer[name] = entry
    out["open3d"] = peer
    return out


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    parser.add_argument("--worker")
    parser.add_argument("--smoke", action="store_true")
    parser.add_argument("--resolutions", type=int, nargs="*", default=None)
    parser.add_argument("--band", type=int, default=3)
    parser.add_argument("--repeats", type=int, default=2)
    parser.add_argument("--unsigned", action="store_true")
    parser.add_argument("--timeout", type=float, default=1800)
    parser.add_argument(
        "--stream",
        type=int,
        nargs="*",
        default=[],
        help="resolutions handed out region by region (sparse_field_regions), each region dropped once counted",
    )
    parser.add_argument("--skip-open3d", action="store_true", help="no Open3D queries (slow and large at 4096^3)")
    parser.add_argument(
        "--layouts",
        nargs="+",
        choices=["full", "compact", "plain"],
        default=["full", "compact", "plain"],
        help="jaxvox's fields: full (the default call: voxels, triangles, values, tree), compact (values and "
        "tree), and plain (the default call in a process without huge pages)",
    )
    parser.add_argument("--update", action="store_true", help="replace only these resolutions' rows in the JSON")
    args = parser.parse_args()
    if _common.answer_as_worker(args, worker):
        return
    resolutions = args.resolutions or ([64] if args.smoke else [256, 1024])
    mesh = str(_common.MESH_DIR / "stanford-bunny.obj")
    cases = []
    scratch = tempfile.TemporaryDirectory()  # jaxvox's values, for OpenVDB's comparison
    for r in _common.progress(resolutions, desc="resolutions"):
        compare = f"{scratch.name}/values_{r}.npz" if r <= COMPARE_MAX and r not in args.stream else None
        case = dict(resolution=r, mesh="stanford-bunny")
        for layout in args.layouts:  # each in a fresh process (its own peak memory)
            spec = dict(
                mesh=mesh,
                resolution=r,
                band=args.band,
                repeats=args.repeats,
                signed=not args.unsigned,
                stream=r in args.stream,
                skip_open3d=args.skip_open3d or layout != "full",
                compact=layout == "compact",
                compare=compare if layout == "full" else None,
            )
            run = _common.run_worker(__file__, spec, timeout=args.timeout, plain=layout == "plain")
            key = {"full": "jaxvox", "compact": "jaxvox_compact", "plain": "jaxvox_plain"}[layout]
            case[key] = run.get("jaxvox", run)  # (or its error)
            case.update({name: run[name] for name in ("voxel_size", "shift", "open3d") if name in run})
        if "voxel_size" in case:
            peer = dict(mesh=mesh, voxel_size=case["voxel_size"], band=args.band, repeats=args.repeats)
            peer.update(shift=case.pop("shift"), resolution=r, signed=not args.unsigned)
            peer["compare"] = compare if compare and os.path.exists(compare) else None
            case["openvdb"] = _openvdb(peer, args.timeout)
        cases.append(case)
        print(json.dumps(case))
    name = "sparse_distance" + ("_unsigned" if args.unsigned else "") + ("_smoke" if args.smoke else "")
    path = _common.RESULTS_DIR / f"{name}.json"
    if args.update and path.exists():  # keep the other rows of the last full run (other resolutions, layouts)
        last = {c["resolution"]: c for c in json.loads(path.read_text())["cases"]}
        cases = [dict(last.pop(c["resolution"], {}), **c) for c in cases]
        cases = sorted(list(last.values()) + cases, key=lambda c: c["resolution"])
    result = dict(band=args.band, signed=not args.unsigned, cases=cases, machine=_common.machine_info(PACKAGES))
    _common.write_json(path, result)
    write_report(result, _common.RESULTS_DIR / name)


PACKAGES = ["jax", "jaxlib", "numpy", "open3d"]


def _rows(case: dict) -> list[dict]:
    vdb, o3d = case.get("openvdb", {}), case.get("open3d", {})
    cmp = vdb.get("compared")
    fmt = lambda x: f"{x:.3g}" if isinstance(x, float) else "-"
    per_voxel = lambda nbytes, voxels: fmt(nbytes / voxels) if nbytes and voxels else "-"
    rows = []
    for key, layout in (
        ("jaxvox", "full (default)"),
        ("jaxvox_compact", "compact"),
        ("jaxvox_plain", "full, plain process"),
    ):
        if key not in case:
            continue
        j = case[key]
        layout += f" ({j['error']})" if "error" in j else ""
        memory = j.get("memory") or {}
        rows.append(
            dict(
                R=case["resolution"],
                layout=layout,
                voxels=f"{j.get('voxels', 0):,}",
                first=fmt(j.get("first_s")),
                compiles=str(j.get("compiles", "-")),
                warm=fmt(j.get("median_s")),
                peak=fmt(j.get("peak_rss_mib")),
                field=fmt(j.get("field_mib")) + (" (by regions)" if j.get("streamed") else ""),
                per_voxel=per_voxel(j.get("field_mib", 0) * 2**20, j.get("voxels")),
                topology=per_voxel(memory.get("topology"), j.get("voxels")),
                vdb=fmt(vdb.get("median_s"))
                + (f" ({vdb['voxels']:,} voxels)" if "voxels" in vdb else "")
                + (f" ({vdb['error']})" if "error" in vdb else ""),
                vdb_per_voxel=per_voxel(vdb.get("bytes"), vdb.get("voxels")),
                vdb_peak=fmt(vdb.get("peak_rss_mib")),
                o3d=fmt(o3d.get("signed", {}).get("median_s")) + " / " + fmt(o3d.get("unsigned", {}).get("median_s")),
                diff=fmt(o3d.get("unsigned", {}).get("max_diff_voxels")),
                vdb_error=" / ".join(
                    [fmt(cmp["max_error_voxels"]), fmt(cmp["p99_error_voxels"]), f"{cmp['share_over_tenth']:.2%}"]
                )
                if cmp
                else "-",
                vdb_signs=(
                    f"{cmp['sign_disagreements']:,} ({100 * cmp['sign_disagreements'] / max(cmp['voxels'], 1):.1f}%)"
                    if cmp and cmp.get("sign_disagreements") is not None
                    else "-"
                ),
                signs=str(o3d.get("signed", {}).get("sign_disagreements", "-")),
            )
        )
    return rows


def write_report(result: dict, stem) -> None:
    """Markdown table and chart (time against resolution) next to the JSON."""
    columns = [
        ("R", "R"),
        ("layout", "jaxvox field"),
        ("voxels", "band voxels"),
        ("first", "jaxvox first call (s)"),
        ("compiles", "compiles"),
        ("warm", "jaxvox warm (s)"),
        ("peak", "peak RSS (MiB)"),
        ("field", "field (MiB)"),
        ("per_voxel", "bytes per voxel"),
        ("topology", "of which the tree"),
        ("vdb", "OpenVDB warm (s)"),
        ("vdb_per_voxel", "OpenVDB bytes per voxel (memUsage)"),
        ("vdb_peak", "OpenVDB peak RSS (MiB)"),
        ("vdb_error", "OpenVDB unsigned error vs jaxvox's exact (voxels): max / p99 / share > 0.1"),
        ("vdb_signs", "OpenVDB signs unlike the winding number's"),
        ("o3d", "Open3D signed / unsigned (s)"),
        ("diff", "max abs diff vs Open3D (voxels)"),
        ("signs", "sign disagreements with Open3D"),
    ]
    rows = _common.case_rows(result["cases"], _rows)
    stem.with_suffix(".md").write_text(_common.markdown_table(rows, columns) + "\n")
    fig, (ax, trade) = _common.new_figure(2)
    series = [
        ("jaxvox first call", lambda c: c.get("jaxvox", {}).get("first_s")),
        ("jaxvox warm", lambda c: c.get("jaxvox", {}).get("median_s")),
        ("jaxvox warm, compact", lambda c: c.get("jaxvox_compact", {}).get("median_s")),
        ("jaxvox warm, plain process", lambda c: c.get("jaxvox_plain", {}).get("median_s")),
        ("OpenVDB meshToLevelSet", lambda c: c.get("openvdb", {}).get("median_s")),
        ("Open3D exact signed query", lambda c: c.get("open3d", {}).get("signed", {}).get("median_s")),
    ]
    for label, get in series:
        pts = [(c["resolution"], get(c)) for c in result["cases"] if isinstance(get(c), float)]
        if pts:
            ax.plot(*zip(*pts), marker="o", label=label)
    ax.set_xscale("log", base=2)
    ax.set_yscale("log")
    ax.set_xlabel("resolution R (bunny, band 3)")
    ax.set_ylabel("seconds")
    ax.set_title("signed narrow band" if result["signed"] else "unsigned narrow band")
    ax.legend()
    # Speed against accuracy where OpenVDB's values were compared: jaxvox's error is its
    # largest difference from Open3D's exact (float32) distances, OpenVDB's from jaxvox's.
    compared = [c for c in result["cases"] if c.get("openvdb", {}).get("compared")]
    errors = (
        ("jaxvox", "o", lambda c: (c.get("open3d", {}).get("unsigned", {}).get("max_diff_voxels"), c["jaxvox"])),
        ("OpenVDB", "s", lambda c: (c["openvdb"]["compared"]["max_error_voxels"], c["openvdb"])),
    )
    for label, marker, get in errors:
        pts = [(*get(c), c["resolution"]) for c in compared]
        pts = [(x, run["median_s"], r) for x, run, r in pts if isinstance(x, float) and "median_s" in run]
        if pts:
            trade.scatter([p[0] for p in pts], [p[1] for p in pts], marker=marker, label=label)
            for x, y, r in pts:
                trade.annotate(f"{r}^3", (x, y), fontsize=7)
    trade.set(
        xscale="log",
        yscale="log",
        xlabel="largest unsigned distance error at the band voxels (voxels)",
        ylabel="warm seconds",
        title="speed vs distance error (bunny, band 3)",
    )
    if trade.collections:
        trade.legend()
    _common.save_figure(fig, stem.with_suffix(".png"))


if __name__ == "__main__":
    main()
