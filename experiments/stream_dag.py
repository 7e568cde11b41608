"""Streaming DAG build: peak memory and time of `jv.mesh_to_dag` against the in-memory build.

For each resolution R (default 1024 and 8192) on ``jv.Grid.fit(bunny, resolution=R)``, one
fresh process per case: ``jv.mesh_to_dag(mesh, grid)`` (``stream``) and, up to
``--whole-max`` (default 1024), ``jv.build_dag(jv.voxelize(mesh, grid))`` (``whole``), each
timed once (first call, compilation included unless the persistent cache is warm), with
the process's peak resident memory (VmHWM), the voxel count and the DAG's compact bytes;
at the resolutions where both run, whether their tables are identical.

Writes experiments/results/stream_dag[_smoke].json and .md.

Examples:
  python experiments/stream_dag.py --smoke             # R = 128, 256
  python experiments/stream_dag.py                     # R = 1024, 8192
"""

from __future__ import annotations

import argparse
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
    small = jv.compact(tree)
    digest = hashlib.sha256()
    for leaf in (small.mask, small.child, small.prefix):
        digest.update(np.ascontiguousarray(np.asarray(leaf)).tobytes())
    return dict(
        seconds=seconds,
        voxels=int(tree.voxel_count),
        dag_mib=small.compact_nbytes / 2**20,
        peak_rss_mib=_common.peak_rss_mib(),
        tables_sha256=digest.hexdigest(),
    )


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    parser.add_argument("--worker")
    parser.add_argument("--smoke", action="store_true")
    parser.add_argument("--resolutions", type=int, nargs="*", default=None)
    parser.add_argument("--whole-max", type=int, default=1024)
    parser.add_argument("--timeout", type=float, default=3600)
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
            spec = dict(mesh=mesh, resolution=r, kind=kind)
            case = dict(_common.run_worker(__file__, spec, timeout=args.timeout), resolution=r, kind=kind)
            cases.append(case)
            print(case, flush=True)
    for r in resolutions:
        both = [c for c in cases if c["resolution"] == r and "tables_sha256" in c]
        if len(both) == 2:
            for c in both:
                c["same_tables"] = both[0]["tables_sha256"] == both[1]["tables_sha256"]
    name = "stream_dag_smoke" if args.smoke else "stream_dag"
    _common.write_json(_common.RESULTS_DIR / f"{name}.json", dict(cases=cases, machine=_common.machine_info(["jax"])))
    columns = [
        ("resolution", "R"),
        ("kind", "build"),
        ("voxels", "voxels"),
        ("dag_mib", "DAG (MiB)"),
        ("seconds", "time (s)"),
        ("peak_rss_mib", "peak RSS (MiB)"),
        ("same_tables", "same tables"),
    ]
    cell = lambda v: f"{v:.4g}" if isinstance(v, float) else str(v)
    rows = [{k: cell(c.get(k, "-")) for k, _ in columns} for c in cases]
    (_common.RESULTS_DIR / f"{name}.md").write_text(_common.markdown_table(rows, columns) + "\n")


if __name__ == "__main__":
    main()
