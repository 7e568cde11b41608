"""Where inside/outside signs fail: jaxvox's winding and pseudonormal signs against peers on bad meshes.

Meshes (from the shared mesh folder, damage generated deterministically with numpy):

* ``spot``: closed and consistently oriented;
* ``stanford-bunny``: open at the bottom;
* ``teapot``: open and self-intersecting;
* ``spot-union``: two overlapping copies of spot, the second shifted along x by 30% of its
  size (triangles concatenated: self-intersecting, winding number 2 in the overlap);
* ``spot-damaged``: spot with ~5% of its faces removed in 4 patches (holes), 2% duplicated
  and 2% flipped.

For each mesh, ``--points`` (100k) points uniform in the box scaled by 1.1 about its centre
(seed 0) are classified by every method: jaxvox ``signed_distance`` (winding and
pseudonormal), libigl ``signed_distance`` (fast winding number and pseudonormal), Open3D
``compute_signed_distance`` (ray parity), Warp (winding-number and normal signs) and pysdf;
the method definitions are shared with `bench_points.py` (`_point_methods.py`). Sign disagreement is the % of a
``--sub`` (8k) subsample where the method's inside differs from the exact winding number's
``w > 1/2`` (``jp.winding_number(mode="exact")``), over points with ``|w - 1/2| >= 0.05``
(the others are counted apart). For ``spot-damaged`` the disagreement with the clean spot's
winding number (the intended shape) is reported too. jaxvox's ``query_points`` UNCERTAIN
count (``status == 1``) is reported for both signs.

All meshes and methods run in one process (so compiled jaxvox programs are reused after the
first mesh: first-call times there include compilation, see `bench_points.py` for fresh-process
first calls); warm time is the median of ``--repeats`` calls after the first.

Outputs ``sign_failures.json``, ``.md`` and ``.png`` (points/s against sign disagreement, one
panel per mesh) in ``--out``.

Examples:
  python experiments/sign_failures.py                 # 100k points, 5 meshes
  python experiments/sign_failures.py --smoke         # 10k points, 2k subsample, *_smoke outputs
"""

from __future__ import annotations

import argparse
import datetime
import statistics
import time
from pathlib import Path

import _common
import numpy as np
from _point_methods import METHODS, inside_of
from bench_points import PACKAGES, box_points, disagreement, fmt, source_state

SIGN_METHODS = [
    "jaxvox SD winding",
    "jaxvox SD pseudonormal",
    "libigl SD fast winding",
    "libigl SD pseudonormal",
    "Open3D signed distance",
    "Warp winding sign",
    "Warp normal sign",
    "pysdf",
]
MESHES = ["spot", "stanford-bunny", "teapot", "spot-union", "spot-damaged"]


def load(name):
    import jaxvox as jv

    mesh = jv.load_mesh(_common.MESH_DIR / f"{name}.obj")
    return np.asarray(mesh.vertices, np.float64), np.asarray(mesh.faces, np.int64)


def union(V, F):
    """Two copies of the mesh, the second shifted along x by 30% of the mesh's size."""
    shift = np.array([0.3 * np.ptp(V, 0).max(), 0.0, 0.0])
    return np.concatenate([V, V + shift]), np.concatenate([F, F + len(V)])


def damage(V, F, seed=0, holes=4, removed=0.05, duplicated=0.02, flipped=0.02):
    """Holes (``removed`` of the faces in `holes` patches of nearest centroids), then duplicated and flipped faces."""
    rng = np.random.default_rng(seed)
    centroid = V[F].mean(1)
    gone = np.zeros(len(F), bool)
    per_hole = int(removed * len(F) / holes)
    for seed_face in rng.choice(len(F), holes, replace=False):
        near = np.argsort(np.linalg.norm(centroid - centroid[seed_face], axis=1))
        gone[near[:per_hole]] = True
    F = F[~gone].copy()
    flip = rng.choice(len(F), int(flipped * len(F)), replace=False)
    F[flip] = F[flip, ::-1]
    dup = rng.choice(len(F), int(duplicated * len(F)), replace=False)
    stats = dict(removed_faces=int(gone.sum()), flipped_faces=len(flip), duplicated_faces=len(dup))
    return V, np.concatenate([F, F[dup]]), stats


def meshes(names):
    for name in names:
        if name == "spot-union":
            yield name, *union(*load("spot")), {}
        elif name == "spot-damaged":
            yield name, *damage(*load("spot"))
        else:
            yield name, *load(name), {}


def exact_winding(V, F, P):
    import jax

    import jaxvox as jv
    import jaxvox.points as jp

    idx = jp.mesh_index(jv.Mesh(V.astype(np.float32), F.astype(np.int32)))
    return np.asarray(jax.block_until_ready(jp.winding_number(idx, P, mode="exact")), np.float64)


def uncertain_counts(V, F, P):
    import jaxvox as jv
    import jaxvox.points as jp

    idx = jp.mesh_index(jv.Mesh(V.astype(np.float32), F.astype(np.int32)))
    out = {}
    for sign in ("winding", "pseudonormal"):
        status = np.asarray(jp.query_points(idx, P, sign=sign).status)
        out[sign] = int((status == int(jp.PointStatus.UNCERTAIN)).sum())
        out[f"{sign}_statuses"] = {s.name: int((status == int(s)).sum()) for s in jp.PointStatus}
    return out


def run_mesh(name, V, F, extra, args, rng):
    P = box_points(V, args.points, rng)
    sub = rng.choice(len(P), min(args.sub, len(P)), replace=False)
    t0 = time.perf_counter()
    w = exact_winding(V, F, P[sub])
    w_clean = exact_winding(*load("spot"), P[sub]) if name == "spot-damaged" else None
    out = dict(
        mesh=name, faces=len(F), points=len(P), sub=len(sub), reference_s=time.perf_counter() - t0,
        inside_fraction=float((w > 0.5).mean()), winding_range=[float(w.min()), float(w.max())], **extra, rows=[],
    )  # fmt: skip
    try:
        out["uncertain"] = uncertain_counts(V, F, P)
    except Exception as e:
        out["uncertain"] = f"failed: {type(e).__name__}: {e}"[:400]
    for method in _common.progress(SIGN_METHODS, desc=name):
        setup, query = METHODS[method]
        row = dict(method=method)
        try:
            t0 = time.perf_counter()
            state = setup(V, F)
            kind, values = query(state, P)
            row["first_s"] = time.perf_counter() - t0
            times = []
            for _ in range(args.repeats):
                t0 = time.perf_counter()
                kind, values = query(state, P)
                times.append(time.perf_counter() - t0)
            row.update(warm_s=statistics.median(times), points_per_s=len(P) / statistics.median(times))
            inside = inside_of(kind, np.asarray(values)[sub])
            row.update(disagreement(inside, w))
            if w_clean is not None:
                row["vs_clean_spot"] = disagreement(inside, w_clean)
        except Exception as e:
            row["unavailable"] = f"{type(e).__name__}: {e}"[:400]
        out["rows"].append(row)
        print(f"  {name} {method}: " + (row.get("unavailable") or
              f"{fmt(row['sign_disagree_pct'])} % wrong, warm {row['warm_s']:.3f} s"), flush=True)  # fmt: skip
    return out


def chart(results, path):
    fig, axes = _common.new_figure(len(results), width=4.5, height=4.5)
    for ax, res in zip(np.atleast_1d(axes), results):
        for r in res["rows"]:
            if "warm_s" in r:
                x = max(r["sign_disagree_pct"], 1e-3)
                ax.scatter(x, r["points_per_s"], marker="o" if r["method"].startswith("jaxvox") else "s")
                ax.annotate(r["method"], (x, r["points_per_s"]), fontsize=6)
        ax.set(xscale="log", yscale="log", title=f"{res['mesh']} ({res['faces']} faces)",
               xlabel="sign disagreement % (0 drawn at 1e-3)", ylabel="points/s (warm)")  # fmt: skip
        ax.grid(alpha=0.3)
    _common.save_figure(fig, path)


def main():
    parser = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    parser.add_argument("--meshes", nargs="+", default=MESHES)
    parser.add_argument("--points", type=int, default=100_000)
    parser.add_argument("--sub", type=int, default=8_000, help="points with an exact winding number")
    parser.add_argument("--repeats", type=int, default=2)
    parser.add_argument("--smoke", action="store_true")
    parser.add_argument("--out", type=Path, default=_common.RESULTS_DIR)
    args = parser.parse_args()
    if not _common.MESH_DIR.is_dir():
        print(f"no mesh folder at {_common.MESH_DIR}: nothing to measure")
        return
    if args.smoke:
        args.points, args.sub, args.repeats = 10_000, 2_000, 1
    stem = "sign_failures" + ("_smoke" if args.smoke else "")
    result = dict(
        machine=dict(_common.machine_info(PACKAGES), plain_process=True),
        source=source_state(),
        date=datetime.datetime.now(datetime.UTC).isoformat(timespec="seconds"),
        settings={k: v for k, v in vars(args).items() if k != "out"},
        meshes=[],
    )
    rng = np.random.default_rng(0)
    for name, V, F, extra in meshes(args.meshes):
        result["meshes"].append(run_mesh(name, V, F, extra, args, rng))
        _common.write_json(args.out / f"{stem}.json", result)
    cols = [("mesh", "mesh"), *[(m, m) for m in SIGN_METHODS], ("unc", "jaxvox UNCERTAIN (winding / pseudonormal)")]
    rows = []
    for res in result["meshes"]:
        row = dict(mesh=res["mesh"])
        for r in res["rows"]:
            if "unavailable" in r:
                row[r["method"]] = "unavailable"
                continue
            row[r["method"]] = f"{r['sign_disagree_pct']:.3g} % ({r['points_per_s']:.3g} pts/s)"
            if "vs_clean_spot" in r:
                row[r["method"]] += f", clean spot {r['vs_clean_spot']['sign_disagree_pct']:.3g} %"
        unc = res["uncertain"]
        row["unc"] = f"{unc['winding']} / {unc['pseudonormal']}" if isinstance(unc, dict) else unc[:80]
        rows.append(row)
    md = _common.markdown_table(rows, cols)
    (args.out / f"{stem}.md").write_text(md)
    print(md)
    chart(result["meshes"], args.out / f"{stem}.png")


if __name__ == "__main__":
    main()
