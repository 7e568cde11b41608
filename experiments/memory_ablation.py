"""Memory ablation: bytes of voxel layouts from a dense bit grid to a DAG with prefix sums.

For each mesh and resolution R a fresh subprocess voxelizes the mesh (conservative,
`jv.Grid.fit`), builds the sparse voxel octree and the DAG with `jv.build_octree` and
`jv.build_dag` (build times: the first call, which includes compilation, and the median
of ``--repeats`` further calls), and reports node counts per level and the bytes of:

==================  ===================================================================
layout              bytes
==================  ===================================================================
dense bits          R^3 / 8: one bit per voxel
spc                 1 byte per octree node (kaolin's SPC: masks only, children found by
                    an exclusive sum of popcounts computed at load time)
spc+exsum           5 bytes per octree node (masks plus kaolin's stored int32 exclusive sum)
octree-33B          every node as a mask + 8 uint32 pointers (33 bytes), the level above the
                    voxels included: the slides' count (955 MB vs 61 MB for the Asian
                    Dragon at 8192^3 is this layout's octree/DAG ratio, i.e. the node ratio)
octree              jaxvox's table without prefix sums: 1 byte per node + 8 uint32
                    pointers per node above the mask-only level (the slides' naive layout)
octree+prefix       ``svo.compact_nbytes``: the above plus 8 uint32 prefix sums per inner node
octree-sparse       1 byte + 1 uint32 first-child pointer per inner node, 1 byte per
                    mask-only node (an octree's children are consecutive)
dag-33B             the DAG, 33 bytes per node
dag                 the DAG in jaxvox's table without prefix sums
dag+prefix          ``dag.compact_nbytes``: jaxvox's DAG as saved (no ladder padding)
dag-sparse          `jv.compact_dag` without prefix sums, as built (``CompactDag.nbytes``):
                    per node above the mask-only level a uint32 mask word and one uint32
                    per present child, addressed by the popcount of the mask bits below
                    the slot; a child at the mask-only level is stored as its mask, so
                    that level takes no bytes of its own
dag-sparse+prefix   `jv.compact_dag` with prefix sums: the above plus a uint32 prefix sum
                    per present child but the first (always 0)
==================  ===================================================================

The SVO layouts' sizes and the DAG's 33-byte count are computed from the built trees'
masks (exact popcounts); the DAG tables and the sparse DAGs are the arrays themselves.
Bits per voxel divide each size by the voxel count.

Speed against bytes (the first mesh, ``--trace``): 1920x1080 primary rays of
`jv.look_at_view` traced by `jv.trace` (esvo, the default lanes, all CPU devices) on
every layout that traverses: the SVO's and the DAG's 8-slot tables (``octree+prefix``,
``dag+prefix``) and the two sparse DAGs. Mrays/s is the median of 3 calls after a first
call (reported with its compilation); every layout must give the same hits.

Resolutions in ``--stream`` (first mesh; default 8192 and 16384) build the DAG with
`jv.mesh_to_dag` (regions, never the whole voxel list), so they have no SVO columns.
Above 2^31 - 1 voxels (32768^3) only the sparse DAG without prefix sums is traced: the
other layouts' hits carry int32 Morton indices.

Outputs ``memory_ablation.json`` (all numbers and the machine), ``.png`` (bytes against
resolution for the first mesh; octree/DAG ratio and bits per voxel for every mesh) and
``.md`` (tables) in ``--out``.

Examples:
  python experiments/memory_ablation.py                     # 8 meshes up to 2048^3, the bunny to 16384^3
  python experiments/memory_ablation.py --smoke             # R = 64, 128 on two meshes
  python experiments/memory_ablation.py --meshes stanford-bunny --resolutions 8192
  python experiments/memory_ablation.py --meshes stanford-bunny --resolutions 1024 --huge --stream --update
"""

from __future__ import annotations

import argparse
import json
import sys
from pathlib import Path

import _common
import numpy as np

ALL_MESHES = ("stanford-bunny", "spot", "teapot", "suzanne", "fandisk", "cow", "woody", "beetle")
LAYOUTS = (
    "dense bits",
    "spc",
    "spc+exsum",
    "octree-33B",
    "octree",
    "octree+prefix",
    "octree-sparse",
    "dag-33B",
    "dag",
    "dag+prefix",
    "dag-sparse",
    "dag-sparse+prefix",
)


def layout_bytes(svo, dag, sparse: dict, resolution: int) -> dict[str, int | None]:
    """Bytes of every layout in the module docstring, from the built trees (`svo` None:
    the SVO layouts are None)."""

    def parts(tree):
        sizes = tree.level_sizes
        nodes, inner = sum(sizes), sum(sizes[:-1])
        children = int(np.unpackbits(np.asarray(tree.mask[:inner])[:, None], axis=1).sum())
        return nodes, inner, sizes[-1], children

    d_nodes, d_inner, _, _ = parts(dag)
    sizes: dict[str, int | None] = dict.fromkeys(LAYOUTS)
    if svo is not None:
        s_nodes, s_inner, _, _ = parts(svo)
        sizes.update(
            {
                "spc": s_nodes,
                "spc+exsum": 5 * s_nodes,
                "octree-33B": 33 * s_nodes,
                "octree": s_nodes + 32 * s_inner,
                "octree+prefix": svo.compact_nbytes,
                "octree-sparse": s_nodes + 4 * s_inner,
            }
        )
    sizes.update(
        {
            "dense bits": resolution**3 // 8,
            "dag-33B": 33 * d_nodes,
            "dag": d_nodes + 32 * d_inner,
            "dag+prefix": dag.compact_nbytes,
            "dag-sparse": sparse["dag-sparse"].nbytes,
            "dag-sparse+prefix": sparse["dag-sparse+prefix"].nbytes,
        }
    )
    return sizes


def trace_layouts(mesh, layouts: dict, repeats: int = 3) -> dict:
    """1920x1080 primary rays on every layout: {layout: timing with Mrays/s}, and whether
    all layouts gave the same hits (status, voxel, t)."""
    import jax
    import jax.numpy as jnp

    import jaxvox as jv

    eye, target = jv.look_at_view(mesh)
    o, d = (jnp.reshape(x, (-1, 3)) for x in jv.pinhole_rays(eye, target, width=1920, height=1080))
    timings, hits = {}, []
    for name, tree in layouts.items():
        timing, hit = _common.time_calls(lambda: jax.block_until_ready(jv.trace(tree, o, d)), repeats)
        timings[name] = dict(timing, mrays_s=o.shape[0] / timing["median_s"] / 1e6)
        hits.append([np.asarray(x) for x in (hit.status, hit.voxel, hit.t)])
    same = all(all(np.array_equal(a, b) for a, b in zip(h, hits[0])) for h in hits)
    return dict(timings=timings, same_hits=same, hit_pixels=int((hits[0][0] == jv.HIT).sum()))


def worker(spec: dict) -> dict:
    """One (mesh, resolution) case in this process; returns its row."""
    import jax

    import jaxvox as jv

    mesh = jv.load_mesh(spec["path"])
    resolution = spec["resolution"]
    grid = jv.Grid.fit(mesh, resolution)
    trees, timings = {"octree": None}, {"octree": None}
    if spec.get("stream"):
        timing, dag = _common.time_calls(lambda: jax.block_until_ready(jv.mesh_to_dag(mesh, grid)), 0)
        trees["dag"], timings["dag"], vox_s = dag, timing, None
    else:
        vox_timing, vox = _common.time_calls(lambda: jax.block_until_ready(jv.voxelize(mesh, grid)), 0)
        vox_s = vox_timing["first_s"]
        for name, build in (("octree", jv.build_octree), ("dag", jv.build_dag)):
            timing, tree = _common.time_calls(lambda: jax.block_until_ready(build(vox)), spec["repeats"])
            trees[name], timings[name] = tree, timing
        del vox
    count = int(trees["dag"].voxel_count)
    sparse = {f"dag-sparse{s}": jv.compact_dag(trees["dag"], prefix=bool(s)) for s in ("", "+prefix")}
    sizes = layout_bytes(trees["octree"], trees["dag"], sparse, resolution)
    speed = None
    if spec.get("trace"):
        layouts = {"octree+prefix": trees["octree"], "dag+prefix": trees["dag"], **sparse}
        if count > jv.octree.MAX_INDEXED:  # int32 Morton indices: only the layout without them traces
            layouts = {"dag-sparse": sparse["dag-sparse"]}
        speed = trace_layouts(mesh, {k: v for k, v in layouts.items() if v is not None})
    return dict(
        voxels=count,
        streamed=bool(spec.get("stream")),
        voxelize_s=vox_s,
        octree_levels=list(trees["octree"].level_sizes) if trees["octree"] else None,
        dag_levels=list(trees["dag"].level_sizes),
        octree_nodes=trees["octree"].num_nodes if trees["octree"] else None,
        dag_nodes=trees["dag"].num_nodes,
        build_octree=timings["octree"],
        build_dag=timings["dag"],
        bytes=sizes,
        bits_per_voxel={k: None if v is None else 8 * v / max(count, 1) for k, v in sizes.items()},
        trace=speed,
        peak_rss_mib=_common.peak_rss_mib(),
        backend=jax.default_backend(),
        device=str(jax.devices()[0]),
    )


def mib(n: float | None) -> str:
    return "-" if n is None else f"{n / 2**20:,.1f}"


def ratio(a: float | None, b: float | None) -> str:
    return "-" if a is None or b is None else f"{a / b:.1f}x"


def seconds(timing: dict | None) -> str:
    return "-" if timing is None else f"{timing['median_s']:.2f}"


def table(rows: list[dict]) -> str:
    """Markdown: sizes in MiB, ratios and build times per case."""
    out = []
    for row in rows:
        if "error" in row:
            out.append(dict(case=f"{row['mesh']} {row['resolution']}^3", octree=row["error"]))
            continue
        b = row["bytes"]
        out.append(
            {
                "case": f"{row['mesh']} {row['resolution']}^3",
                "voxels": f"{row['voxels']:,}",
                "dense": mib(b["dense bits"]),
                "spc": mib(b["spc"]),
                "octree": mib(b["octree"]),
                "octree+prefix": mib(b["octree+prefix"]),
                "dag": mib(b["dag"]),
                "dag+prefix": mib(b["dag+prefix"]),
                "dag-sparse": mib(b["dag-sparse"]),
                "dag-sparse+prefix": mib(b["dag-sparse+prefix"]),
                "ratio": ratio(b["octree"], b["dag"]),
                "ratio33": ratio(b["octree-33B"], b["dag-33B"]),
                "bpv": f"{row['bits_per_voxel']['dag+prefix']:.2f}",
                "bpv_sparse": f"{row['bits_per_voxel']['dag-sparse']:.2f}",
                "t_svo": seconds(row["build_octree"]),
                "t_dag": seconds(row["build_dag"]) + (" (streamed)" if row.get("streamed") else ""),
                "peak": f"{row['peak_rss_mib'] / 1024:.1f}",
            }
        )
    columns = [
        ("case", "case"),
        ("voxels", "voxels"),
        ("dense", "dense bits MiB"),
        ("spc", "SPC MiB"),
        ("octree", "octree MiB"),
        ("octree+prefix", "octree+prefix MiB"),
        ("dag", "DAG MiB"),
        ("dag+prefix", "DAG+prefix MiB"),
        ("dag-sparse", "sparse DAG MiB"),
        ("dag-sparse+prefix", "sparse DAG+prefix MiB"),
        ("ratio", "octree/DAG bytes"),
        ("ratio33", "octree/DAG, 33 B/node (slides)"),
        ("bpv", "DAG+prefix bits/voxel"),
        ("bpv_sparse", "sparse DAG bits/voxel"),
        ("t_svo", "SVO build s"),
        ("t_dag", "DAG build s"),
        ("peak", "peak RSS GiB"),
    ]
    return _common.markdown_table(out, columns) + speed_table(rows)


SPEED_LAYOUTS = ("octree+prefix", "dag+prefix", "dag-sparse+prefix", "dag-sparse")


def speed_table(rows: list[dict]) -> str:
    """Markdown: Mrays/s against bits per voxel per traversable layout (cases with --trace)."""
    out = []
    for row in rows:
        if not row.get("trace"):
            continue
        for layout, timing in row["trace"]["timings"].items():
            out.append(
                {
                    "case": f"{row['mesh']} {row['resolution']}^3",
                    "layout": layout,
                    "mib": mib(row["bytes"][layout]),
                    "bpv": f"{row['bits_per_voxel'][layout]:.2f}",
                    "mrays": f"{timing['mrays_s']:.2f}",
                    "first": f"{timing['first_s']:.2f}",
                    "same": str(row["trace"]["same_hits"]),
                }
            )
    if not out:
        return ""
    columns = [
        ("case", "case"),
        ("layout", "layout"),
        ("mib", "MiB"),
        ("bpv", "bits/voxel"),
        ("mrays", "1080p Mrays/s"),
        ("first", "first call s"),
        ("same", "same hits as the others"),
    ]
    return "\n\nTraversal speed against bytes (`jv.trace`, esvo, 1920x1080 primary rays):\n\n" + _common.markdown_table(
        out, columns
    )


def plot(rows: list[dict], path: Path) -> None:
    """Bytes vs R (first mesh), octree/DAG ratio vs R and DAG bits per voxel vs R (all meshes)."""
    rows = [r for r in rows if "error" not in r]
    fig, (ax_bytes, ax_ratio, ax_bits, ax_speed) = _common.new_figure(4, width=5.5)
    first = rows[0]["mesh"]
    mine = sorted((r for r in rows if r["mesh"] == first), key=lambda r: r["resolution"])
    res = [r["resolution"] for r in mine]
    colours = [f"C{i % 10}" for i in range(len(LAYOUTS))]
    for i, layout in enumerate(LAYOUTS):
        have = [r for r in mine if r["bytes"][layout] is not None]
        ax_bytes.plot(
            [r["resolution"] for r in have],
            [r["bytes"][layout] for r in have],
            marker="os^"[i // 10 % 3],
            color=colours[i],
            ls="-" if i < 10 else "--",
            label=layout,
        )
    ax_bytes.set(xscale="log", yscale="log", xlabel="resolution R", ylabel="bytes", title=f"{first}: bytes per layout")
    ax_bytes.legend(fontsize=7)
    for mesh in dict.fromkeys(r["mesh"] for r in rows):
        part = sorted((r for r in rows if r["mesh"] == mesh), key=lambda r: r["resolution"])
        x = [r["resolution"] for r in part]
        svo = [r for r in part if r["bytes"]["octree"] is not None]
        xs = [r["resolution"] for r in svo]
        ax_ratio.plot(xs, [r["bytes"]["octree-33B"] / r["bytes"]["dag-33B"] for r in svo], marker="o", label=mesh)
        ax_ratio.plot(
            xs, [r["bytes"]["octree"] / r["bytes"]["dag"] for r in svo], ls=":", color=ax_ratio.lines[-1].get_color()
        )
        ax_bits.plot(x, [r["bits_per_voxel"]["dag+prefix"] for r in part], marker="o", label=mesh)
    ax_ratio.set(
        xscale="log",
        yscale="log",
        xlabel="resolution R",
        ylabel="octree bytes / DAG bytes",
        title="DAG compression (solid: 33 B/node, dotted: jaxvox tables)",
    )
    ax_bits.set(
        xscale="log",
        yscale="log",
        xlabel="resolution R",
        ylabel="bits per voxel",
        title="DAG + prefix sums, bits per voxel",
    )
    for ax in (ax_bytes, ax_ratio, ax_bits):
        ax.set_xticks(res, [str(r) for r in res])
        ax.grid(True, which="both", alpha=0.3)
    ax_ratio.legend(fontsize=7)
    traced = [r for r in mine if r.get("trace")]
    for i, layout in enumerate(SPEED_LAYOUTS):
        have = [r for r in traced if layout in r["trace"]["timings"]]
        bits = [r["bits_per_voxel"][layout] for r in have]
        speed = [r["trace"]["timings"][layout]["mrays_s"] for r in have]
        ax_speed.plot(bits, speed, marker="os^D"[i], label=layout)
        for r, b, v in zip(have, bits, speed):
            ax_speed.annotate(str(r["resolution"]), (b, v), fontsize=6, xytext=(3, 3), textcoords="offset points")
    ax_speed.set(
        xscale="log",
        xlabel="bits per voxel",
        ylabel="Mrays/s (1920x1080 primary rays)",
        title=f"{first}: traversal speed against bytes (labels: R)",
    )
    ax_speed.grid(True, which="both", alpha=0.3)
    ax_speed.legend(fontsize=7)
    _common.save_figure(fig, path)


def parse_args(argv=None) -> argparse.Namespace:
    """Command-line options; see the module docstring."""
    parser = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    parser.add_argument("--meshes", nargs="+", default=list(ALL_MESHES))
    parser.add_argument("--mesh-dir", type=Path, default=_common.MESH_DIR)
    parser.add_argument("--resolutions", nargs="*", type=int, default=[64, 128, 256, 512, 1024, 2048])
    parser.add_argument(
        "--huge",
        nargs="*",
        type=int,
        default=[4096],
        metavar="R",
        help="resolutions run for the first mesh only (default 4096)",
    )
    parser.add_argument(
        "--stream",
        nargs="*",
        type=int,
        default=[8192, 16384],
        metavar="R",
        help="resolutions built with mesh_to_dag, first mesh only, no SVO (default 8192 16384; the in-memory "
        "SVO and DAG at 8192^3 need more than this machine's 24 GiB)",
    )
    parser.add_argument(
        "--no-trace", dest="trace", action="store_false", help="skip the traversal speed of each layout (first mesh)"
    )
    parser.add_argument("--repeats", type=int, default=2, help="timed builds after the first (0 above 2048)")
    parser.add_argument("--timeout", type=float, default=3600)
    parser.add_argument("--out", type=Path, default=_common.RESULTS_DIR)
    parser.add_argument("--smoke", action="store_true", help="R = 64, 128 on two meshes; *_smoke outputs")
    parser.add_argument("--plot-only", action="store_true", help="redraw the PNG and table from the JSON")
    parser.add_argument(
        "--update",
        action="store_true",
        help="merge into the existing JSON: replace its rows for the cases run, keep the others",
    )
    parser.add_argument("--worker", help=argparse.SUPPRESS)
    args = parser.parse_args(argv)
    if args.smoke:
        args.meshes, args.resolutions, args.huge, args.stream = args.meshes[:2], [64, 128], [], [256]
    return args


def main(argv=None) -> None:
    """Runs every case in its own process, then writes JSON, PNG and markdown."""
    args = parse_args(argv)
    if _common.answer_as_worker(args, worker):
        return
    stem = "memory_ablation_smoke" if args.smoke else "memory_ablation"
    if args.plot_only:
        rows = json.loads((args.out / f"{stem}.json").read_text())["results"]
        (args.out / f"{stem}.md").write_text(table(rows))
        plot(rows, args.out / f"{stem}.png")
        return
    first = args.meshes[0]
    cases = [(mesh, r, False) for mesh in args.meshes for r in args.resolutions]
    cases += [(first, r, False) for r in args.huge if r not in args.resolutions]
    cases += [(first, r, True) for r in args.stream]
    rows = []
    for mesh, resolution, stream in _common.progress(cases, desc="cases"):
        spec = dict(
            path=str(args.mesh_dir / f"{mesh}.obj"),
            resolution=resolution,
            repeats=args.repeats if resolution <= 2048 else 0,
            stream=stream,
            trace=args.trace and mesh == first and resolution >= (64 if args.smoke else 512),
        )
        row = dict(mesh=mesh, resolution=resolution)
        row.update(_common.run_worker(__file__, spec, timeout=args.timeout))
        rows.append(row)
        print(table([row]).splitlines()[-1], file=sys.stderr, flush=True)
    settings = dict(
        meshes=args.meshes,
        resolutions=args.resolutions,
        huge=args.huge,
        stream=args.stream,
        trace=args.trace,
        repeats=args.repeats,
    )
    if args.update:
        old = json.loads((args.out / f"{stem}.json").read_text())
        done = {(r["mesh"], r["resolution"]) for r in rows}
        order = list(dict.fromkeys(r["mesh"] for r in old["results"] + rows))
        rows = sorted(
            [r for r in old["results"] if (r["mesh"], r["resolution"]) not in done] + rows,
            key=lambda r: (order.index(r["mesh"]), r["resolution"]),
        )
        settings = dict(old["settings"], updated=old["settings"].get("updated", []) + [settings])
    report = table(rows)
    _common.write_json(
        args.out / f"{stem}.json",
        dict(
            machine=_common.machine_info(["jax", "jaxlib", "numpy"]), settings=settings, layouts=LAYOUTS, results=rows
        ),
    )
    (args.out / f"{stem}.md").write_text(report)
    plot(rows, args.out / f"{stem}.png")
    print(report)


if __name__ == "__main__":
    main()
