"""Voxelization time against voxel count, 1024^3 to 16384^3, against the talk's C++.

For each resolution R (default 1024, 2048, 4096, 8192, 16384) on the bunny
(`jv.Grid.fit`, conservative), one fresh worker process voxelizes every region of the
grid with `jaxvox.voxelize.host.region_voxels`, the region loop that `jv.voxelize` and
`jv.mesh_to_dag` run (emit, sort and unique per 1024^3 region; the keys are kept
only as a count, so 16384^3 fits in memory): a first pass (compilation included, unless
the persistent cache is warm) and, up to ``--repeat-max`` (4096), a second pass. Per
pass: seconds, voxels, nanoseconds per voxel, and the time in each host step (the
emit calls; the host sort, on a worker thread beside the next region's emits), from
wrappers around them. With
``--hako PATH`` (the seed author's single-threaded C++ from ``shared/anchors/hako``, built
with its README), the same run also times its voxelize + sort + unique (median of 3; up
to ``--hako-max``, 8192), on its own grid fit (bounding-box minimum, longest side / R,
so its voxel counts differ slightly); the ratio is per voxel. Up to ``--build-max``
(4096) the worker also times the public calls on the voxels in memory, `jv.voxelize` and
`jv.build_dag` (first call with its XLA compilations, after the region loop's passes
have compiled the voxelizer's programs, and the best of two more), beside the C++'s voxelize + sort +
unique and its DAG build (`buildDAGReference`) from the same run of it. Every worker
asks for huge pages (`_common`); up to ``--build-max`` a second worker in a plain process
(as a user's `python` or notebook starts) times the same public calls, its first call
compiling the voxelizer's programs.

Writes ``voxelize_scaling[_smoke].json``, ``.md`` and ``.png`` (time against voxels,
log-log, with a line of slope 1; ns per voxel against R) in ``--out``.

Examples:
  python experiments/voxelize_scaling.py --hako /tmp/hako/hako-bench
  python experiments/voxelize_scaling.py --hako /tmp/hako/hako-bench --resolutions 8192 16384 --update
  python experiments/voxelize_scaling.py --smoke
"""

from __future__ import annotations

import json
import subprocess
import time
from pathlib import Path

import _common

STEPS = ("_emit_chunk", "_sort_region")


def worker(spec: dict) -> dict:
    import jax

    import jaxvox as jv
    from jaxvox.voxelize import host

    spent: dict[str, float] = {}

    def timed(name):
        inner = getattr(host, name)

        def call(*args, **kwargs):
            start = time.perf_counter()
            out = jax.block_until_ready(inner(*args, **kwargs))
            spent[name] = spent.get(name, 0.0) + time.perf_counter() - start
            return out

        return call

    for name in STEPS:
        setattr(host, name, timed(name))
    mesh = jv.load_mesh(spec["mesh"])
    grid = jv.Grid.fit(mesh, spec["resolution"])
    passes, voxels, regions = [], 0, 0
    for _ in range(0 if spec.get("public_only") else 2 if spec["resolution"] <= spec["repeat_max"] else 1):
        spent.clear()
        before, start = _common.compile_count(), time.perf_counter()
        voxels = regions = 0
        for _, _, keys, _ in host.region_voxels(
            mesh, grid, six_sep=False, region_size=min(1024, grid.resolution), triangle_ids=False, progress=False
        ):
            voxels += len(keys)
            regions += 1
        seconds = time.perf_counter() - start
        compiles = _common.compile_count() - before
        passes.append(dict(seconds=seconds, ns_per_voxel=1e9 * seconds / voxels, steps=dict(spent), compiles=compiles))
    out = dict(voxels=voxels, regions=regions, passes=passes, environment=_common.environment())
    if spec["resolution"] <= spec["build_max"]:  # the public calls, the voxels in memory: first and warm
        for name, call in (("voxelize", lambda: jv.voxelize(mesh, grid)), ("build_dag", lambda: jv.build_dag(vox))):
            times, compiles = [], []
            for _ in range(3):
                before, start = _common.compile_count(), time.perf_counter()
                result = jax.block_until_ready(call())
                times.append(time.perf_counter() - start)
                compiles.append(_common.compile_count() - before)
                if name == "voxelize":
                    vox = result
            out[name] = dict(
                first_s=times[0], warm_s=min(times[1:]), times_s=times, compiles_first=compiles[0], compiles=compiles
            )
        del vox, result
    return dict(out, peak_rss_mib=_common.peak_rss_mib())


def hako(path: str, mesh: str, resolution: int) -> dict:
    out = subprocess.run(
        [path, mesh, "--res", str(resolution), "--dag-only", "--reps", "3"],
        stdout=subprocess.PIPE,
        text=True,
        check=True,
    ).stdout
    line = json.loads(next(x for x in out.splitlines() if x.startswith("{")))
    return dict(voxels=line["voxels"], seconds=line["voxelize_total_ms"] / 1e3, dag_seconds=line["dag_build_ms"] / 1e3)


def table(cases: list[dict]) -> str:
    columns = [
        ("R", "R"),
        ("voxels", "voxels"),
        ("first", "first pass (s, compiles)"),
        ("warm", "second pass (s)"),
        ("ns", "ns/voxel"),
        ("steps", "emit / sort (s)"),
        ("peak", "peak RSS (MiB)"),
        ("hako", "C++ (s, voxels)"),
        ("ratio", "jaxvox / C++ per voxel"),
        ("voxelize", "jv.voxelize first (compiles) / warm (s)"),
        ("voxelize_ratio", "jv.voxelize warm / C++"),
        ("plain_voxelize", "plain process: jv.voxelize first (compiles) / warm (s), warm / C++"),
        ("dag", "jv.build_dag first (compiles) / warm (s)"),
        ("hako_dag", "C++ DAG (s)"),
        ("dag_ratio", "build_dag warm / C++"),
        ("plain_dag", "plain process: jv.build_dag first (compiles) / warm (s), warm / C++"),
    ]
    rows = []
    for c in cases:
        best = c["passes"][-1]
        steps = best["steps"]
        row = dict(
            R=c["resolution"],
            voxels=f"{c['voxels']:,}",
            first=f"{c['passes'][0]['seconds']:.2f} ({c['passes'][0].get('compiles', '-')})",
            warm=f"{c['passes'][1]['seconds']:.2f}" if len(c["passes"]) > 1 else "-",
            ns=f"{best['ns_per_voxel']:.0f}",
            steps=" / ".join(f"{steps.get(s, 0):.2f}" for s in STEPS),
            peak=f"{c['peak_rss_mib']:.0f}",
        )
        h = c.get("hako") or {}
        for name, key, base in (("voxelize", "voxelize", "seconds"), ("dag", "build_dag", "dag_seconds")):
            for prefix, timed in (("", c), ("plain_", c.get("plain", {}))):
                if key in timed:
                    t = timed[key]
                    row[prefix + name] = f"{t['first_s']:.2f} ({t.get('compiles_first', '-')}) / {t['warm_s']:.2f}"
                    if prefix and base in h:
                        row[prefix + name] += f", {t['warm_s'] / h[base]:.2f}x"
        if c.get("hako"):
            h = c["hako"]
            row["hako"] = f"{h['seconds']:.2f} ({h['voxels']:,})"
            row["ratio"] = f"{best['ns_per_voxel'] / (1e9 * h['seconds'] / h['voxels']):.2f}x"
            if "dag_seconds" in h:
                row["hako_dag"] = f"{h['dag_seconds']:.2f}"
            if "voxelize" in c:
                row["voxelize_ratio"] = f"{c['voxelize']['warm_s'] / h['seconds']:.2f}x"
            if "build_dag" in c and "dag_seconds" in h:
                row["dag_ratio"] = f"{c['build_dag']['warm_s'] / h['dag_seconds']:.2f}x"
        rows.append(row)
    return _common.markdown_table(rows, columns)


def plot(cases: list[dict], path: Path) -> None:
    fig, (ax_time, ax_ns) = _common.new_figure(2)
    voxels = [c["voxels"] for c in cases]
    for label, pick in (("jaxvox, first pass", 0), ("jaxvox, best pass", -1)):
        ax_time.plot(voxels, [c["passes"][pick]["seconds"] for c in cases], marker="o", label=label)
        ax_ns.plot(
            [c["resolution"] for c in cases],
            [c["passes"][pick]["ns_per_voxel"] for c in cases],
            marker="o",
            label=label,
        )
    with_hako = [c for c in cases if c.get("hako")]
    if with_hako:
        ax_time.plot(
            [c["hako"]["voxels"] for c in with_hako],
            [c["hako"]["seconds"] for c in with_hako],
            marker="s",
            label="talk's C++ (1 thread)",
        )
        ax_ns.plot(
            [c["resolution"] for c in with_hako],
            [1e9 * c["hako"]["seconds"] / c["hako"]["voxels"] for c in with_hako],
            marker="s",
            label="talk's C++ (1 thread)",
        )
    base = cases[0]
    ax_time.plot(
        voxels, [base["passes"][-1]["seconds"] * v / base["voxels"] for v in voxels], "k:", label="linear in voxels"
    )
    ax_time.set(xscale="log", yscale="log", xlabel="voxels", ylabel="seconds", title="bunny: voxelization time")
    ax_ns.set(xscale="log", xlabel="resolution R", ylabel="ns per voxel", title="time per voxel")
    ax_ns.set_xticks([c["resolution"] for c in cases], [str(c["resolution"]) for c in cases])
    for ax in (ax_time, ax_ns):
        ax.grid(True, which="both", alpha=0.3)
        ax.legend(fontsize=8)
    _common.save_figure(fig, path)


def main() -> None:
    parser = _common.experiment_parser(__doc__)
    parser.add_argument("--repeat-max", type=int, default=4096)
    parser.add_argument("--hako", help="path of the hako-bench binary (shared/anchors/hako)")
    parser.add_argument("--hako-max", type=int, default=8192)
    parser.add_argument(
        "--build-max", type=int, default=4096, help="largest R at which jv.voxelize and jv.build_dag are timed"
    )
    parser.add_argument("--update", action="store_true", help="replace only these resolutions' rows in the JSON")
    args = parser.parse_args()
    if _common.answer_as_worker(args, worker):
        return
    resolutions = args.resolutions or ([128, 256] if args.smoke else [1024, 2048, 4096, 8192, 16384])
    mesh = str(_common.MESH_DIR / "stanford-bunny.obj")
    cases = []
    for r in resolutions:
        spec = dict(mesh=mesh, resolution=r, repeat_max=args.repeat_max, build_max=args.build_max)
        case = dict(_common.run_worker(__file__, spec, timeout=args.timeout), resolution=r)
        if "error" in case:
            print(json.dumps(case), flush=True)
            continue
        if r <= args.build_max:  # the public calls again, in a plain process (no huge pages)
            plain = _common.run_worker(__file__, dict(spec, public_only=True), timeout=args.timeout, plain=True)
            case["plain"] = {
                k: plain[k] for k in ("voxelize", "build_dag", "environment", "peak_rss_mib") if k in plain
            }
        if args.hako and r <= args.hako_max:
            case["hako"] = hako(args.hako, mesh, r)
        cases.append(case)
        print(table([case]).splitlines()[-1], flush=True)
    name = "voxelize_scaling_smoke" if args.smoke else "voxelize_scaling"
    path = args.out / f"{name}.json"
    if args.update and path.exists():  # keep the other resolutions' rows of the last run
        last = {c["resolution"]: c for c in json.loads(path.read_text())["cases"]}
        cases = sorted([c for r, c in last.items() if r not in resolutions] + cases, key=lambda c: c["resolution"])
    _common.write_json(path, dict(cases=cases, machine=_common.machine_info(["jax", "jaxlib", "numpy"])))
    (args.out / f"{name}.md").write_text(table(cases))
    plot(cases, args.out / f"{name}.png")
    print(table(cases))


if __name__ == "__main__":
    main()
