"""Classifies every voxel on which Open3D and jaxvox disagree, with the float64 reference.

`bench_voxelize.py` counts Open3D's false positives/negatives against jaxvox's
conservative set. This script looks at each disagreeing voxel and asks the independent
float64 reference (`tests/reference.py`, run on the triangles near that voxel) how far
the geometry is from flipping the decision. A margin within about 1e-4 voxel is a
near-tie: jaxvox widens its float32 tests by that much on purpose (it adds such voxels,
never drops them), and here Open3D reads the OBJ's float64 vertices while jaxvox rounds
them to float32.

Writes ``peer_disagreements.json`` to ``--out`` and prints a summary table.

Example:
  python experiments/peer_disagreements.py --resolutions 256 512 1024
"""

from __future__ import annotations

import argparse
import sys
from pathlib import Path

import _common
import numpy as np

REPO = Path(__file__).resolve().parents[1]
sys.path.insert(0, str(REPO))
from tests.reference import reference_voxelize  # noqa: E402  (test-only reference, not in jaxvox)


def _linear(ijk: np.ndarray, r: int) -> np.ndarray:
    ijk = np.asarray(ijk, np.int64)
    return (ijk[:, 0] * r + ijk[:, 1]) * r + ijk[:, 2]


def classify(mesh_path: Path, resolution: int) -> dict:
    """Open3D vs jaxvox on one mesh and grid; the reference margin of each disagreement."""
    import open3d as o3d

    import jaxvox as jv

    mesh = jv.load_mesh(mesh_path)
    grid = jv.Grid.fit(mesh, resolution=resolution)
    ours = jv.voxelize(mesh, grid).to_numpy()
    import trimesh

    tm = trimesh.load(mesh_path, force="mesh", process=False)
    o3 = o3d.geometry.TriangleMesh(
        o3d.utility.Vector3dVector(np.asarray(tm.vertices, np.float64)),
        o3d.utility.Vector3iVector(np.asarray(tm.faces, np.int32)),
    )
    origin = np.asarray(grid.origin, np.float64)
    h = float(grid.voxel_size)
    vg = o3d.geometry.VoxelGrid.create_from_triangle_mesh_within_bounds(o3, h, origin, origin + resolution * h)
    theirs = np.array([v.grid_index for v in vg.get_voxels()], np.int64).reshape(-1, 3)
    theirs = theirs[((theirs >= 0) & (theirs < resolution)).all(1)]
    a, b = _linear(ours, resolution), _linear(theirs, resolution)
    only_ours = ours[~np.isin(a, b)]
    only_theirs = theirs[~np.isin(b, a)]

    v = np.asarray(mesh.vertices)
    f = np.asarray(mesh.faces)
    p = (v.astype(np.float64) - np.asarray(grid.origin, np.float64)) / np.float64(grid.voxel_size)
    lo, hi = p[f].min(1), p[f].max(1)
    margins = []
    for ijk in np.concatenate([only_ours, only_theirs]):
        near = np.all((lo <= ijk + 2) & (hi >= ijk - 1), axis=1)
        ref = reference_voxelize(v, f[near], grid.origin, grid.voxel_size, resolution)
        margins.append(float(ref.lookup(ijk[None])[0][0]))
    margins = np.array(margins)
    return dict(
        mesh=mesh_path.stem,
        resolution=resolution,
        exact=len(ours),
        open3d_missed=len(only_ours),
        open3d_extra=len(only_theirs),
        max_abs_margin_voxels=float(np.abs(margins).max()) if len(margins) else 0.0,
        margins_missed=margins[: len(only_ours)].tolist(),
        margins_extra=margins[len(only_ours) :].tolist(),
    )


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("--meshes", nargs="+", default=["stanford-bunny"])
    parser.add_argument("--mesh-dir", type=Path, default=REPO.parent / "shared" / "meshes")
    parser.add_argument("--resolutions", nargs="+", type=int, default=[256, 512, 1024])
    parser.add_argument("--out", type=Path, default=REPO / "experiments" / "results")
    args = parser.parse_args()
    rows = [classify(args.mesh_dir / f"{m}.obj", r) for m in args.meshes for r in args.resolutions]
    _common.write_json(args.out / "peer_disagreements.json", dict(machine=_common.machine_info(["open3d"]), rows=rows))
    print(
        _common.markdown_table(
            rows,
            [
                ("mesh", "mesh"),
                ("resolution", "R"),
                ("exact", "exact voxels"),
                ("open3d_missed", "Open3D missed"),
                ("open3d_extra", "Open3D extra"),
                ("max_abs_margin_voxels", "largest |margin| (voxels)"),
            ],
        )
    )


if __name__ == "__main__":
    main()
