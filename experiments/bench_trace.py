"""Ray traversal benchmark: jaxvox's octree/DAG traversals against Embree on the triangles.

For each mesh and resolution R, in one fresh subprocess per case:

* the voxels (`jv.voxelize`, conservative) and their SVO and DAG, with node counts and
  bytes;
* 1920x1080 primary rays of a pinhole camera framing the mesh, traced by `jv.trace` on
  the DAG with both traversals (``esvo``: PUSH/ADVANCE/POP; ``stack``: save state and go
  down) and on the SVO with ``esvo``; the same rays against the triangle mesh with Embree
  (embreex, single-threaded ``rtcIntersect1`` loop) in the same process;
* incoherent rays (2^20, random origins on a sphere around the mesh towards random points
  in its box) and shadow rays (from the primary hit points, pushed one voxel along the
  normal, towards a fixed light direction), both ways;
* agreement of the primary image with Embree: the fraction of pixels whose hit/miss
  agree, and the depth difference (mesh t minus voxel t) in voxels where both hit;
* the SVO only up to ``--svo-max`` (4096: at 8192^3 it does not fit beside the DAG build);
* at R <= ``--naive-max`` the naive baseline: a plain vmapped dense-grid DDA
  (`jv.trace_dense` with ``lanes=None``) on 256x256 of the primary rays.

Primary rays are passed as the [H, W, 3] image: the default call ``jv.trace(dag, o, d)``
(which takes the beam start for image-shaped rays: 8 x 8 tiles), the same with each
traversal and tree (``beam=True``), and the DAG without the beam (``beam=False``).
Each case runs in two workers (``--environments``): a plain process, as a user's
`python` or notebook starts (``plain``), and one with glibc's malloc asking for huge pages
(``huge pages``, `jaxvox.cli.ask_for_huge_pages`), with the same number of JAX devices.
``--devices`` sets the number of JAX CPU devices the workers start with (default: one
per core; `jaxvox.trace` shards concrete rays over them); ``--device gpu`` runs on JAX's
GPU backend with lanes sized for it.

Timings are the median of ``--repeats`` calls after a warm-up call (its excess over the
median is reported as compile time, with the XLA compilations it ran), with
`jax.block_until_ready`. The default call runs first, so its first call is the one
that compiles the primary rays' program (the ``beam=True`` calls share it).

Outputs ``bench_trace.json``, ``.md`` and ``.png`` (Mrays/s against resolution, and
Mrays/s against depth error) in ``--out``.

Examples:
  python experiments/bench_trace.py                 # bunny and spot, R = 512 .. 2048
  python experiments/bench_trace.py --smoke         # R = 64, 128 at 480x270
  python experiments/bench_trace.py --resolutions 4096 8192 --meshes stanford-bunny
"""

from __future__ import annotations

import argparse
import json
import os
import sys
from pathlib import Path

import _common
import numpy as np

DEFAULT_MESHES = ("stanford-bunny", "spot")


def _embree(mesh):
    from embreex import rtcore_scene
    from embreex.mesh_construction import TriangleMesh

    scene = rtcore_scene.EmbreeScene()
    v = np.asarray(mesh.vertices, np.float32)
    TriangleMesh(scene, v[np.asarray(mesh.faces)])

    def run(o, d):
        out = scene.run(np.ascontiguousarray(o, np.float32), np.ascontiguousarray(d, np.float32), output=1)
        return np.where(out["primID"] >= 0, out["tfar"], np.inf)

    return run


def worker(spec: dict) -> dict:
    import jax
    import jax.numpy as jnp

    import jaxvox as jv

    mesh = jv.load_mesh(_common.MESH_DIR / f"{spec['mesh']}.obj")
    R, width, height = spec["resolution"], spec["width"], spec["height"]
    grid = jv.Grid.fit(mesh, R)
    h = float(grid.voxel_size)
    vox = jv.voxelize(mesh, grid)
    trees = {"dag": jv.build_dag(vox)}
    if R <= spec["svo_max"]:  # the SVO at 8192^3 (74 M nodes) and its build do not fit beside the DAG's
        trees["svo"] = jv.build_octree(vox)
    result = dict(
        spec,
        voxels=int(vox.count),
        rays=width * height,
        voxel_size_world=h,
        extent_world=float(np.ptp(np.asarray(mesh.vertices), 0).max()),
        nodes={k: t.num_nodes for k, t in trees.items()},
        bytes={k: t.compact_nbytes for k, t in trees.items()},
        mesh_bytes=int(np.asarray(mesh.vertices).nbytes + np.asarray(mesh.faces).nbytes),
    )
    eye, target = jv.look_at_view(mesh)
    o_img, d_img = jv.pinhole_rays(eye, target, width=width, height=height)  # [H, W, 3]: beams are image tiles
    o, d = (jnp.reshape(x, (-1, 3)) for x in (o_img, d_img))
    # lanes sized for the device: a few thousand per CPU device, a million on a GPU
    lanes = 8192 if jax.default_backend() == "cpu" else 1 << 20
    result.update(
        backend=jax.default_backend(), devices=len(jax.devices()), lanes=lanes, environment=_common.environment()
    )
    rng = np.random.default_rng(0)
    lo, hi = np.asarray(grid.origin), np.asarray(grid.origin) + R * h
    centre, radius = (lo + hi) / 2, 1.5 * np.linalg.norm(hi - lo)
    n_inc = spec["incoherent"]
    u = rng.normal(size=(n_inc, 3))
    o_inc = (centre + radius * u / np.linalg.norm(u, axis=1, keepdims=True)).astype(np.float32)
    d_inc = (rng.uniform(lo, hi, (n_inc, 3)) - o_inc).astype(np.float32)
    d_inc /= np.linalg.norm(d_inc, axis=1, keepdims=True)
    light = np.array([0.3, 1.0, 0.5], np.float32) / np.linalg.norm([0.3, 1.0, 0.5])
    embree = _embree(mesh)

    timings, hits = {}, {}

    def timed(name, fn, rays):
        """Times `fn` (median of repeats after a warm-up) and records its Mrays/s."""
        timing, out = _common.time_calls(fn, spec["repeats"])
        timings[name] = dict(timing, rays=rays, mrays_s=rays / timing["median_s"] / 1e6)
        return out

    if jax.default_backend() == "cpu":  # every default (its lanes are the CPU's), first: its first call compiles
        timed("primary/default", lambda: jax.block_until_ready(jv.trace(trees["dag"], o_img, d_img)), width * height)
    cases = [("dag-esvo", "dag", "esvo"), ("dag-stack", "dag", "stack"), ("svo-esvo", "svo", "esvo")]
    for name, kind, method in cases[: len(trees) + 1]:
        trace = lambda: jax.block_until_ready(
            jv.trace(trees[kind], o_img, d_img, method=method, lanes=lanes, beam=True)
        )
        hits[name] = jax.tree.map(
            lambda x: x.reshape((-1,) + x.shape[2:]), timed(f"primary/{name}", trace, width * height)
        )
    no_beam = lambda: jax.block_until_ready(jv.trace(trees["dag"], o_img, d_img, lanes=lanes, beam=False))
    timed("primary/dag-esvo-no-beam", no_beam, width * height)
    hit = hits["dag-esvo"]
    o_np, d_np = np.asarray(o), np.asarray(d)
    t_mesh = timed("primary/embree", lambda: embree(o_np, d_np), width * height)
    t_vox, vox_hit = np.asarray(hit.t), np.asarray(hit.status) == jv.HIT
    mesh_hit = np.isfinite(t_mesh)
    both = vox_hit & mesh_hit
    gap = (t_mesh[both] - t_vox[both]) / h
    result["agreement"] = dict(
        pixels_agree=float((vox_hit == mesh_hit).mean()),
        mesh_hits=int(mesh_hit.sum()),
        voxel_hits=int(vox_hit.sum()),
        voxel_only=int((vox_hit & ~mesh_hit).sum()),
        mesh_only=int((mesh_hit & ~vox_hit).sum()),
        depth_voxels={
            q: float(np.quantile(gap, p))
            for q, p in (("min", 0), ("median", 0.5), ("p90", 0.9), ("p99", 0.99), ("max", 1))
        }
        if both.any()
        else None,
        within_diagonal=float((np.abs(gap) <= np.sqrt(3)).mean()) if both.any() else None,
    )
    # incoherent and shadow rays
    for name, kind, method in cases[:2]:
        timed(
            f"incoherent/{name}",
            lambda: jax.block_until_ready(jv.trace(trees[kind], o_inc, d_inc, method=method, lanes=lanes)),
            n_inc,
        )
    timed("incoherent/embree", lambda: embree(o_inc, d_inc), n_inc)
    p = o_np[vox_hit] + t_vox[vox_hit, None] * d_np[vox_hit] + np.asarray(hit.normal)[vox_hit] * h
    s_dir = np.broadcast_to(light, p.shape).astype(np.float32)
    p = p.astype(np.float32)
    result["shadow_rays"] = len(p)
    timed("shadow/dag-esvo", lambda: jax.block_until_ready(jv.trace(trees["dag"], p, s_dir, lanes=lanes)), len(p))
    timed("shadow/embree", lambda: embree(p, s_dir), len(p))
    if R <= spec["naive_max"]:
        occupancy = np.zeros((R,) * 3, bool)
        occupancy[tuple(vox.to_numpy().T)] = True
        sub = (slice(None, None, max(height // 256, 1)), slice(None, None, max(width // 256, 1)))
        o_sub = o_np.reshape(height, width, 3)[sub].reshape(-1, 3)
        d_sub = d_np.reshape(height, width, 3)[sub].reshape(-1, 3)
        for name, lanes in (("naive-dda", None), ("dda-lanes", 16384)):
            timed(
                f"primary/{name}",
                lambda: jax.block_until_ready(jv.trace_dense(occupancy, grid, o_sub, d_sub, lanes=lanes)),
                len(o_sub),
            )
    result["timings"] = timings
    result["peak_rss_mib"] = _common.peak_rss_mib()
    return result


def chart(rows, path):
    import matplotlib.ticker

    fig, (left, right) = _common.new_figure(2)
    for mesh in sorted({r["mesh"] for r in rows}):
        mine = sorted((r for r in rows if r["mesh"] == mesh), key=lambda r: r["resolution"])
        for case, style in (("dag-esvo", "o-"), ("dag-stack", "s--"), ("svo-esvo", "^:"), ("embree", "k-")):
            points = [
                (r["resolution"], r["timings"][f"primary/{case}"]["mrays_s"])
                for r in mine
                if f"primary/{case}" in r["timings"]
            ]
            left.plot(*zip(*points), style, label=f"{mesh} {case}")
        naive = [
            (r["resolution"], r["timings"]["primary/naive-dda"]["mrays_s"])
            for r in mine
            if "primary/naive-dda" in r["timings"]
        ]
        if naive:
            left.plot(*zip(*naive), "x", label=f"{mesh} naive vmapped DDA")
        err = [r["agreement"]["depth_voxels"]["median"] * r["voxel_size_world"] / r["extent_world"] for r in mine]
        right.plot(err, [r["timings"]["primary/dag-esvo"]["mrays_s"] for r in mine], "o-", label=f"{mesh} DAG (esvo)")
        for r, e in zip(mine, err):
            right.annotate(f"{r['resolution']}", (e, r["timings"]["primary/dag-esvo"]["mrays_s"]), fontsize=7)
        right.axhline(
            np.median([r["timings"]["primary/embree"]["mrays_s"] for r in mine]),
            color=right.lines[-1].get_color(),
            ls="--",
            label=f"{mesh} Embree (triangles, exact)",
        )
    resolutions = sorted({r["resolution"] for r in rows})
    left.set(
        xscale="log",
        yscale="log",
        xlabel="resolution R",
        ylabel="Mrays/s (1920x1080 primary)",
        title="traversal speed (2-core CPU)",
    )
    left.set_xticks(resolutions, [str(x) for x in resolutions])
    left.xaxis.set_minor_locator(matplotlib.ticker.NullLocator())
    right.xaxis.set_minor_formatter(matplotlib.ticker.NullFormatter())
    right.yaxis.set_minor_formatter(matplotlib.ticker.NullFormatter())
    right.set(
        xscale="log",
        xlabel="median depth error (mesh t - voxel t) / mesh extent",
        ylabel="Mrays/s",
        yscale="log",
        title="speed vs depth error (primary rays)",
    )
    for ax in (left, right):
        ax.legend(fontsize=7)
        ax.grid(alpha=0.3)
    _common.save_figure(fig, path)


def main():
    parser = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    parser.add_argument("--meshes", nargs="+", default=list(DEFAULT_MESHES))
    parser.add_argument("--resolutions", nargs="+", type=int, default=[512, 1024, 2048])
    parser.add_argument("--repeats", type=int, default=3)
    parser.add_argument("--naive-max", type=int, default=1024)
    parser.add_argument("--svo-max", type=int, default=4096, help="largest R at which the SVO is built too")
    parser.add_argument("--smoke", action="store_true")
    parser.add_argument(
        "--devices", type=int, default=os.cpu_count(), help="JAX CPU devices (rays are sharded over them)"
    )
    parser.add_argument("--device", default=None, help="cpu or gpu (JAX_PLATFORMS); default: JAX's default backend")
    parser.add_argument(
        "--environments",
        nargs="+",
        choices=("plain", "huge pages"),
        default=["plain", "huge pages"],
        help="run each case in a plain process, with huge pages, or both",
    )
    parser.add_argument("--update", action="store_true", help="merge into the existing JSON instead of replacing it")
    parser.add_argument("--out", type=Path, default=_common.RESULTS_DIR)
    parser.add_argument("--plot-only", action="store_true", help="redraw the table and chart from the JSON")
    parser.add_argument("--worker")
    args = parser.parse_args()
    if _common.answer_as_worker(args, worker):
        return
    os.environ["JAX_NUM_CPU_DEVICES"] = str(args.devices)  # read by every worker's JAX at start
    if args.device:
        os.environ["JAX_PLATFORMS"] = args.device
    width, height, n_inc = (1920, 1080, 2**20) if not args.smoke else (480, 270, 2**16)
    resolutions = args.resolutions if not args.smoke else [64, 128]
    stem = "bench_trace" + ("_smoke" if args.smoke else "")
    path = args.out / f"{stem}.json"
    rows = json.loads(path.read_text())["rows"] if (args.update or args.plot_only) and path.exists() else []
    cases = [(m, R, e) for m in args.meshes for R in resolutions for e in args.environments]
    for mesh, R, env in _common.progress(cases if not args.plot_only else [], desc="cases"):
        spec = dict(
            mesh=mesh,
            resolution=R,
            width=width,
            height=height,
            incoherent=n_inc,
            repeats=args.repeats,
            naive_max=args.naive_max,
            svo_max=args.svo_max,
        )
        row = _common.run_worker(__file__, spec, timeout=3600, plain=env == "plain")
        if "error" in row:
            print(f"{mesh} {R} ({env}): {row['error']}", file=sys.stderr)
            continue
        key = lambda r: (
            r["mesh"],
            r["resolution"],
            r.get("devices", 1),
            r.get("backend", "cpu"),
            r.get("environment", "huge pages"),
        )
        rows = [r for r in rows if key(r) != key(row)] + [row]
        t = row["timings"]
        print(
            f"{mesh} {R}^3 ({env}): default call {t.get('primary/default', {}).get('mrays_s', 0):.2f}, "
            f"DAG esvo {t['primary/dag-esvo']['mrays_s']:.2f}, stack "
            f"{t['primary/dag-stack']['mrays_s']:.2f}, "
            f"SVO esvo {t.get('primary/svo-esvo', {}).get('mrays_s', 0):.2f}, "
            f"Embree {t['primary/embree']['mrays_s']:.2f} Mrays/s; agree "
            f"{row['agreement']['pixels_agree']:.4f}",
            flush=True,
        )
        _common.write_json(path, dict(machine=_common.machine_info(["jax", "embreex", "numpy"]), rows=rows))
    rows.sort(key=lambda r: (r["mesh"], r["resolution"], r.get("environment", "huge pages")))
    columns = [
        ("mesh", "mesh"),
        ("resolution", "R"),
        ("devices", "devices"),
        ("environment", "process"),
        ("default", "default call Mrays/s"),
        ("default_first", "its first call s (compiles)"),
        ("of_embree", "of Embree"),
        ("dag_esvo", "DAG esvo beam"),
        ("no_beam", "without beam"),
        ("dag_stack", "DAG stack"),
        ("svo_esvo", "SVO esvo"),
        ("embree", "Embree"),
        ("ratio", "Embree / DAG esvo"),
        ("naive", "naive vmapped DDA"),
        ("incoherent", "incoherent DAG / Embree"),
        ("shadow", "shadow DAG / Embree"),
        ("compile", "compile s"),
        ("agree", "pixels agree"),
        ("depth", "depth diff (voxels) median / p99"),
        ("dag_mib", "DAG MiB"),
    ]
    table = []
    for r in rows:
        t = r["timings"]
        rate = lambda k: t[k]["mrays_s"]
        table.append(
            dict(
                mesh=r["mesh"],
                resolution=r["resolution"],
                devices=r.get("devices", 1),
                environment=r.get("environment", "huge pages"),
                default=f"{rate('primary/default'):.2f}" if "primary/default" in t else "-",
                default_first=f"{t['primary/default']['first_s']:.2f} ({t['primary/default']['compiles_first']})"
                if "compiles_first" in t.get("primary/default", {})
                else "-",
                of_embree=f"{rate('primary/default') / rate('primary/embree'):.2f}" if "primary/default" in t else "-",
                dag_esvo=f"{rate('primary/dag-esvo'):.2f}",
                no_beam=f"{rate('primary/dag-esvo-no-beam'):.2f}" if "primary/dag-esvo-no-beam" in t else "-",
                dag_stack=f"{rate('primary/dag-stack'):.2f}",
                svo_esvo=f"{rate('primary/svo-esvo'):.2f}" if "primary/svo-esvo" in t else "-",
                embree=f"{rate('primary/embree'):.2f}",
                ratio=f"{rate('primary/embree') / rate('primary/dag-esvo'):.1f}x",
                naive=f"{rate('primary/naive-dda'):.3f}" if "primary/naive-dda" in t else "-",
                incoherent=f"{rate('incoherent/dag-esvo'):.2f} / {rate('incoherent/embree'):.2f}",
                shadow=f"{rate('shadow/dag-esvo'):.2f} / {rate('shadow/embree'):.2f}",
                compile=f"{t.get('primary/default', t['primary/dag-esvo'])['compile_s']:.1f}",
                agree=f"{r['agreement']['pixels_agree']:.4f}",
                depth=f"{r['agreement']['depth_voxels']['median']:.2f} / {r['agreement']['depth_voxels']['p99']:.2f}",
                dag_mib=f"{r['bytes']['dag'] / 2**20:.1f}",
            )
        )
    md = _common.markdown_table(table, columns)
    (args.out / f"{stem}.md").write_text(md + "\n")
    print(md)
    chart(rows, args.out / f"{stem}.png")


if __name__ == "__main__":
    main()
