"""Point queries (issue 42): `jaxvox.points` against libigl, Open3D, Warp, fcpw, pysdf and mesh_to_sdf.

For each mesh (default: the Stanford bunny, open at the bottom), ``--points`` (1M) points
uniform in the mesh's bounding box scaled by 1.1 about its centre (seed 0) are queried by
every method, each in a fresh subprocess (a *worker*):

* jaxvox: ``closest_points``, ``signed_distance`` (winding and pseudonormal signs) and
  ``occupancy`` (winding) on an index built once (``jp.mesh_index``). The first call
  includes compilation; the compiled programs are counted (``jax.monitoring``). Times are
  reported with the index build excluded and included (build median + query median);
* peers (optional: a missing or failing one is recorded as ``unavailable: <reason>``):
  libigl ``signed_distance`` (fast winding number and pseudonormal signs; it builds its tree
  on every call) and ``FastWindingNumberBVH``; Open3D ``RaycastingScene`` distance, signed
  distance and occupancy; Warp on the CPU (``mesh_query_point_sign_winding_number`` and
  ``..._sign_normal``); fcpw closest points; pysdf; mesh_to_sdf. A peer's first call
  includes its build.

Accuracy against references on subsamples: the exact winding number (``jp.winding_number(...,
mode="exact")``, checked against the float64 `tests/reference.py` to ~1e-6) at ``--sub``
points, and the float64 brute-force distance (`tests/reference.py` ``mesh_distance``) at
``--dist-sub`` points. Sign disagreement is the % of the subsample where the method's
inside/outside differs from ``w > 1/2``, over points with ``|w - 1/2| >= 0.05``; those with
``|w - 1/2| < 0.05`` are counted and reported separately. Distance error is the max
``| |value| - d |`` over the bounding-box diagonal.

Compile-count check: a worker warms every jaxvox query up on the bunny, then builds an index
of ``spot`` (another size) and queries it, counting compiled programs.

Warm timings are the median of ``--repeats`` calls after the first (1 repeat where the first
call took over a minute), with ``jax.block_until_ready``. Outputs ``bench_points.json``,
``.md`` and ``.png`` (time per method, log; sign accuracy against speed) in ``--out``.

Examples:
  python experiments/bench_points.py                  # bunny, 1M points, 3 repeats
  python experiments/bench_points.py --smoke          # 20k points, 1 repeat, *_smoke outputs
  python experiments/bench_points.py --meshes spot stanford-bunny --methods jaxvox libigl
"""

from __future__ import annotations

import argparse
import datetime
import statistics
import sys
import tempfile
import time
from pathlib import Path

import _common
import numpy as np
from _point_methods import METHODS, inside_of

SUMMARY = ("first_s", "warm_s", "sign_disagree_pct", "max_dist_err_rel")
PACKAGES = ["jax", "jaxlib", "numpy", "libigl", "open3d", "warp-lang", "fcpw", "pysdf", "mesh-to-sdf", "trimesh"]


def disagreement(inside, w) -> dict:
    """Sign disagreement (%) of `inside` with the winding number `w`'s ``w > 1/2``, apart where ``|w - 1/2| < 0.05``."""
    clear = np.abs(w - 0.5) >= 0.05
    wrong = inside != (w > 0.5)
    return dict(
        sign_disagree_pct=100 * float(wrong[clear].mean()),
        sign_wrong=int(wrong[clear].sum()),
        ambiguous=int((~clear).sum()),
        ambiguous_disagree_pct=100 * float(wrong[~clear].mean()) if (~clear).any() else None,
    )


def accuracy(kind, values, ref) -> dict:
    """Sign disagreement against the exact winding number and max distance error / bounding-box diagonal."""
    inside = inside_of(kind, np.asarray(values)[ref["sub"]])
    out = disagreement(inside, ref["w"]) if inside is not None else {}
    if kind in ("signed", "unsigned"):
        err = np.abs(np.abs(np.asarray(values, np.float64)[ref["dsub"]]) - ref["d"])
        out.update(max_dist_err_rel=float(np.nanmax(err) / ref["diag"]), nonfinite=int((~np.isfinite(values)).sum()))
    return out


def run_method(name, V, F, P, ref, repeats):
    """First call (build + query), warm queries (median), build alone; accuracy. In this process."""
    setup, query = METHODS[name]
    compiles = _common.compile_count if name.startswith("jaxvox") else (lambda: 0)
    c0, t0 = compiles(), time.perf_counter()
    state = setup(V, F)
    build_first = time.perf_counter() - t0
    kind, values = query(state, P)
    first = time.perf_counter() - t0
    row = dict(method=name, kind=kind, first_s=first, build_first_s=build_first, compiles_first=compiles() - c0)
    reps = repeats if first < 60 else 1
    c1, times, builds = compiles(), [], []
    for _ in range(reps):
        t0 = time.perf_counter()
        kind, values = query(state, P)
        times.append(time.perf_counter() - t0)
    for _ in range(reps if name.startswith("jaxvox") else 0):
        t0 = time.perf_counter()
        setup(V, F)
        builds.append(time.perf_counter() - t0)
    row.update(warm_times_s=times, warm_s=statistics.median(times), compiles_warm=compiles() - c1)
    row["points_per_s"] = len(P) / row["warm_s"]
    if builds:
        row.update(build_s=statistics.median(builds), warm_with_build_s=statistics.median(builds) + row["warm_s"])
        row["points_per_s_with_build"] = len(P) / row["warm_with_build_s"]
    if name == "mesh_to_sdf":
        row["scan_error"] = getattr(METHODS["mesh_to_sdf"][1], "scan_error", None)
    row.update(accuracy(kind, values, ref))
    return row


def worker(spec: dict) -> dict:
    data = dict(np.load(spec["data"]))
    ref = dict(sub=data["sub"], w=data["w"], dsub=data["dsub"], d=data["d"], diag=float(data["diag"]))
    try:
        return run_method(spec["method"], data["V"], data["F"], data["P"], ref, spec["repeats"])
    except Exception as e:
        return dict(method=spec["method"], unavailable=f"{type(e).__name__}: {e}"[:400])


def compile_check(spec: dict) -> dict:
    """Compiled programs for queries on a second mesh after warming up on the first."""
    import jax

    import jaxvox as jv
    import jaxvox.points as jp

    rng = np.random.default_rng(1)
    out = dict(meshes=spec["compile_check"], points=spec["points"])
    for mesh_name in spec["compile_check"]:
        mesh = jv.load_mesh(_common.MESH_DIR / f"{mesh_name}.obj")
        P = box_points(np.asarray(mesh.vertices), spec["points"], rng)
        c0 = _common.compile_count()
        idx = jax.block_until_ready(jp.mesh_index(mesh))
        out[f"{mesh_name}_faces"] = int(np.asarray(mesh.faces).shape[0])
        out[f"compiles/{mesh_name}/mesh_index"] = _common.compile_count() - c0
        for name in [m for m in METHODS if m.startswith("jaxvox")]:
            c0 = _common.compile_count()
            METHODS[name][1](idx, P)
            out[f"compiles/{mesh_name}/{name}"] = _common.compile_count() - c0
    return out


def source_state() -> dict:
    """The commit measured and whether `jaxvox/` had uncommitted edits (with a hash of the diff)."""
    import hashlib
    import subprocess

    git = lambda *a: subprocess.run(["git", *a], cwd=_common.REPO_ROOT, capture_output=True, text=True).stdout
    diff = git("diff", "HEAD", "--", "jaxvox")
    return dict(commit=git("rev-parse", "HEAD").strip(), jaxvox_dirty=bool(diff),
                jaxvox_diff_sha1=hashlib.sha1(diff.encode()).hexdigest()[:12] if diff else None)  # fmt: skip


def box_points(V, n, rng):
    lo, hi = V.min(0), V.max(0)
    centre, half = (lo + hi) / 2, 1.1 * (hi - lo) / 2
    return rng.uniform(centre - half, centre + half, (n, 3)).astype(np.float32)


def references(V, F, P, n_sub, n_dist, rng):
    """Exact winding numbers at `n_sub` points, float64 brute-force distances at `n_dist` of them."""
    sys.path.insert(0, str(_common.REPO_ROOT / "tests"))
    import jax
    import reference

    import jaxvox as jv
    import jaxvox.points as jp

    sub = rng.choice(len(P), min(n_sub, len(P)), replace=False)
    idx = jp.mesh_index(jv.Mesh(V.astype(np.float32), F.astype(np.int32)))
    w = np.asarray(jax.block_until_ready(jp.winding_number(idx, P[sub], mode="exact")), np.float64)
    dsub = sub[: min(n_dist, len(sub))]
    d = reference.mesh_distance(V, F, P[dsub].astype(np.float64))
    return dict(sub=sub, w=w, dsub=dsub, d=d, diag=np.linalg.norm(V.max(0) - V.min(0)))


def chart(rows, path, title):
    fig, (left, right) = _common.new_figure(2, width=7.0, height=6.0)
    ok = [r for r in rows if "warm_s" in r]
    y = np.arange(len(ok))
    left.barh(y - 0.2, [r["first_s"] for r in ok], 0.4, label="first call (build, compile)")
    left.barh(y + 0.2, [r["warm_s"] for r in ok], 0.4, label="warm (median)")
    left.set_yticks(y, [r["method"] for r in ok], fontsize=7)
    left.invert_yaxis()
    left.set(xscale="log", xlabel="seconds", title=title)
    for r in ok:
        if "sign_disagree_pct" in r:
            x = max(r["sign_disagree_pct"], 1e-3)
            right.scatter(x, r["points_per_s"], marker="o" if r["method"].startswith("jaxvox") else "s")
            right.annotate(r["method"], (x, r["points_per_s"]), fontsize=7)
    right.set(
        xscale="log",
        yscale="log",
        xlabel="sign disagreement with exact winding number, % (0 drawn at 1e-3)",
        ylabel="points/s (warm)",
        title="speed vs sign accuracy",
    )
    for ax in (left, right):
        ax.grid(alpha=0.3)
    left.legend(fontsize=7)
    _common.save_figure(fig, path)


def fmt(x, f="{:.3g}"):
    return "-" if x is None else f.format(x)


def table(rows):
    cols = [("method", "method"), ("first", "first call s"), ("compiles", "compiles first/warm"), ("warm", "warm s"),
            ("pps", "points/s"), ("with_build", "warm+build s"), ("sign", "sign disagree %"),
            ("amb", "ambiguous n (disagree %)"), ("dist", "max dist err / diag")]  # fmt: skip
    out = []
    for r in rows:
        if "unavailable" in r:
            out.append(dict(method=r["method"], first=r["unavailable"][:120]))
            continue
        out.append(
            dict(
                method=r["method"],
                first=fmt(r["first_s"]),
                compiles=f"{r['compiles_first']}/{r['compiles_warm']}" if r["method"].startswith("jaxvox") else "-",
                warm=fmt(r["warm_s"]),
                pps=fmt(r["points_per_s"]),
                with_build=fmt(r.get("warm_with_build_s")),
                sign=fmt(r.get("sign_disagree_pct")),
                amb=f"{r['ambiguous']} ({fmt(r['ambiguous_disagree_pct'])})" if "ambiguous" in r else "-",
                dist=fmt(r.get("max_dist_err_rel")),
            )
        )
    return _common.markdown_table(out, cols)


def main():
    parser = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    parser.add_argument("--meshes", nargs="+", default=["stanford-bunny"])
    parser.add_argument("--points", type=int, default=1_000_000)
    parser.add_argument("--repeats", type=int, default=3)
    parser.add_argument("--sub", type=int, default=20_000, help="points with an exact winding number")
    parser.add_argument("--dist-sub", type=int, default=2_000, help="points with a brute-force distance")
    parser.add_argument("--check-points", type=int, default=100_000, help="points per query in the compile check")
    parser.add_argument("--methods", nargs="+", default=None, help="name prefixes to run (default: all)")
    parser.add_argument("--timeout", type=float, default=900, help="seconds per worker")
    parser.add_argument("--smoke", action="store_true")
    parser.add_argument("--out", type=Path, default=_common.RESULTS_DIR)
    parser.add_argument("--worker", help=argparse.SUPPRESS)
    args = parser.parse_args()
    if _common.answer_as_worker(args, lambda spec: compile_check(spec) if "compile_check" in spec else worker(spec)):
        return
    if not _common.MESH_DIR.is_dir():
        print(f"no mesh folder at {_common.MESH_DIR}: nothing to measure")
        return
    if args.smoke:
        args.points, args.repeats, args.sub, args.dist_sub, args.check_points = 20_000, 1, 2_000, 200, 10_000
    methods = [m for m in METHODS if args.methods is None or any(m.startswith(p) for p in args.methods)]
    stem = "bench_points" + ("_smoke" if args.smoke else "")
    result = dict(
        machine=dict(_common.machine_info(PACKAGES), plain_process=True),
        source=source_state(),
        date=datetime.datetime.now(datetime.UTC).isoformat(timespec="seconds"),
        settings={k: v for k, v in vars(args).items() if k not in ("worker", "compile_check", "out")},
        meshes={},
    )
    import jaxvox as jv

    md = []
    with tempfile.TemporaryDirectory() as tmp:
        for mesh_name in args.meshes:
            mesh = jv.load_mesh(_common.MESH_DIR / f"{mesh_name}.obj")
            V, F = np.asarray(mesh.vertices, np.float64), np.asarray(mesh.faces, np.int64)
            rng = np.random.default_rng(0)
            P = box_points(V, args.points, rng)
            t0 = time.perf_counter()
            ref = references(V, F, P, args.sub, args.dist_sub, rng)
            print(f"{mesh_name}: {len(F)} faces, references in {time.perf_counter() - t0:.0f} s", flush=True)
            data = Path(tmp) / f"{mesh_name}.npz"
            np.savez(data, V=V, F=F, P=P, **ref)
            rows = []
            for name in _common.progress(methods, desc=mesh_name):
                row = _common.run_worker(
                    __file__, dict(method=name, data=str(data), repeats=args.repeats), timeout=args.timeout
                )
                if "error" in row:
                    row = dict(method=name, unavailable=row["error"])
                rows.append(row)
                print(f"  {name}:", row.get("unavailable") or {k: row.get(k) for k in SUMMARY}, flush=True)
            result["meshes"][mesh_name] = dict(
                faces=len(F), vertices=len(V), points=len(P), ambiguous=int((np.abs(ref["w"] - 0.5) < 0.05).sum()),
                inside_fraction=float((ref["w"] > 0.5).mean()), rows=rows,
            )  # fmt: skip
            md.append(f"## {mesh_name} ({len(F)} faces, {len(P)} points)\n\n" + table(rows))
            _common.write_json(args.out / f"{stem}.json", result)
    if any(m.startswith("jaxvox") for m in methods):
        spec = dict(compile_check=["stanford-bunny", "spot"], points=args.check_points)
        check = result["compile_check"] = _common.run_worker(__file__, spec, timeout=args.timeout)
        print("compile check:", check, flush=True)
        lines = "\n".join(f"- {k}: {v}" for k, v in check.items())
        md.append(f"## compile check (warm-up on the bunny, then spot)\n\n{lines}")
    _common.write_json(args.out / f"{stem}.json", result)
    (args.out / f"{stem}.md").write_text("\n\n".join(md) + "\n")
    print("\n\n".join(md))
    first = next(iter(result["meshes"]))
    chart(result["meshes"][first]["rows"], args.out / f"{stem}.png", f"{first}, {args.points} points, 2-core CPU")


if __name__ == "__main__":
    main()
