"""`jaxvox sample` on a dataset of 100 meshes: time per mesh, compiles, resumption.

The dataset is made from the shared test meshes (`../shared/meshes`): each of the 100
meshes is one of them under a random rotation and scale, a third of them damaged (a few
patches of faces removed, some faces flipped, some duplicated), plus two bad files (an
empty mesh and unreadable text) that must be reported and skipped. `sample_meshes` (what
the command runs) writes one `.npz` per mesh; the script records each mesh's time, the
programs compiled while sampling it, then deletes a third of the outputs and runs again
to check that only those are redone.

Writes ``sample_dataset.json`` and ``.png`` (time per mesh in processing order, compiles
marked) to ``--out`` (default ``experiments/results``).

  python experiments/sample_dataset.py                  # 100 meshes, 250k samples each
  python experiments/sample_dataset.py --meshes 12 --samples 20000   # quick
"""

from __future__ import annotations

import argparse
import json
import os
import platform
import sys
import tempfile
import time

import numpy as np

sys.path.insert(0, os.path.dirname(__file__))
from _common import MESH_DIR, RESULTS_DIR  # noqa: E402


def make_dataset(folder: str, count: int, seed: int = 0) -> list[str]:
    """`count` transformed (and a third of them damaged) copies of the shared meshes, plus two bad files."""
    import trimesh

    rng = np.random.default_rng(seed)
    sources = sorted(p for p in os.listdir(MESH_DIR) if p.endswith(".obj"))
    meshes = {name: trimesh.load(os.path.join(MESH_DIR, name), force="mesh", process=False) for name in sources}
    paths = []
    for i in range(count):
        name = sources[i % len(sources)]
        m = meshes[name]
        q, _ = np.linalg.qr(rng.normal(size=(3, 3)))
        v = (m.vertices - m.vertices.mean(0)) @ q.T * rng.uniform(0.5, 2.0)
        f = np.asarray(m.faces)
        if i % 3 == 2:  # damaged: holes, flipped and duplicated faces
            centres = v[f].mean(1)
            for c in v[rng.choice(len(v), 3)]:
                radius = np.sort(np.linalg.norm(centres - c, axis=1))[max(1, len(f) // 60)]
                keep = np.linalg.norm(centres - c, axis=1) > radius
                f, centres = f[keep], centres[keep]
            flip = rng.random(len(f)) < 0.02
            f[flip] = f[flip][:, ::-1]
            f = np.concatenate([f, f[rng.random(len(f)) < 0.02]])
        path = os.path.join(folder, f"{i:03d}_{name[:-4]}.obj")
        trimesh.Trimesh(v, f, process=False).export(path)
        paths.append(path)
    for bad, text in (("empty.obj", "# nothing\n"), ("garbage.obj", "not a mesh at all\n")):
        with open(os.path.join(folder, bad), "w") as file:
            file.write(text)
        paths.append(os.path.join(folder, bad))
    return paths


def main() -> int:
    parser = argparse.ArgumentParser(description=__doc__.split("\n")[0])
    parser.add_argument("--meshes", type=int, default=100)
    parser.add_argument("--samples", type=int, default=250_000)
    parser.add_argument("--out", default=str(RESULTS_DIR))
    args = parser.parse_args()
    if not MESH_DIR.is_dir():
        print(f"shared meshes not found at {MESH_DIR}: nothing to do")
        return 0
    import jax

    from jaxvox.points import sample as sampling

    compiles: list[float] = []
    jax.monitoring.register_event_duration_secs_listener(
        lambda name, secs, **_: compiles.append(secs) if name == "/jax/core/compile/backend_compile_duration" else None
    )
    rows = []
    original = sampling.sample_sdf

    def timed(mesh, n, key, **options):  # per-mesh time and compiles, around the library call
        before, start = len(compiles), time.perf_counter()
        out = jax.block_until_ready(original(mesh, n, key, **options))
        rows.append(
            {"faces": mesh.num_faces, "seconds": time.perf_counter() - start, "compiles": len(compiles) - before}
        )
        return out

    sampling.sample_sdf = timed
    with tempfile.TemporaryDirectory() as work:
        src, dst = os.path.join(work, "meshes"), os.path.join(work, "out")
        os.makedirs(src)
        paths = make_dataset(src, args.meshes)
        start = time.perf_counter()
        report = sampling.sample_meshes(paths, dst, n=args.samples, seed=0)
        first_run = time.perf_counter() - start
        written = sorted(os.listdir(dst))
        for name in written[::3]:
            os.remove(os.path.join(dst, name))
        rows_before = len(rows)
        start = time.perf_counter()
        again = sampling.sample_meshes(paths, dst, n=args.samples, seed=0)
        second_run = time.perf_counter() - start
    redone = len(rows) - rows_before
    seconds = np.array([r["seconds"] for r in rows[:rows_before]])
    result = {
        "machine": {"cpu": platform.processor() or platform.machine(), "cores": os.cpu_count(), "jax": jax.__version__},
        "meshes": args.meshes,
        "samples": args.samples,
        "statuses": {s: sum(v.startswith(s) for v in report.values()) for s in ("written", "done", "error")},
        "first_run_s": first_run,
        "per_mesh_s": {"median": float(np.median(seconds)), "min": float(seconds.min()), "max": float(seconds.max())},
        "compiles_total": int(sum(r["compiles"] for r in rows[:rows_before])),
        "meshes_that_compiled": int(sum(r["compiles"] > 0 for r in rows[:rows_before])),
        "resumed_run": {
            "redone": redone,
            "deleted": len(written[::3]),
            "seconds": second_run,
            "statuses": {s: sum(v.startswith(s) for v in again.values()) for s in ("written", "done", "error")},
        },
        "per_mesh": rows[:rows_before],
    }
    os.makedirs(args.out, exist_ok=True)
    with open(os.path.join(args.out, "sample_dataset.json"), "w") as file:
        json.dump(result, file, indent=1)
    import matplotlib

    matplotlib.use("Agg")
    import matplotlib.pyplot as plt

    fig, ax = plt.subplots(figsize=(8, 3.5))
    ax.bar(range(len(seconds)), seconds, color=["C3" if r["compiles"] else "C0" for r in rows[:rows_before]])
    ax.set_xlabel("mesh (processing order); red: compiled programs")
    ax.set_ylabel("seconds")
    ax.set_title(f"jaxvox sample: {args.meshes} meshes x {args.samples} samples (median {np.median(seconds):.2f} s)")
    fig.tight_layout()
    fig.savefig(os.path.join(args.out, "sample_dataset.png"), dpi=120)
    print(json.dumps({k: v for k, v in result.items() if k != "per_mesh"}, indent=1))
    return 0


if __name__ == "__main__":
    sys.exit(main())
