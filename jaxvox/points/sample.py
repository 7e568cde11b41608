"""Training data for neural SDFs and occupancy networks: points near a mesh and in its box,
with their signed distances and occupancies (`sample_sdf`), for one mesh or a folder of
meshes (`sample_meshes`, the ``jaxvox sample`` command).

Near-surface points are surface points (uniform by area) moved by isotropic Gaussian
offsets at two scales; the rest are uniform in the mesh's box, padded. Signs come from
the generalized winding number's side of 1/2 (`jaxvox.points.query_points`; from cells for
many points, `jaxvox.points.sides`), so open and broken meshes get the inside their
surface implies.

Files written by `sample_meshes` (one ``<name>.npz`` per mesh, numpy's format):

=============  ===============  ==============================================
key            shape, dtype     meaning
=============  ===============  ==============================================
``points``     [n, 3] float32   sample positions, the mesh's own units
``sdf``        [n] float32      signed distance, negative inside
``occupancy``  [n] bool         inside (winding number > 1/2)
``status``     [n] int32        `PointStatus` (1: winding number near 1/2)
``kind``       [n] int8         0 near (small scale), 1 near (large), 2 uniform
``seed``       [] int64         the seed the mesh's samples were drawn with
=============  ===============  ==============================================
"""

from __future__ import annotations

import dataclasses
import hashlib
import os
import time

import jax
import jax.numpy as jnp
import numpy as np
from jaxtyping import Array, Bool, Float32, Int8, Int32

from jaxvox._core.checks import check_int, check_number, refuse
from jaxvox._core.pytree import pytree_dataclass
from jaxvox.mesh import Mesh
from jaxvox.points.index import MeshIndex, mesh_index
from jaxvox.points.queries import query_flat


@pytree_dataclass
@dataclasses.dataclass(frozen=True)
class SdfSamples:
    """Samples of a mesh's signed distance field (`sample_sdf`).

    Attributes:
      points: [n, 3] float32 positions.
      sdf: [n] float32 signed distance, negative inside.
      occupancy: [n] bool inside.
      status: [n] int32 `jaxvox.points.PointStatus` per point.
      kind: [n] int8 0 near the surface (small scale), 1 near (large scale), 2 uniform.
    """

    points: Float32[Array, "n 3"]
    sdf: Float32[Array, " n"]
    occupancy: Bool[Array, " n"]
    status: Int32[Array, " n"]
    kind: Int8[Array, " n"]


def sample_sdf(
    mesh: Mesh,
    n: int,
    key: jax.Array,
    *,
    fractions: tuple[float, float, float] = (0.4, 0.4, 0.2),
    sigmas: tuple[float, float] = (0.005, 0.05),
    padding: float = 0.1,
    index: MeshIndex | None = None,
) -> SdfSamples:
    """`n` points near `mesh` and in its box with their signed distances and occupancies.

    Host-side: the points are drawn with numpy (seeded from `key`, so deterministic), the
    queries size their search on the host. Meshes whose face counts share a ladder bucket
    share the compiled queries: a dataset compiles once per bucket, not once per mesh.

    Args:
      mesh: `Mesh` with faces of nonzero total area.
      n: number of samples, >= 1.
      key: a `jax.random` key.
      fractions: shares of near points at the small and the large scale and of uniform
        points (non-negative, summing to 1; counts are rounded, the rest go to uniform).
      sigmas: standard deviations of the near points' Gaussian offsets, as fractions of
        the mesh's bounding-box diagonal.
      padding: the uniform box is the mesh's box grown by this fraction of its extent on
        every side.
      index: the mesh's `MeshIndex` when already built (else it is built here).

    Returns:
      `SdfSamples` in the order near (small), near (large), uniform.

    Raises:
      JaxvoxError: bad n, fractions, sigmas or padding; a mesh without area.
    """
    n = check_int("sample_sdf n", n, minimum=1)
    shares = [check_number("sample_sdf fractions", f, minimum=0.0) for f in fractions]
    if len(shares) != 3 or abs(sum(shares) - 1.0) > 1e-6:
        raise refuse("sample_sdf fractions", "must be three shares summing to 1", fractions)
    scales = [check_number("sample_sdf sigmas", s, minimum=0.0) for s in sigmas]
    if len(scales) != 2:
        raise refuse("sample_sdf sigmas", "must be two scales", sigmas)
    padding = check_number("sample_sdf padding", padding, minimum=0.0)
    index = mesh_index(mesh) if index is None else index
    v = np.asarray(mesh.vertices, np.float64)
    f = np.asarray(mesh.faces)
    tris = v[f]
    area = 0.5 * np.linalg.norm(np.cross(tris[:, 1] - tris[:, 0], tris[:, 2] - tris[:, 0]), axis=1)
    if not area.sum() > 0:
        raise refuse("sample_sdf mesh", "has no surface area", float(area.sum()))
    lo, hi = tris.reshape(-1, 3).min(0), tris.reshape(-1, 3).max(0)
    diag = float(np.linalg.norm(hi - lo))
    counts = [round(n * shares[0]), round(n * shares[1])]
    counts.append(n - sum(counts))
    rng = np.random.default_rng(np.asarray(jax.random.key_data(key)).ravel().tolist())
    near = counts[0] + counts[1]
    tri = rng.choice(len(f), near, p=area / area.sum())
    u, w = rng.random((2, near))
    root = np.sqrt(u)[:, None]
    corners = tris[tri]
    surface = (1 - root) * corners[:, 0] + root * (1 - w[:, None]) * corners[:, 1] + root * w[:, None] * corners[:, 2]
    scale = np.repeat(np.asarray(scales) * diag, counts[:2])[:, None]
    grow = (hi - lo) * padding
    uniform = (lo - grow) + rng.random((counts[2], 3)) * (hi - lo + 2 * grow)
    points = np.concatenate([surface + scale * rng.standard_normal((near, 3)), uniform]).astype(np.float32)
    # the side is all a sample needs: sides from cells for many points (statuses stay exact
    # for margins up to `jaxvox.points.sides.MARGIN`)
    q = query_flat(index, jax.device_put(points), (len(points),), sign="winding", margin=0.01, winding_numbers=False)
    kind = np.repeat(np.arange(3, dtype=np.int8), counts)
    return SdfSamples(jnp.asarray(points), q.signed_distance, q.inside, q.status, jnp.asarray(kind))


def mesh_seed(seed: int, name: str) -> int:
    """The seed of one mesh's samples: `seed` mixed with the file name (stable across runs
    and across the order files are processed in)."""
    digest = hashlib.sha256(f"{seed}:{name}".encode()).digest()
    return int.from_bytes(digest[:4], "little")


def sample_meshes(
    paths: list[str], out: str, *, n: int, seed: int = 0, progress: bool | None = None, **options
) -> dict[str, str]:
    """`sample_sdf` for each mesh file, one ``<stem>.npz`` in `out` each (module docstring).

    Resumable: a mesh whose file already exists is skipped ("done"); files are written to
    a temporary name and renamed, so an interrupted run leaves no partial file. A mesh
    that cannot be read, is empty, holds non-finite vertices or has no area is reported
    ("error: ...") and skipped; the others go on. Prints one status line per mesh.

    Args:
      paths: mesh files (anything `jaxvox.load_mesh` reads).
      out: output folder (created).
      n: samples per mesh.
      seed: base seed; each mesh draws with `mesh_seed` (seed, file name).
      progress: show a progress bar (default: when stderr is a terminal).
      options: passed to `sample_sdf`.

    Returns:
      {path: status} with status "written", "done" or "error: <message>".
    """
    from tqdm import tqdm

    from jaxvox._core.errors import JaxvoxError
    from jaxvox.io.meshes import load_mesh

    os.makedirs(out, exist_ok=True)
    report: dict[str, str] = {}
    bar = tqdm(paths, unit="mesh", disable=not (os.isatty(2) if progress is None else progress))
    for path in bar:
        stem = os.path.splitext(os.path.basename(path))[0]
        target = os.path.join(out, stem + ".npz")
        if os.path.exists(target):
            report[path] = "done"
            bar.write(f"{stem}: done already")
            continue
        start = time.perf_counter()
        try:
            mesh = load_mesh(path)
            if mesh.num_faces == 0:
                raise JaxvoxError("the mesh has no faces")
            s = mesh_seed(seed, os.path.basename(path))
            samples = sample_sdf(mesh, n, jax.random.PRNGKey(s), **options)
        except (JaxvoxError, OSError, ValueError) as exc:
            report[path] = f"error: {exc}"
            bar.write(f"{stem}: skipped ({exc})")
            continue
        arrays: dict[str, np.ndarray] = {
            k: np.asarray(getattr(samples, k)) for k in ("points", "sdf", "occupancy", "status", "kind")
        }
        arrays["seed"] = np.asarray(s, np.int64)
        partial = target + ".partial.npz"
        with open(partial, "wb") as file:
            np.savez(file, **arrays)  # type: ignore[arg-type]
        os.replace(partial, target)
        report[path] = "written"
        uncertain = int((arrays["status"] == 1).sum())
        bar.write(
            f"{stem}: {mesh.num_faces} faces, {n} samples, {np.mean(arrays['occupancy']):.1%} inside, "
            f"{uncertain} uncertain, {time.perf_counter() - start:.2f} s"
        )
    return report
