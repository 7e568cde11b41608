"""Streaming DAG build: peak memory and time of `jv.mesh_to_dag` against the in-memory build.

For each resolution R (default 1024 and 8192) on ``jv.Grid.fit(bunny, resolution=R)``, one
fresh process per case: ``jv.mesh_to_dag(mesh, grid)`` (``stream``) and, up to
``--whole-max`` (default 1024), ``jv.build_dag(jv.voxelize(mesh, grid))`` (``whole``), each
timed once (first call, compilation included unless the persistent cache is warm), with
the process's peak resident memory (VmHWM), the voxel count and the DAG's compact bytes;
at the resolutions where both run, whether their tables are identical. From
``--trace-from`` (default 8192) on, the streamed DAG is also traced with 1920x1080
primary rays (median of 3 after a first call) and path-traced at 480x270, 4 spp, 2
bounces (experiments/results/stream_dag_R.png), and the peak memory is reported again.

Writes experiments/results/stream_dag[_smoke].json and .md.

Examples:
  python experiments/stream_dag.py --smoke             # R = 128, 256
  python experiments/stream_dag.py                     # R = 1024, 8192
  python experiments/stream_dag.py --resolutions 1024 8192 16384
  python experiments/stream_dag.py --resolutions 32768 --update   # adds a row
"""

from __future__ import annotations

import argparse
import json
import os
import time

import _common


def worker(spec: dict) -> dict:
    import hashlib

    import numpy as np

    import jaxvox as jv

    mesh = jv.load_mesh(spec["mesh"])
    grid = jv.Grid.fit(mesh, resolution=spec["resolution"])
    start = time.perf_counter()
    if spec["kind"] == "stream":
        tree = jv.mesh_to_dag(mesh, grid, progress=False)
    else:
        tree = jv.build_dag(jv.voxelize(mesh, grid, progress=False))
    tree.mask.block_until_ready()
    seconds = time.perf_counter() - start
    build_peak = _common.peak_rss_mib()
    small = jv.compact(tree)
    sparse = {
        name: jv.compact_dag(small, prefix=prefix) for name, prefix in (("sparse", False), ("sparse_prefix", True))
    }
    digest = hashlib.sha256()
    for leaf in (small.mask, small.child, small.prefix):
        digest.update(np.ascontiguousarray(np.asarray(leaf)).tobytes())
    result = dict(
        seconds=seconds,
        voxels=int(tree.voxel_count),
        nodes=small.num_nodes,
        dag_mib=small.compact_nbytes / 2**20,
        bits_per_voxel=8 * small.compact_nbytes / max(int(tree.voxel_count), 1),
        peak_rss_mib=build_peak,
        tables_sha256=digest.hexdigest(),
        **{f"{name}_mib": s.nbytes / 2**20 for name, s in sparse.items()},
        **{f"{name}_bits_per_voxel": 8 * s.nbytes / max(int(tree.voxel_count), 1) for name, s in sparse.items()},
    )
    if spec.get("trace"):
        # Beyond int32 Morton indices only the sparse layout without prefix sums traces.
        indexed = int(tree.voxel_count) <= jv.octree.MAX_INDEXED
        result["traced_layout"] = "dag+prefix" if indexed else "sparse DAG"
        result.update(_trace_and_render(jv, mesh, small if indexed else sparse["sparse"], spec))
    return result


def _trace_and_render(jv, mesh, tree, spec: dict) -> dict:
    """1920x1080 primary rays at the DAG (first call and median of 3 compiled calls, hit
    count) and a small path-traced image written to experiments/results/."""
    import jax
    import jax.numpy as jnp
    import numpy as np

    eye, target = jv.look_at_view(mesh)
    width, height = 1920, 1080
    o, d = (jnp.reshape(x, (-1, 3)) for x in jv.pinhole_rays(eye, target, width=width, height=height))
    timing, hit = _common.time_calls(lambda: jax.block_until_ready(jv.trace(tree, o, d)), 3)
    start = time.perf_counter()
    image = jv.render(tree, eye, target, width=480, height=270, spp=4, bounces=2, key=0, progress=False)
    render_s = time.perf_counter() - start
    exr, png = jv.save_render(_common.RESULTS_DIR / f"stream_dag_{spec['resolution']}.exr", image)
    os.remove(exr)  # the PNG is the record
    return dict(
        trace_first_s=timing["first_s"],
        trace_median_s=timing["median_s"],
        trace_mrays_s=width * height / timing["median_s"] / 1e6,
        trace_hits=int(np.sum(np.asarray(hit.status) == jv.HIT)),
        render_s=render_s,
        render_png=os.path.basename(png),
        render_stopped=int(image.stopped),
        peak_rss_with_trace_mib=_common.peak_rss_mib(),
    )


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    parser.add_argument("--worker")
    parser.add_argument("--smoke", action="store_true")
    parser.add_argument("--resolutions", type=int, nargs="*", default=None)
    parser.add_argument("--whole-max", type=int, default=1024)
    parser.add_argument("--update", action="store_true", help="merge into the existing JSON and table")
    parser.add_argument("--timeout", type=float, default=3600)
    parser.add_argument(
        "--trace-from", type=int, default=8192, help="trace 1920x1080 rays and render the stream DAG from this R on"
    )
    args = parser.parse_args()
    if _common.answer_as_worker(args, worker):
        return
    resolutions = args.resolutions or ([128, 256] if args.smoke else [1024, 8192])
    mesh = str(_common.MESH_DIR / "stanford-bunny.obj")
    cases = []
    for r in _common.progress(resolutions, desc="resolutions"):
        for kind in ("stream", "whole"):
            if kind == "whole" and r > args.whole_max:
                continue
            spec = dict(mesh=mesh, resolution=r, kind=kind, trace=kind == "stream" and r >= args.trace_from)
            case = dict(_common.run_worker(__file__, spec, timeout=args.timeout), resolution=r, kind=kind)
            cases.append(case)
            print(case, flush=True)
    for r in resolutions:
        both = [c for c in cases if c["resolution"] == r and "tables_sha256" in c]
        if len(both) == 2:
            for c in both:
                c["same_tables"] = both[0]["tables_sha256"] == both[1]["tables_sha256"]
    name = "stream_dag_smoke" if args.smoke else "stream_dag"
    if args.update:  # keep the earlier cases that were not run again
        old = json.loads((_common.RESULTS_DIR / f"{name}.json").read_text())["cases"]
        done = {(c["resolution"], c["kind"]) for c in cases}
        cases = sorted(
            [c for c in old if (c["resolution"], c["kind"]) not in done] + cases,
            key=lambda c: (c["resolution"], c["kind"]),
        )
    _common.write_json(_common.RESULTS_DIR / f"{name}.json", dict(cases=cases, machine=_common.machine_info(["jax"])))
    columns = [
        ("resolution", "R"),
        ("kind", "build"),
        ("voxels", "voxels"),
        ("dag_mib", "DAG (MiB)"),
        ("nodes", "nodes"),
        ("bits_per_voxel", "bits/voxel"),
        ("sparse_bits_per_voxel", "sparse DAG bits/voxel"),
        ("seconds", "time (s)"),
        ("peak_rss_mib", "peak RSS (MiB)"),
        ("trace_first_s", "1080p first call (s)"),
        ("trace_mrays_s", "1080p Mrays/s"),
        ("traced_layout", "traced"),
        ("peak_rss_with_trace_mib", "peak RSS with tracing (MiB)"),
        ("render_s", "render 480x270x4 (s)"),
        ("same_tables", "same tables"),
    ]
    cell = lambda v: f"{v:.4g}" if isinstance(v, float) else str(v)
    rows = [{k: cell(c.get(k, "-")) for k, _ in columns} for c in cases]
    (_common.RESULTS_DIR / f"{name}.md").write_text(_common.markdown_table(rows, columns) + "\n")


if __name__ == "__main__":
    main()
