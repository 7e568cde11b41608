"""Sphere tracing: plain, over-relaxed and octree-accelerated, where each pays and where each fails.

For each scene (a sphere; a CSG of many primitives; a thin torus; a "mix" that breaks
the Lipschitz bound; a non-uniform scale left uncorrected) one W x H camera image is
traced by:

* "plain": `jaxvox.sphere_trace`, steps of d;
* "relaxed": over-relaxed, omega = 1.6 (Keinert et al.);
* "octree": `jaxvox.sphere_trace_octree` over the scene's DAG at ``--octree-res``
  (built by `jaxvox.build_octree_from_sdf`; build time reported separately);
* "safe": steps of d / L with L = `jaxvox.sdf.lipschitz_bound` (only differs from
  plain on the non-Lipschitz scenes).

Reference: the first crossing of a fine float32 march (steps of ``--march`` world
units over [0, t_max], refined by bisection to 1e-6), independent of the distance
values, so it holds for non-Lipschitz scenes too. Per method: time per image (median
of repeats; compile time separate), scene evaluations per ray (mean, p99, max),
misses (reference hits, method does not), false hits (the reverse), step-cap rays, and
the hit-distance error where both hit (max, mean, p99, in voxels of the octree grid).

Outputs sdf_stability[_smoke].json / .md (table) / .png (steps vs error, and time
with and without the octree per scene) and sdf_stability[_smoke]_maps.png (per scene:
steps per pixel and the failure map of each method).

Examples:
  python experiments/sdf_stability.py --smoke   # 96 x 64 pixels (a few minutes)
  python experiments/sdf_stability.py           # 480 x 270 pixels, DAG at 128^3
"""

from __future__ import annotations

import argparse
import sys

import _common
import numpy as np

sys.path.insert(0, str(_common.REPO_ROOT))
import jax  # noqa: E402
import jax.numpy as jnp  # noqa: E402

import jaxvox as jv  # noqa: E402
from jaxvox import sdf  # noqa: E402

T_MAX = 8.0
MAX_STEPS = 512
BOUNDS = ((-1.2, -1.2, -1.2), (1.2, 1.2, 1.2))  # every scene fits; the octree grid covers it


def csg_scene(count: int):
    """A rounded box and `count` random small spheres and boxes around it, less a
    cylinder: ``count + 2`` primitives (the same first ones for every count)."""
    rng = np.random.default_rng(0)
    parts = []
    for n in range(count):
        c = rng.uniform(-0.8, 0.8, 3)
        parts.append(
            sdf.sphere(rng.uniform(0.08, 0.2), center=c) if n % 2 else sdf.box(rng.uniform(0.05, 0.15, 3), center=c)
        )
    return sdf.difference(sdf.union(sdf.rounded_box((0.35, 0.25, 0.3), 0.05), *parts), sdf.cylinder(0.12, 1.0))


def scenes() -> dict:
    return {
        "sphere": sdf.sphere(0.7),
        "csg (26 primitives)": csg_scene(24),
        "thin torus": sdf.rotate(sdf.torus(0.75, 0.02), sdf.rotation((1.0, 0.0, 0.3), 0.9)),
        "mix k=3 (L=5)": sdf.mix(sdf.sphere(0.6), sdf.box((0.4, 0.4, 0.4)), 3.0),
        "scale (1,0.3,1) uncorrected": sdf.scale(sdf.torus(0.6, 0.2), (1.0, 0.3, 1.0), correct=False),
    }


def reference(scene, o, u, march: float):
    """First crossing t [n] (inf if none) of a fine march plus bisection, in float32.

    Every call has the full batch shape (one compiled program): the march records each
    ray's first bracketing interval, then all rays are bisected together.
    """
    f = jax.jit(jax.vmap(lambda oo, uu, t: scene(oo + t * uu)))
    n = len(o)
    lo, hi = np.zeros(n, np.float32), np.full(n, np.inf, np.float32)
    inside = np.asarray(f(o, u, jnp.zeros(n))) < 0
    hi[inside] = 0.0
    prev = 0.0
    for t in np.arange(march, T_MAX + march, march, dtype=np.float32):
        new = np.isinf(hi) & (np.asarray(f(o, u, jnp.full(n, t))) <= 0)
        lo[new], hi[new] = prev, t
        prev = t
    found = np.isfinite(hi) & ~inside
    a, b = lo.copy(), np.where(found, hi, 0.0).astype(np.float32)
    for _ in range(24):
        mid = (a + b) / 2
        below = np.asarray(f(o, u, jnp.asarray(mid))) <= 0
        b, a = np.where(below, mid, b), np.where(below, a, mid)
    return np.where(found, b, np.where(inside, 0.0, np.inf))


def run_method(name, scene, tree, o, u, repeats):
    kw = dict(t_max=T_MAX, max_steps=MAX_STEPS, return_steps=True)
    if name == "octree":
        fn = lambda: jv.sphere_trace_octree(scene, tree, o, u, **kw)
    else:
        omega = {"plain": 1.0, "relaxed": 1.6, "safe": 1.0 / sdf.lipschitz_bound(scene)}[name]
        fn = lambda: jv.sphere_trace(scene, o, u, relaxation=omega, **kw)
    timing, (hit, steps) = _common.time_calls(lambda: jax.block_until_ready(fn()), repeats)
    return timing, hit, np.asarray(steps)


def evaluate(t_ref, hit, steps, voxel) -> dict:
    status, t = np.asarray(hit.status), np.asarray(hit.t)
    ref_hit = np.isfinite(t_ref)
    is_hit = status == jv.HIT
    both = ref_hit & is_hit
    err = np.abs(t - t_ref)[both] / voxel
    return dict(
        misses=int((ref_hit & ~is_hit).sum()),
        false_hits=int((~ref_hit & is_hit).sum()),
        step_cap=int((status == jv.STEP_CAP).sum()),
        hits=int(is_hit.sum()),
        ref_hits=int(ref_hit.sum()),
        steps_mean=float(steps.mean()),
        steps_p99=float(np.percentile(steps, 99)),
        steps_max=int(steps.max()),
        err_max=float(err.max()) if err.size else 0.0,
        err_mean=float(err.mean()) if err.size else 0.0,
        err_p99=float(np.percentile(err, 99)) if err.size else 0.0,
    )


def failure_map(t_ref, hit, voxel, shape) -> np.ndarray:
    """0 ok, 1 hit-distance error above one voxel, 2 miss, 3 false hit, 4 step cap."""
    status, t = np.asarray(hit.status), np.asarray(hit.t)
    ref_hit, is_hit = np.isfinite(t_ref), status == jv.HIT
    out = np.zeros(status.shape, np.int8)
    both = ref_hit & is_hit
    out[both] = np.where(np.abs(t[both] - t_ref[both]) > voxel, 1, 0)
    out[ref_hit & ~is_hit] = 2
    out[~ref_hit & is_hit] = 3
    out[status == jv.STEP_CAP] = 4
    return out.reshape(shape)


METHODS = ("plain", "relaxed", "octree", "safe")


def main(argv=None) -> None:
    parser = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    parser.add_argument("--width", type=int, default=480)
    parser.add_argument("--height", type=int, default=270)
    parser.add_argument("--octree-res", type=int, default=128)
    parser.add_argument("--repeats", type=int, default=3)
    parser.add_argument("--march", type=float, default=2e-3, help="reference march step (world units)")
    parser.add_argument(
        "--sweep", type=int, nargs="*", default=[0, 6, 24, 62, 126], help="breakeven: CSG scenes with N + 2 primitives"
    )
    parser.add_argument("--smoke", action="store_true", help="96 x 64 pixels, octree at 64^3, one repeat")
    args = parser.parse_args(argv)
    if args.smoke:
        args.width, args.height, args.octree_res, args.repeats, args.march = 96, 64, 64, 1, 1e-2
        args.sweep = [0, 24]
    lo, hi = (np.asarray(b, np.float32) for b in BOUNDS)
    grid = jv.Grid(origin=lo, voxel_size=float(hi[0] - lo[0]) / args.octree_res, resolution=args.octree_res)
    voxel = float(grid.voxel_size)
    eye, target = jv.look_at_view(BOUNDS, azimuth=30.0, elevation=20.0, distance=1.6)
    o, u = jv.pinhole_rays(eye, target, width=args.width, height=args.height, fov=45.0)
    o, u = np.asarray(o).reshape(-1, 3), np.asarray(u).reshape(-1, 3)
    shape = (args.height, args.width)

    rows, maps = [], {}
    for scene_name, scene in _common.progress(list(scenes().items()), desc="scenes"):
        build, tree = _common.time_calls(lambda: jv.build_octree_from_sdf(scene, grid, dag=True), 1)
        t_ref = reference(scene, o, u, args.march)
        maps[scene_name] = {}
        for method in METHODS:
            timing, hit, steps = run_method(method, scene, tree, o, u, args.repeats)
            row = dict(
                scene=scene_name,
                method=method,
                lipschitz=sdf.lipschitz_bound(scene),
                median_s=timing["median_s"],
                compile_s=timing["compile_s"],
                mrays_s=len(o) / timing["median_s"] / 1e6,
                **evaluate(t_ref, hit, steps, voxel),
            )
            if method == "octree":
                row.update(
                    build_s=build["median_s"],
                    build_compile_s=build["compile_s"],
                    leaves=int(tree.voxel_count),
                    nodes=tree.num_nodes,
                )
            rows.append(row)
            maps[scene_name][method] = dict(steps=steps.reshape(shape), failures=failure_map(t_ref, hit, voxel, shape))
            print(
                f"{scene_name} {method}: {row['median_s']:.3f} s, {row['steps_mean']:.1f} steps/ray, "
                f"misses {row['misses']}, false hits {row['false_hits']}, cap {row['step_cap']}",
                flush=True,
            )

    sweep = breakeven(args.sweep, grid, o, u, args.repeats)
    stem = _common.RESULTS_DIR / ("sdf_stability_smoke" if args.smoke else "sdf_stability")
    _common.write_json(
        stem.with_suffix(".json"),
        dict(machine=_common.machine_info(["jax", "jaxlib", "numpy"]), settings=vars(args), rows=rows, sweep=sweep),
    )
    report = table(rows, args) + "\n\n" + sweep_table(sweep, args)
    stem.with_suffix(".md").write_text(report)
    plot(rows, maps, sweep, stem)
    print(report)


def breakeven(counts, grid, o, u, repeats) -> list[dict]:
    """Plain against octree sphere tracing on CSG scenes of growing cost: where the octree pays."""
    rows = []
    for count in _common.progress(counts, desc="breakeven"):
        scene = csg_scene(count)
        build, tree = _common.time_calls(lambda: jv.build_octree_from_sdf(scene, grid, dag=True), 1)
        for method in ("plain", "octree"):
            timing, _, steps = run_method(method, scene, tree, o, u, repeats)
            rows.append(
                dict(
                    primitives=count + 2,
                    method=method,
                    median_s=timing["median_s"],
                    first_s=timing["first_s"],
                    compile_s=timing["compile_s"],
                    steps_mean=float(steps.mean()),
                    steps_max=int(steps.max()),
                    build_s=build["median_s"] if method == "octree" else 0.0,
                )
            )
            print(f"breakeven {count + 2} primitives {method}: {timing['median_s']:.3f} s", flush=True)
    return rows


def sweep_table(sweep, args) -> str:
    plain = {r["primitives"]: r["median_s"] for r in sweep if r["method"] == "plain"}
    out = [
        dict(
            primitives=r["primitives"],
            method=r["method"],
            time=f"{r['median_s'] * 1e3:.1f}",
            first=f"{r['first_s']:.2f}",
            speedup=f"{plain[r['primitives']] / r['median_s']:.2f}x",
            steps=f"{r['steps_mean']:.1f} / {r['steps_max']}",
            build=f"{r['build_s']:.2f}" if r["method"] == "octree" else "",
        )
        for r in sweep
    ]
    columns = [
        ("primitives", "CSG primitives"),
        ("method", "method"),
        ("time", f"ms per {args.width}x{args.height} image"),
        ("first", "first call s (compile included)"),
        ("speedup", "vs plain"),
        ("steps", "evaluations per ray: mean / max"),
        ("build", "octree build s"),
    ]
    return _common.markdown_table(out, columns)


def table(rows, args) -> str:
    out = []
    plain = {r["scene"]: r["median_s"] for r in rows if r["method"] == "plain"}
    for r in rows:
        out.append(
            dict(
                scene=r["scene"],
                method=r["method"],
                time=f"{r['median_s'] * 1e3:.1f}",
                speedup=f"{plain[r['scene']] / r['median_s']:.2f}x",
                steps=f"{r['steps_mean']:.1f} / {r['steps_p99']:.0f} / {r['steps_max']}",
                errors=f"{r['misses']} / {r['false_hits']} / {r['step_cap']}",
                err=f"{r['err_max']:.3f} / {r['err_mean']:.4f} / {r['err_p99']:.3f}",
                build=(
                    f"{r['build_s']:.2f} s (+{r['build_compile_s']:.0f} s compile), {r['leaves']:,} leaves"
                    if "build_s" in r
                    else ""
                ),
            )
        )
    columns = [
        ("scene", "scene"),
        ("method", "method"),
        ("time", f"ms per {args.width}x{args.height} image"),
        ("speedup", "vs plain"),
        ("steps", "evaluations per ray: mean / p99 / max"),
        ("errors", "misses / false hits / step cap"),
        ("err", "|t - t_ref| max / mean / p99 (voxels)"),
        ("build", "octree build"),
    ]
    return _common.markdown_table(out, columns)


def plot(rows, maps, sweep, stem) -> None:
    import matplotlib.colors as mcolors

    fig, (ax_err, ax_time, ax_sweep) = _common.new_figure(3)
    markers = dict(zip(METHODS, "osD^"))
    scene_names = list(dict.fromkeys(r["scene"] for r in rows))
    for r in rows:
        c = f"C{scene_names.index(r['scene'])}"
        bad = (r["misses"] + r["false_hits"] + r["step_cap"]) / max(r["ref_hits"], 1)
        ax_err.scatter(
            r["steps_mean"],
            max(r["err_p99"], 1e-5) + bad,
            color=c,
            marker=markers[r["method"]],
            label=f"{r['scene']}" if r["method"] == "plain" else None,
        )
    for m, mk in markers.items():
        ax_err.scatter([], [], color="k", marker=mk, label=m)
    ax_err.set(
        xscale="log",
        yscale="log",
        xlabel="scene evaluations per ray (mean)",
        ylabel="p99 |t error| (voxels) + failed-ray fraction",
        title="Speed vs accuracy",
    )
    ax_err.legend(fontsize=6)
    width = 0.2
    for n, m in enumerate(METHODS):
        ys = [next(r["median_s"] for r in rows if r["scene"] == s and r["method"] == m) for s in scene_names]
        ax_time.bar(np.arange(len(scene_names)) + n * width, ys, width, label=m)
    ax_time.set_xticks(
        np.arange(len(scene_names)) + 1.5 * width, [s[:14] for s in scene_names], fontsize=6, rotation=20
    )
    ax_time.set(ylabel="seconds per image", title="Time per image")
    ax_time.legend(fontsize="small")
    for m, mk in (("plain", "o-"), ("octree", "D-")):
        mine = [r for r in sweep if r["method"] == m]
        ax_sweep.plot([r["primitives"] for r in mine], [r["median_s"] for r in mine], mk, label=m)
    ax_sweep.set(
        xscale="log", yscale="log", xlabel="CSG primitives", ylabel="seconds per image", title="Where the octree pays"
    )
    ax_sweep.legend(fontsize="small")
    _common.save_figure(fig, stem.with_suffix(".png"))

    fig, axes = _common.new_figure(2 * len(METHODS), rows=len(maps), width=1.9, height=1.4)
    cmap = mcolors.ListedColormap(["#f0f0f0", "#fdae61", "#d7191c", "#2c7bb6", "#000000"])
    for i, (scene_name, per_method) in enumerate(maps.items()):
        for j, m in enumerate(METHODS):
            ax_s, ax_f = axes[i, 2 * j], axes[i, 2 * j + 1]
            ax_s.imshow(per_method[m]["steps"], cmap="magma", vmin=0, vmax=128)
            ax_f.imshow(per_method[m]["failures"], cmap=cmap, vmin=-0.5, vmax=4.5, interpolation="nearest")
            ax_s.set_title(f"{m}: steps", fontsize=6)
            ax_f.set_title(f"{m}: failures", fontsize=6)
            for ax in (ax_s, ax_f):
                ax.set_xticks([])
                ax.set_yticks([])
        axes[i, 0].set_ylabel(scene_name[:16], fontsize=6)
    fig.suptitle(
        "steps per pixel (0-128) | failures: orange t error > 1 voxel, red miss, blue false hit, black step cap",
        fontsize=7,
    )
    _common.save_figure(fig, stem.parent / f"{stem.name}_maps.png")


if __name__ == "__main__":
    main()
