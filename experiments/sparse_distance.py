"""Sparse narrow-band distance fields: jaxvox against OpenVDB's meshToLevelSet on the bunny.

For each resolution R (default 256 and 1024), on ``jv.Grid.fit(bunny, resolution=R)``
with half width ``--band`` (3) voxels:

* jaxvox: `jv.sparse_distance_field` (first call on a fresh process, compilation
  included, then the median of ``--repeats`` warmed-up calls) and the band voxel count.
  The bunny has open edges, so the signed field takes the brute-force winding number
  (O(band voxels x F), far too slow at these sizes); by default the *unsigned* field is
  timed (``--signed`` times the signed one);
* OpenVDB: ``FloatGrid.createLevelSetFromPolygons`` (meshToLevelSet) with the same voxel
  size and half width, run by the system ``/usr/bin/python3`` (Debian ``python3-openvdb``)
  in a subprocess, timed there; ``{"error": ...}`` when it is not installed.

Each case runs in a fresh process. Writes experiments/results/sparse_distance[_smoke].json.

Examples:
  python experiments/sparse_distance.py --smoke      # R = 64
  python experiments/sparse_distance.py              # R = 256, 1024
"""

from __future__ import annotations

import argparse
import json
import subprocess
import textwrap

import _common

SYSTEM_PYTHON = "/usr/bin/python3"
_OPENVDB = textwrap.dedent(
    """
    import json, sys, time
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
    v = np.asarray(v, np.float32)
    f = np.asarray(f, np.int32)
    xform = vdb.createLinearTransform(voxelSize=spec["voxel_size"])
    times = []
    for _ in range(spec["repeats"] + 1):
        t = time.perf_counter()
        grid = vdb.FloatGrid.createLevelSetFromPolygons(v, triangles=f, transform=xform, halfWidth=spec["band"])
        times.append(time.perf_counter() - t)
    print(json.dumps(dict(first_s=times[0], median_s=float(np.median(times[1:])), voxels=int(grid.activeVoxelCount()))))
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
        return {"error": (proc.stderr.strip().splitlines() or ["failed"])[-1]}
    return json.loads(proc.stdout.strip().splitlines()[-1])


def worker(spec: dict) -> dict:
    import jax

    import jaxvox as jv

    mesh = jv.load_mesh(spec["mesh"])
    grid = jv.Grid.fit(mesh, resolution=spec["resolution"])
    run = lambda: jax.block_until_ready(jv.sparse_distance_field(mesh, grid, band=spec["band"], signed=spec["signed"]))
    timing, field = _common.time_calls(run, spec["repeats"])
    n = int(field.count)
    return dict(
        jaxvox=dict(timing, voxels=n, value_bytes=4 * n, peak_rss_mib=_common.peak_rss_mib()),
        voxel_size=float(grid.voxel_size),
    )


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    parser.add_argument("--worker")
    parser.add_argument("--smoke", action="store_true")
    parser.add_argument("--resolutions", type=int, nargs="*", default=None)
    parser.add_argument("--band", type=int, default=3)
    parser.add_argument("--repeats", type=int, default=2)
    parser.add_argument("--signed", action="store_true")
    parser.add_argument("--timeout", type=float, default=1800)
    args = parser.parse_args()
    if _common.answer_as_worker(args, worker):
        return
    resolutions = args.resolutions or ([64] if args.smoke else [256, 1024])
    mesh = str(_common.MESH_DIR / "stanford-bunny.obj")
    cases = []
    for r in _common.progress(resolutions, desc="resolutions"):
        spec = dict(mesh=mesh, resolution=r, band=args.band, repeats=args.repeats, signed=args.signed)
        case = dict(_common.run_worker(__file__, spec, timeout=args.timeout), resolution=r)
        if "voxel_size" in case:
            peer = dict(mesh=mesh, voxel_size=case["voxel_size"], band=args.band, repeats=args.repeats)
            case["openvdb"] = _openvdb(peer, args.timeout)
        cases.append(case)
        print(json.dumps(case))
    name = "sparse_distance_smoke" if args.smoke else "sparse_distance"
    _common.write_json(
        _common.RESULTS_DIR / f"{name}.json",
        dict(
            band=args.band,
            signed=args.signed,
            cases=cases,
            machine=_common.machine_info(["jax", "jaxlib", "numpy"]),
        ),
    )


if __name__ == "__main__":
    main()
