"""The DAG build split over processes: ``jaxvox build --processes N`` against one process.

For each resolution R (default 1024, 2048, 4096) and each process count in ``--processes``
(default 1 and 2), one fresh worker runs ``jaxvox build bunny --resolution R --region S
--processes N`` (S: ``--region``, default 256, so that there are regions to split below
4096^3; the one-process run streams the same regions) and records the command's wall
time, the build time it reports (voxelization and DAG, first call), the largest resident
peak of its processes (``ru_maxrss`` of the worker's children: the launcher and the N
build processes, which are local jax.distributed processes with CPU collectives over
gloo), and the SHA-256 of the file written, which must be the same for every N. Then,
for each device count in ``--devices`` (default 1 and 2), one process runs
``jv.mesh_to_dag(mesh, grid, region=S, distributed=True)`` with that many local CPU devices
(``jax_num_cpu_devices``; a thread per device): a first and a second call, and whether
the tables are those of one device.

Writes ``distributed_build[_smoke].json``, ``.md`` and ``.png`` (wall time and build time
against N per R) in ``--out``.

Examples:
  python experiments/distributed_build.py                  # R = 1024, 2048, 4096; N = 1, 2
  python experiments/distributed_build.py --smoke          # R = 128, 256
"""

from __future__ import annotations

import hashlib
import json
import os
import re
import resource
import subprocess
import sys
import tempfile
import time
from pathlib import Path

import _common


def worker(spec: dict) -> dict:
    if spec.get("devices"):
        return devices_worker(spec)
    with tempfile.TemporaryDirectory() as folder:
        out = os.path.join(folder, "tree.jvx")
        command = [sys.executable, "-m", "jaxvox", "build", spec["mesh"], "--resolution", str(spec["resolution"])]
        command += ["--region", str(spec["region"]), "--processes", str(spec["processes"]), "--out", out]
        start = time.perf_counter()
        proc = subprocess.run(command, stdout=subprocess.PIPE, text=True)
        wall = time.perf_counter() - start
        if proc.returncode:
            return {"error": f"jaxvox build exited with status {proc.returncode}"}
        digest = hashlib.sha256()
        with open(out, "rb") as fh:
            for block in iter(lambda: fh.read(1 << 24), b""):
                digest.update(block)
        size = os.path.getsize(out)
    built = re.search(r"([\d,]+) voxels .* built in ([\d.]+) s", proc.stdout)
    return dict(
        wall_s=wall,
        build_s=float(built.group(2)) if built else None,
        voxels=int(built.group(1).replace(",", "")) if built else None,
        file_bytes=size,
        file_sha256=digest.hexdigest(),
        largest_process_peak_mib=resource.getrusage(resource.RUSAGE_CHILDREN).ru_maxrss / 1024.0,
        stdout=proc.stdout,
    )


def devices_worker(spec: dict) -> dict:
    """`jv.mesh_to_dag(distributed=True)` in this one process with ``spec["devices"]`` local
    CPU devices (a thread each): seconds of a first and a second call, and the tables' hash."""
    import jax

    jax.config.update("jax_num_cpu_devices", spec["devices"])
    import numpy as np

    import jaxvox as jv

    mesh = jv.load_mesh(spec["mesh"])
    grid = jv.Grid.fit(mesh, spec["resolution"])
    times = []
    for _ in range(2):
        start = time.perf_counter()
        dag = jv.mesh_to_dag(mesh, grid, region=spec["region"], distributed=True, progress=False)
        dag.mask.block_until_ready()
        times.append(time.perf_counter() - start)
    digest = hashlib.sha256()
    for leaf in (dag.mask, dag.child, dag.prefix):
        digest.update(np.ascontiguousarray(np.asarray(leaf)).tobytes())
    return dict(
        first_s=times[0],
        second_s=times[1],
        voxels=int(dag.voxel_count),
        tables_sha256=digest.hexdigest(),
        peak_rss_mib=_common.peak_rss_mib(),
        local_devices=len(jax.local_devices()),
    )


def _table(cases: list[dict], split: str, speed_key: str, same_key: str, columns, cells) -> str:
    """Markdown: one row per case with `cells(case)`, the speed-up of `speed_key` and
    whether `same_key` matches the case with ``split == 1`` at the same resolution."""
    rows = []
    for c in cases:
        if "error" in c:
            rows.append({"resolution": c["resolution"], split: c[split], "first": c["error"]})
            continue
        one = next(o for o in cases if o["resolution"] == c["resolution"] and o[split] == 1)
        rows.append(
            dict(
                resolution=c["resolution"],
                **{split: c[split]},
                **cells(c),
                speedup=f"{one[speed_key] / c[speed_key]:.2f}x",
                same=str(c[same_key] == one[same_key]),
            )
        )
    return _common.markdown_table(rows, [("resolution", "R"), *columns])


def devices_table(cases: list[dict]) -> str:
    columns = [
        ("devices", "local devices (threads)"),
        ("first", "first call (s)"),
        ("second", "second call (s)"),
        ("speedup", "speed-up"),
        ("peak", "peak RSS (MiB)"),
        ("same", "same tables as 1 device"),
    ]
    cells = lambda c: dict(first=f"{c['first_s']:.1f}", second=f"{c['second_s']:.1f}", peak=f"{c['peak_rss_mib']:.0f}")
    return _table(cases, "devices", "second_s", "tables_sha256", columns, cells)


def table(cases: list[dict]) -> str:
    columns = [
        ("processes", "processes"),
        ("voxels", "voxels"),
        ("wall", "wall (s)"),
        ("build", "build (s)"),
        ("speedup", "build speed-up"),
        ("peak", "largest process peak (MiB)"),
        ("mib", "file (MiB)"),
        ("same", "same file as 1 process"),
    ]
    cells = lambda c: dict(
        voxels=f"{c['voxels']:,}",
        wall=f"{c['wall_s']:.1f}",
        build=f"{c['build_s']:.1f}",
        peak=f"{c['largest_process_peak_mib']:.0f}",
        mib=f"{c['file_bytes'] / 2**20:.1f}",
    )
    return _table(cases, "processes", "build_s", "file_sha256", columns, cells)


def plot(cases: list[dict], path: Path) -> None:
    fig, (ax,) = _common.new_figure(1)
    ok = [c for c in cases if "error" not in c]
    resolutions = sorted({c["resolution"] for c in ok})
    counts = sorted({c["processes"] for c in ok})
    width = 0.8 / len(counts)
    for i, n in enumerate(counts):
        for key, hatch in (("wall_s", ""), ("build_s", "//")):
            xs = [k + i * width for k, r in enumerate(resolutions)]
            ys = [next(c[key] for c in ok if c["resolution"] == r and c["processes"] == n) for r in resolutions]
            ax.bar(
                xs,
                ys,
                width * (0.9 if key == "wall_s" else 0.6),
                color=f"C{i}",
                hatch=hatch,
                alpha=0.9 - 0.3 * bool(hatch),
            )
        ax.bar([], [], color=f"C{i}", label=f"{n} process{'es' if n > 1 else ''}")
    ax.bar([], [], color="white", edgecolor="black", hatch="//", label="build time it reports (inner bar)")
    ax.set_xticks([k + 0.4 - width / 2 for k in range(len(resolutions))], [f"{r}^3" for r in resolutions])
    ax.set(ylabel="seconds", title="jaxvox build, bunny: wall time (outer) and build time (inner)")
    ax.legend(fontsize=8)
    _common.save_figure(fig, path)


def main() -> None:
    parser = _common.experiment_parser(__doc__)
    parser.add_argument("--processes", type=int, nargs="*", default=[1, 2])
    parser.add_argument("--region", type=int, default=256)
    parser.add_argument("--devices", type=int, nargs="*", default=[1, 2], help="local CPU device counts (threads)")
    args = parser.parse_args()
    if _common.answer_as_worker(args, worker):
        return
    resolutions = args.resolutions or ([128, 256] if args.smoke else [1024, 2048, 4096])
    region = 32 if args.smoke else args.region
    mesh = str(_common.MESH_DIR / "stanford-bunny.obj")
    cases = []
    for r in resolutions:
        for n in sorted(args.processes):
            spec = dict(mesh=mesh, resolution=r, processes=n, region=min(region, r))
            case = dict(_common.run_worker(__file__, spec, timeout=args.timeout), resolution=r, processes=n)
            cases.append(case)
            print(json.dumps({k: v for k, v in case.items() if k != "stdout"}), flush=True)
    device_cases = []
    for r in resolutions:
        for n in sorted(args.devices):
            spec = dict(mesh=mesh, resolution=r, devices=n, region=min(region, r))
            case = dict(_common.run_worker(__file__, spec, timeout=args.timeout), resolution=r, devices=n)
            device_cases.append(case)
            print(json.dumps(case), flush=True)
    name = "distributed_build_smoke" if args.smoke else "distributed_build"
    _common.write_json(
        args.out / f"{name}.json",
        dict(
            cases=cases,
            device_cases=device_cases,
            settings=dict(region=region),
            machine=_common.machine_info(["jax", "jaxlib"]),
        ),
    )
    report = table(cases) + "\nOne process, regions split over local CPU devices (`mesh_to_dag(distributed=True)`):\n\n"
    report += devices_table(device_cases)
    (args.out / f"{name}.md").write_text(report)
    plot(cases, args.out / f"{name}.png")
    print(report)


if __name__ == "__main__":
    main()
