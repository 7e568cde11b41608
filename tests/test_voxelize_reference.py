"""jaxvox.voxelize against the independent float64 numpy reference in ``reference.py``.

Two groups of tests:

* the reference on its own (Morton helper, hand-made cases, brute-force polygon clipping,
  the meaning of its margins, 6-separation of a closed mesh), so that it can be trusted;
* the implementation against the reference: real meshes at 64^3 and 128^3, hypothesis
  triangles (general, slivers, degenerate, on voxel planes and voxel edges, huge), the
  subset relation between the modes, and 6-separation by flood fill.

Mismatches are allowed only on near-ties: voxels whose reference margin is within the
deciding triangle's tolerance (``reference.triangle_tolerance``: ``1e-4 * (1 + L) * cond``
voxels, ``L`` the longest edge in voxels, ``cond = L / min altitude``). Inputs on the dyadic
lattice (multiples of 1/8 voxel, origin 0, voxel size 1, small coordinates) are exact in
float32 and float64 alike and must match exactly.
"""

from __future__ import annotations

import functools
import itertools
import math
import os

import numpy as np
import pytest
import scipy.ndimage
import trimesh
from hypothesis import HealthCheck, example, given, settings
from hypothesis import strategies as st

import jaxvox as jv
from tests.reference import MODES, Reference, morton_encode, morton_order, reference_voxelize, winding_number

CONSERVATIVE, SIX_SEP = MODES
MESHES = ("beetle", "cow", "fandisk", "spot", "stanford-bunny", "suzanne", "teapot", "woody")
CLOSED_MESHES = ("spot", "cow", "fandisk")
MAX_EXCUSED_FRACTION = 1e-3  # excused near-tie voxels per reference voxel on real meshes


def _slow_resolution(resolution: int) -> int:
    """Resolution of a slow case: ``JAXVOX_SLOW_SCALE`` is ``full`` (as written), a factor, or
    unset (half size); rounded to a power of two, at least 16."""
    raw = os.environ.get("JAXVOX_SLOW_SCALE", "").strip().lower()
    scale = 1.0 if raw == "full" else float(raw) if raw else 0.5
    return max(16, 2 ** round(math.log2(max(resolution * scale, 1))))


# --------------------------------------------------------------------------------------------
# Helpers
# --------------------------------------------------------------------------------------------


def _unit_grid(resolution: int):
    return jv.Grid(origin=(0.0, 0.0, 0.0), voxel_size=1.0, resolution=resolution)


def _grid_params(grid):
    origin = np.asarray(grid.origin, dtype=np.float32).reshape(3)
    voxel_size = np.asarray(grid.voxel_size, dtype=np.float32).reshape(())
    return origin, voxel_size, int(grid.resolution)


def _impl(vertices, faces, grid, mode) -> np.ndarray:
    mesh = jv.Mesh(np.asarray(vertices, np.float32), np.asarray(faces, np.int32))
    return np.asarray(jv.voxelize(mesh, grid, mode=mode).to_numpy())


def _reference(vertices, faces, grid, mode) -> Reference:
    origin, voxel_size, resolution = _grid_params(grid)
    return reference_voxelize(vertices, faces, origin, voxel_size, resolution, mode)


def _check_format(got: np.ndarray, resolution: int) -> None:
    assert got.ndim == 2 and got.shape[1] == 3, got.shape
    assert got.dtype == np.int32, got.dtype
    if len(got):
        assert got.min() >= 0 and got.max() < resolution, "voxel index outside the grid"
        codes = morton_encode(got)
        assert np.all(np.diff(codes.astype(np.int64)) > 0), "voxels not unique and in Morton order"


def _keys(ijk, resolution):
    ijk = np.asarray(ijk, np.int64).reshape(-1, 3)
    return (ijk[:, 0] * resolution + ijk[:, 1]) * resolution + ijk[:, 2]


def _unkey(keys, resolution):
    keys = np.asarray(keys, np.int64)
    return np.stack([keys // resolution**2, (keys // resolution) % resolution, keys % resolution], 1)


class Comparison:
    """Set difference between the implementation and the reference, with margins."""

    def __init__(self, ref: Reference, got: np.ndarray):
        r = ref.resolution
        want_k, got_k = _keys(ref.voxels, r), _keys(got, r)
        self.n_ref, self.n_got = len(want_k), len(got_k)
        self.missing = _unkey(np.setdiff1d(want_k, got_k), r)  # reference sets, impl does not
        self.extra = _unkey(np.setdiff1d(got_k, want_k), r)  # impl sets, reference does not
        self.margin_missing, rel_missing = ref.lookup(self.missing)
        self.margin_extra, rel_extra = ref.lookup(self.extra)
        self.ok_missing = np.abs(rel_missing) <= 1.0
        self.ok_extra = np.abs(rel_extra) <= 1.0

    @property
    def n_excused(self) -> int:
        return int(self.ok_missing.sum() + self.ok_extra.sum())

    @property
    def n_bad(self) -> int:
        return int((~self.ok_missing).sum() + (~self.ok_extra).sum())

    @property
    def n_mismatch(self) -> int:
        return len(self.missing) + len(self.extra)

    def report(self, limit: int = 8) -> str:
        lines = [
            f"reference {self.n_ref} voxels, implementation {self.n_got}; "
            f"missing {len(self.missing)} ({int((~self.ok_missing).sum())} not excused), "
            f"extra {len(self.extra)} ({int((~self.ok_extra).sum())} not excused)"
        ]
        for name, ijk, margin, ok in (
            ("missing", self.missing, self.margin_missing, self.ok_missing),
            ("extra", self.extra, self.margin_extra, self.ok_extra),
        ):
            order = np.argsort(ok, kind="stable")  # unexcused first
            for idx in order[:limit]:
                tag = "excused" if ok[idx] else "NOT excused"
                lines.append(f"  {name} {tuple(int(x) for x in ijk[idx])}: margin {margin[idx]:.3g} voxel ({tag})")
        return "\n".join(lines)


def _assert_matches(ref: Reference, got: np.ndarray, context: str, *, exact: bool) -> Comparison:
    _check_format(got, ref.resolution)
    cmp = Comparison(ref, got)
    if exact:
        assert cmp.n_mismatch == 0, f"{context}: exact input must match exactly\n{cmp.report()}"
    else:
        assert cmp.n_bad == 0, f"{context}: mismatches beyond the near-tie tolerance\n{cmp.report()}"
    return cmp


def _assert_subset(six: np.ndarray, cons: np.ndarray, ref_cons: Reference, context: str, *, exact: bool):
    """6-separating voxels must be conservative voxels (up to conservative near-ties)."""
    r = ref_cons.resolution
    outside = _unkey(np.setdiff1d(_keys(six, r), _keys(cons, r)), r)
    if not exact and len(outside):
        _, rel = ref_cons.lookup(outside)
        outside = outside[np.abs(rel) > 1.0]
    assert len(outside) == 0, f"{context}: 6-separating voxels not in the conservative set: {outside[:8].tolist()}"


# --------------------------------------------------------------------------------------------
# The reference on its own
# --------------------------------------------------------------------------------------------


def _morton_python(i: int, j: int, k: int) -> int:
    code = 0
    for b in range(21):
        code |= ((i >> b) & 1) << (3 * b) | ((j >> b) & 1) << (3 * b + 1) | ((k >> b) & 1) << (3 * b + 2)
    return code


@settings(max_examples=50, deadline=None)
@given(st.lists(st.tuples(*[st.integers(0, 2**21 - 1)] * 3), min_size=1, max_size=20))
def test_morton_helper_matches_python_ints(points):
    codes = morton_encode(np.array(points))
    assert [int(c) for c in codes] == [_morton_python(*p) for p in points]
    ordered = morton_order(np.array(points))
    assert [tuple(p) for p in ordered.tolist()] == sorted(map(tuple, points), key=lambda p: _morton_python(*p))


_BOX = st.tuples(*[st.integers(0, 2**20 - 4)] * 3, *[st.integers(0, 3)] * 3)  # first cell, extent


@settings(max_examples=50, deadline=None)
@given(st.lists(_BOX, max_size=12), st.sampled_from([16, 1000, 2**20 - 4]))
def test_box_cells_are_every_cell_in_morton_then_id_order(boxes, span):
    """`jaxvox.morton.box_cells` (the voxelizer's regions, the sparse field's tiles) against
    Python loops over each box's cells, with Python-int Morton codes; the first cells lie
    below `span` per axis: 16 keeps the codes below 2^16 (the radix sort of 16-bit keys),
    1000 the cells below 1024 (the packed sort), else they may pass it (the stable argsort)."""
    first = np.array([b[:3] for b in boxes], np.int64).reshape(-1, 3) % span
    last = first + np.array([b[3:] for b in boxes], np.int64).reshape(-1, 3)
    ids = np.arange(len(boxes), dtype=np.int64) * 3  # ascending, not 0..n-1
    expected = sorted(
        (_morton_python(*cell), int(box_id))
        for box_id, lo, hi in zip(ids, first, last)
        for cell in itertools.product(*(range(a, b + 1) for a, b in zip(lo, hi)))
    )
    got_ids, got_codes = jv.morton.box_cells(ids, first, last)
    assert got_ids.dtype == np.int64 and got_codes.dtype == np.uint64
    assert list(zip(got_codes.tolist(), got_ids.tolist())) == expected


@settings(max_examples=50, deadline=None)
@given(st.lists(st.integers(0, 5), max_size=30))
def test_run_starts_are_the_first_index_of_each_run(values):
    """`jaxvox.morton.run_starts` (regions, tiles, blocks, edges) against a Python loop."""
    keys = np.sort(np.array(values, np.uint64))
    expected = [i for i in range(len(keys)) if i == 0 or keys[i] != keys[i - 1]]
    got = jv.morton.run_starts(keys)
    assert got.dtype == np.int64 and got.tolist() == expected


@settings(max_examples=50, deadline=None)
@given(st.lists(st.integers(0, 2**62), max_size=40), st.sampled_from(["int64", "uint64", "int32"]), st.integers(0, 3))
def test_stable_order_is_numpys_stable_argsort(values, dtype, spread):
    """`jaxvox.morton.stable_order_host` (edge tables, crossings' cells, curve orders)
    against ``np.argsort(kind="stable")``: many ties (values folded onto 3 keys), keys
    too large to pack beside their index, and a negative key (both take the argsort)."""
    keys = np.array(values, np.uint64) % np.uint64([3, 1000, 2**31 - 1, 2**62][spread])
    keys = keys.astype(dtype)
    if spread == 0 and len(keys) and dtype != "uint64":
        keys[0] = -1
    got = jv.morton.stable_order_host(keys)
    assert got.dtype == np.int64 and got.tolist() == np.argsort(keys, kind="stable").tolist()


def _ref1(tri, resolution=8, mode=CONSERVATIVE) -> Reference:
    return reference_voxelize(
        np.asarray(tri, np.float32), [[0, 1, 2]], np.zeros(3, np.float32), np.float32(1.0), resolution, mode
    )


def _as_set(voxels):
    return set(map(tuple, np.asarray(voxels).tolist()))


def test_reference_points_and_segments():
    # a point inside a voxel, on a face, on an edge, on a corner
    for p, n in (((2.5, 3.5, 4.5), 1), ((2.0, 3.5, 4.5), 2), ((2.0, 3.0, 4.5), 4), ((2.0, 3.0, 4.0), 8)):
        ref = _ref1([p] * 3)
        assert len(ref.voxels) == n, (p, ref.voxels)
        assert len(_ref1([p] * 3, mode=SIX_SEP).voxels) == 0  # zero area: nothing in 6-separating mode
    # a point on the outer face of the grid touches only the voxel inside the grid
    assert _as_set(_ref1([(8.0, 3.5, 3.5)] * 3).voxels) == {(7, 3, 3)}
    # a segment along a voxel edge: the four voxels around it, over its length
    ref = _ref1([(2, 3, 1), (2, 3, 1), (2, 3, 4)])
    assert _as_set(ref.voxels) == {(i, j, k) for i in (1, 2) for j in (2, 3) for k in range(0, 5)}
    # a diagonal segment through voxel corners in the xy plane
    ref = _ref1([(1, 1, 0.5), (3, 3, 0.5), (3, 3, 0.5)])
    assert _as_set(ref.voxels) == {
        (0, 0, 0),
        (1, 1, 0),
        (2, 2, 0),
        (3, 3, 0),
        (0, 1, 0),
        (1, 0, 0),
        (1, 2, 0),
        (2, 1, 0),
        (2, 3, 0),
        (3, 2, 0),
    }


def test_reference_triangle_in_voxel_plane_sets_both_layers():
    tri = [(0.5, 0.5, 3.0), (5.5, 1.0, 3.0), (2.0, 6.0, 3.0)]
    for mode in MODES:
        vox = _ref1(tri, mode=mode).voxels
        layers = {k: {(i, j) for i, j, kk in vox.tolist() if kk == k} for k in (2, 3)}
        assert set(vox[:, 2].tolist()) == {2, 3}, mode
        assert layers[2] == layers[3], mode
    # a large triangle covering a whole voxel plane inside the grid: two full layers
    big = [(-20.0, -20.0, 4.0), (60.0, -20.0, 4.0), (-20.0, 60.0, 4.0)]
    for mode in MODES:
        assert _as_set(_ref1(big, mode=mode).voxels) == {(i, j, k) for i in range(8) for j in range(8) for k in (3, 4)}
    # the same plane at a half coordinate: one layer in both modes
    for mode in MODES:
        mid = [(x, y, 4.5) for x, y, _ in big]
        assert len(_ref1(mid, mode=mode).voxels) == 64


def test_reference_outside_grid_is_empty():
    for mode in MODES:
        assert len(_ref1([(9, 9, 9), (12, 9, 9), (9, 12, 9.5)], mode=mode).voxels) == 0
        assert len(_ref1([(-3, 1, 1), (-1.01, 1, 1), (-2, 5, 3)], mode=mode).voxels) == 0
    # touching the grid's outer face from outside sets the boundary voxels (conservative)
    assert len(_ref1([(-3, 1.5, 1.5), (0.0, 1.5, 1.5), (-2, 1.5, 1.5)]).voxels) == 1


def _clip(poly: np.ndarray, normal: np.ndarray, offset: float) -> np.ndarray:
    """Sutherland-Hodgman: the part of a convex polygon with ``normal . x <= offset``."""
    if len(poly) == 0:
        return poly
    s = poly @ normal - offset
    out = []
    for a in range(len(poly)):
        b = (a + 1) % len(poly)
        if s[a] <= 0:
            out.append(poly[a])
        if (s[a] < 0 < s[b]) or (s[b] < 0 < s[a]):
            out.append(poly[a] + s[a] / (s[a] - s[b]) * (poly[b] - poly[a]))
    return np.array(out).reshape(-1, poly.shape[1])


def _brute_force(tri: np.ndarray, resolution: int, mode: str) -> np.ndarray:
    """Decision per voxel by polygon clipping: [R, R, R] bool."""
    out = np.zeros((resolution,) * 3, bool)
    n = np.cross(tri[1] - tri[0], tri[2] - tri[0])
    if mode == SIX_SEP and not np.any(n):
        return out
    for ijk in np.ndindex(*out.shape):
        lo = np.array(ijk, float)
        if mode == CONSERVATIVE:
            poly = tri
            for k in range(3):
                e = np.eye(3)[k]
                poly = _clip(_clip(poly, e, lo[k] + 1), -e, -lo[k])
            out[ijk] = len(poly) > 0
            continue
        c = lo + 0.5
        d = int(np.argmax(np.abs(n)))
        f_lo = n @ (c - 0.5 * np.eye(3)[d] - tri[0])
        f_hi = n @ (c + 0.5 * np.eye(3)[d] - tri[0])
        plane = f_lo * f_hi <= 0
        box = np.all(lo <= tri.max(0)) and np.all(lo + 1 >= tri.min(0))
        diamonds = True
        for drop in range(3):
            keep = [k for k in range(3) if k != drop]
            poly = tri[:, keep]
            for a, b in ((1, 1), (1, -1), (-1, 1), (-1, -1)):
                w = np.array([a, b], float)
                poly = _clip(poly, w, 0.5 + w @ c[keep])
            diamonds &= len(poly) > 0
        out[ijk] = plane and box and diamonds
    return out


def _coord(lo, hi):
    return st.one_of(
        st.integers(lo, hi).map(float), st.integers(8 * lo, 8 * hi).map(lambda x: x / 8), st.floats(lo, hi, width=32)
    )


@settings(max_examples=40, deadline=None)
@given(
    st.lists(st.tuples(*[_coord(-1, 5)] * 3), min_size=3, max_size=3), st.sampled_from(["general", "repeat", "point"])
)
def test_reference_matches_brute_force_clipping(tri, kind):
    tri = np.array(tri, np.float32)
    if kind == "repeat":
        tri[2] = tri[0]
    elif kind == "point":
        tri[1:] = tri[0]
    for mode in MODES:
        ref = _ref1(tri, resolution=4, mode=mode)
        brute = _brute_force(tri.astype(np.float64), 4, mode)
        ijk = np.argwhere(np.ones((4, 4, 4), bool))
        margin, _ = ref.lookup(ijk)
        want = brute[tuple(ijk.T)]
        clear = np.abs(margin) > 1e-9  # clipping is not exact on exact touching
        assert np.array_equal((margin >= 0)[clear], want[clear]), (mode, ijk[clear & ((margin >= 0) != want)])


@settings(max_examples=40, deadline=None)
@given(
    st.lists(st.tuples(*[st.floats(-2, 10, width=32)] * 3), min_size=3, max_size=3),
    st.tuples(*[st.floats(-0.05, 0.05)] * 3),
)
@example(tri=[(0.0, 0.0, 0.0), (0.0, 0.0, 0.0), (0.0, 0.0, 1.96875)], shift=(0.0, 0.0, 0.03125))
@example(tri=[(0.0, 1.0, 1.0), (1.0, 0.0, 0.0), (1.6377985e-21, 1.0, 1.0)], shift=(0.03125, 0.0, 0.0))
def test_reference_margin_bounds_translation(tri, shift):
    """Translating the triangle by s cannot flip a voxel whose margin exceeds |s|.

    Voxels the reference never examined (outside the triangle's bounding box) have the
    sentinel margin -inf, not a distance, so they are not counted as firm decisions.
    In 6-separating mode a zero-area triangle sets nothing: where rounding the moved
    corners to float32 merges two of them (or parts them), the triangle's area is a
    switch, not a margin, and that mode is not compared.
    """
    tri = np.array(tri, np.float32)
    moved = (tri.astype(np.float64) + np.array(shift)).astype(np.float32)
    slack = np.abs(moved.astype(np.float64) - tri - np.array(shift)).max()  # float32 rounding
    bound = np.linalg.norm(shift) + slack + 1e-9
    flat = [not np.cross(t[1] - t[0], t[2] - t[0]).any() for t in (tri.astype(np.float64), moved.astype(np.float64))]
    for mode in MODES:
        if mode == SIX_SEP and flat[0] != flat[1]:
            continue
        a, b = _ref1(tri, mode=mode), _ref1(moved, mode=mode)
        ijk = np.argwhere(np.ones((8, 8, 8), bool))
        ma, _ = a.lookup(ijk)
        mb, _ = b.lookup(ijk)
        firm = np.isfinite(ma) & (np.abs(ma) > bound)
        assert np.array_equal((ma >= 0)[firm], (mb >= 0)[firm]), mode


def test_reference_six_separating_closed_sphere():
    sphere = trimesh.creation.icosphere(subdivisions=3, radius=11.3)
    v = (sphere.vertices + 16.2).astype(np.float32)
    for mode in MODES:
        ref = reference_voxelize(v, sphere.faces, np.zeros(3, np.float32), np.float32(1.0), 32, mode)
        occ = np.zeros((32,) * 3, bool)
        occ[tuple(ref.voxels.T)] = True
        labels, count = scipy.ndimage.label(~occ)
        assert count >= 2, mode
        assert labels[16, 16, 16] != labels[0, 0, 0], mode
    six = _as_set(reference_voxelize(v, sphere.faces, np.zeros(3), 1.0, 32, SIX_SEP).voxels)
    cons = _as_set(reference_voxelize(v, sphere.faces, np.zeros(3), 1.0, 32, CONSERVATIVE).voxels)
    assert six < cons


# --------------------------------------------------------------------------------------------
# Implementation vs reference: real meshes
# --------------------------------------------------------------------------------------------


def _rotation(seed: int = 20240601) -> np.ndarray:
    rng = np.random.default_rng(seed)
    q, r = np.linalg.qr(rng.normal(size=(3, 3)))
    q = q * np.sign(np.diag(r))
    if np.linalg.det(q) < 0:
        q[:, 0] = -q[:, 0]
    return q


@functools.cache
def _rotated_mesh(meshes_dir, name: str):
    path = meshes_dir / f"{name}.obj"
    assert path.is_file(), f"test mesh {path} missing from tests/data"
    m = trimesh.load(path, process=False, force="mesh")
    v = np.asarray(m.vertices, np.float64)
    centre = v.mean(0)
    v = ((v - centre) @ _rotation().T + centre).astype(np.float32)
    return v, np.asarray(m.faces, np.int32)


@functools.cache
def _mesh_case(meshes_dir, name: str, resolution: int, mode: str):
    v, f = _rotated_mesh(meshes_dir, name)
    grid = jv.Grid.fit(jv.Mesh(v, f), resolution=resolution)
    return grid, _reference(v, f, grid, mode), _impl(v, f, grid, mode)


def _mesh_params():
    """Every mesh at 64^3, and at 128^3 as a slow case (run at ``_slow_resolution(128)``; at
    the default half scale that is the 64^3 case again, which the cache makes free)."""
    out = []
    for name in MESHES:
        out.append(pytest.param(name, 64, id=f"{name}-64"))
        out.append(pytest.param(name, _slow_resolution(128), marks=[pytest.mark.slow], id=f"{name}-128"))
    return out


@pytest.mark.codegen
@pytest.mark.parametrize("mode", MODES)
@pytest.mark.parametrize("name,resolution", _mesh_params())
def test_mesh_matches_reference(meshes_dir, name, resolution, mode):
    grid, ref, got = _mesh_case(meshes_dir, name, resolution, mode)
    context = f"{name} at {resolution}^3, {mode}, origin {_grid_params(grid)[0]}, voxel {_grid_params(grid)[1]}"
    cmp = _assert_matches(ref, got, context, exact=False)
    assert cmp.n_excused <= MAX_EXCUSED_FRACTION * cmp.n_ref, f"{context}: too many near-ties\n{cmp.report()}"


@pytest.mark.parametrize("name,resolution", _mesh_params())
def test_mesh_six_separating_subset_of_conservative(meshes_dir, name, resolution):
    _, ref_cons, cons = _mesh_case(meshes_dir, name, resolution, CONSERVATIVE)
    _, _, six = _mesh_case(meshes_dir, name, resolution, SIX_SEP)
    _assert_subset(six, cons, ref_cons, f"{name} at {resolution}^3", exact=False)


def _padded_grid(v: np.ndarray, resolution: int, pad: int = 3):
    lo, hi = v.min(0).astype(np.float64), v.max(0).astype(np.float64)
    h = float((hi - lo).max()) / (resolution - 2 * pad)
    origin = lo - pad * h
    return jv.Grid(origin=tuple(float(x) for x in origin), voxel_size=h, resolution=resolution)


def _dense(voxels: np.ndarray, resolution: int) -> np.ndarray:
    occ = np.zeros((resolution,) * 3, bool)
    occ[tuple(np.asarray(voxels).T)] = True
    return occ


@pytest.mark.parametrize("name", CLOSED_MESHES)
def test_six_separating_closed_mesh_flood_fill(meshes_dir, name):
    """No 6-connected path of empty voxels leads from outside to a voxel fully inside."""
    resolution = 64
    v, f = _rotated_mesh(meshes_dir, name)
    grid = _padded_grid(v, resolution)
    # voxels fully inside: empty in the reference conservative voxelization and enclosed
    cons = _dense(_reference(v, f, grid, CONSERVATIVE).voxels, resolution)
    labels, _ = scipy.ndimage.label(~cons)
    inside = ~cons & (labels != labels[0, 0, 0])
    assert inside.sum() > 0, f"{name}: no enclosed voxels at {resolution}^3"
    # cross-check a few of them with the mesh's winding number (about 1 inside, 0 outside)
    sample = np.argwhere(inside)[:: max(1, int(inside.sum()) // 20)]
    origin, h, _ = _grid_params(grid)
    centres = origin.astype(np.float64) + (sample + 0.5) * float(h)
    winding = np.abs(winding_number(v, f, centres))
    assert (winding > 0.5).all(), f"{name}: enclosed voxel centres not inside the mesh {winding.min()}"
    outer = origin.astype(np.float64) + 0.5 * float(h)  # grid corner: outside
    assert abs(winding_number(v, f, outer[None])[0]) < 0.5

    candidates = (("reference", _reference(v, f, grid, SIX_SEP).voxels), ("jaxvox", _impl(v, f, grid, SIX_SEP)))
    for label, voxels in candidates:
        occ = _dense(voxels, resolution)
        assert not occ[inside].any(), f"{name} ({label}): 6-separating voxel strictly inside the surface"
        labels6, count = scipy.ndimage.label(~occ)  # 6-connectivity
        outside = labels6 == labels6[0, 0, 0]
        leaked = np.argwhere(outside & inside)
        assert count >= 2, f"{name} ({label}): empty space is a single 6-connected component"
        assert len(leaked) == 0, (
            f"{name} ({label}): flood from outside reaches {len(leaked)} inside voxels, e.g. {leaked[:5].tolist()}"
        )


# --------------------------------------------------------------------------------------------
# Implementation vs reference: single triangles (hypothesis)
# --------------------------------------------------------------------------------------------

R_EXACT = 8  # exact cases: coordinates in [-1, 9], multiples of 1/8 -> exact in float32 too
R_FLOAT = 16

_HYPO = settings(max_examples=25, deadline=None, suppress_health_check=[HealthCheck.too_slow])


def _dyadic(lo, hi):
    return st.integers(8 * lo, 8 * hi).map(lambda x: x / 8)


def _lattice(lo=-1, hi=R_EXACT + 1):
    """Lattice coordinates, biased towards integers (voxel planes, edges and corners)."""
    return st.one_of(st.integers(lo, hi).map(float), _dyadic(lo, hi))


_lattice_point = st.tuples(_lattice(), _lattice(), _lattice())


@st.composite
def exact_general(draw):
    return np.array([draw(_lattice_point) for _ in range(3)])


@st.composite
def exact_in_voxel_plane(draw):
    axis, value = draw(st.integers(0, 2)), float(draw(st.integers(0, R_EXACT)))
    tri = np.array([draw(_lattice_point) for _ in range(3)])
    tri[:, axis] = value
    return tri


@st.composite
def exact_edge_on_voxel_edge(draw):
    """Two vertices share integer coordinates on two axes: that edge lies on a voxel edge line."""
    axis = draw(st.integers(0, 2))
    others = [k for k in range(3) if k != axis]
    tri = np.array([draw(_lattice_point) for _ in range(3)])
    for k in others:
        tri[0, k] = tri[1, k] = float(draw(st.integers(0, R_EXACT)))
    if draw(st.booleans()):  # and maybe the whole triangle in a voxel plane through that edge
        k = draw(st.sampled_from(others))
        tri[2, k] = tri[0, k]
    return tri[draw(st.permutations([0, 1, 2]))]


@st.composite
def exact_degenerate(draw):
    kind = draw(st.sampled_from(["point", "repeated", "collinear"]))
    a = np.array(draw(_lattice_point))
    if kind == "point":
        tri = np.array([a, a, a])
    elif kind == "repeated":
        tri = np.array([a, a, draw(_lattice_point)])
    else:
        step = np.array(draw(st.tuples(*[st.integers(-8, 8)] * 3))) / 8
        m, n = draw(st.integers(-4, 4)), draw(st.integers(-4, 4))
        tri = np.array([a, a + m * step, a + n * step])
    return tri[draw(st.permutations([0, 1, 2]))]


@st.composite
def exact_sliver(draw):
    """Long and thin: a third vertex one lattice step off a long edge."""
    a = np.array(draw(st.tuples(*[_dyadic(0, 3)] * 3)))
    d = np.array(draw(st.tuples(*[st.integers(-3, 6)] * 3)), float)
    m = draw(st.integers(1, 7))
    off = np.zeros(3)
    off[draw(st.integers(0, 2))] = draw(st.sampled_from([-1 / 8, 1 / 8]))
    return np.array([a, a + d, a + d * m / 8 + off])


def _float_point(lo, hi):
    return st.tuples(*[st.floats(lo, hi, width=32)] * 3)


@st.composite
def float_general(draw):
    return np.array([draw(_float_point(-2, R_FLOAT + 2)) for _ in range(3)])


@st.composite
def float_sliver(draw):
    a, b = (np.array(draw(_float_point(-1, R_FLOAT + 1))) for _ in range(2))
    t = draw(st.floats(0, 1))
    eps = draw(st.floats(1e-3, 0.1))
    w = np.array(draw(_float_point(-1, 1)))
    e = b - a
    w = w - e * (w @ e) / max(e @ e, 1e-12)
    w = w / max(np.linalg.norm(w), 1e-12)
    return np.array([a, b, a + t * e + eps * w])


@st.composite
def float_huge(draw):
    return np.array([draw(_float_point(-3 * R_FLOAT, 4 * R_FLOAT)) for _ in range(3)])


def _check_triangle(tri, grid, *, exact: bool):
    tri = np.asarray(tri, np.float32)
    faces = [[0, 1, 2]]
    results = {}
    for mode in MODES:
        ref = _reference(tri, faces, grid, mode)
        got = _impl(tri, faces, grid, mode)
        _assert_matches(ref, got, f"{mode}, triangle {tri.tolist()}, grid {_grid_params(grid)}", exact=exact)
        results[mode] = (ref, got)
    _assert_subset(
        results[SIX_SEP][1], results[CONSERVATIVE][1], results[CONSERVATIVE][0], f"triangle {tri.tolist()}", exact=exact
    )


@_HYPO
@given(st.one_of(exact_general(), exact_in_voxel_plane(), exact_edge_on_voxel_edge()))
def test_exact_triangles_match_exactly(tri):
    _check_triangle(tri, _unit_grid(R_EXACT), exact=True)


@_HYPO
@given(st.one_of(exact_degenerate(), exact_sliver()))
def test_exact_degenerate_and_sliver_triangles_match_exactly(tri):
    _check_triangle(tri, _unit_grid(R_EXACT), exact=True)


@_HYPO
@given(
    st.one_of(float_general(), float_sliver(), exact_degenerate()),
    st.tuples(*[st.floats(-5, 5, width=32)] * 3),
    st.floats(0.125, 4.0, width=32),
)
def test_float_triangles_match_up_to_near_ties(tri, origin, voxel_size):
    """Random, sliver and degenerate triangles (grid units) under a random grid placement."""
    origin, h = np.array(origin, np.float32), np.float32(voxel_size)
    world = (origin.astype(np.float64) + tri * np.float64(h)).astype(np.float32)
    grid = jv.Grid(origin=tuple(float(x) for x in origin), voxel_size=float(h), resolution=R_FLOAT)
    _check_triangle(world, grid, exact=False)


@_HYPO
@given(float_huge())
def test_huge_triangles_match_up_to_near_ties(tri):
    _check_triangle(tri, _unit_grid(R_FLOAT), exact=False)


@pytest.mark.parametrize("shift", [0.0, 0.5, 2.0])
def test_a_corner_1e_10_off_a_long_edge_in_one_projection(shift):
    """A large triangle whose corner c lies 1e-10 voxel off the line of a and b in the xy
    projection only (found by `test_huge_triangles_match_up_to_near_ties`). The compiled
    setup contracted one product of the projection's 2D crosses into a fused
    multiply-add, and the other product's rounding (about 4e-6) outweighed the sliver's
    true cross (2.75e-10) with the wrong sign: the short edge's half-plane turned
    outwards and the conservative voxels past y = 9 were lost (margins up to 0.48 voxel),
    whether or not the edge bc lies on a voxel plane (`shift`)."""
    tri = np.array([[0.0, 0.0, 1.0], [2.75, 24.048507690429688, 0.0], [0.0, 1e-10, 0.0]]) + [0.0, 0.0, shift]
    _check_triangle(tri, _unit_grid(R_FLOAT), exact=False)


@pytest.mark.parametrize("axes", [(0, 1, 2), (1, 2, 0), (2, 0, 1)])
def test_a_corner_a_tiny_float_off_a_voxel_plane(axes):
    """A corner at x = 1.2e-38, the smallest normal float32 (found by hypothesis): a
    half-plane's coefficient of that size made its bounds infinite, and an infinite slope
    times 0 is NaN, which dropped the columns (conservative: 2 of 8 voxels; 6-separating:
    none). Every order of the axes, both modes; a corner at x = 0 gives the same voxels."""
    tri = np.array([[0.0, 4.0, 0.0], [1.0, 0.0, 1.0], [1.1754943508222875e-38, 0.0, 1.0]], np.float32)
    grid = _unit_grid(R_FLOAT)
    _check_triangle(tri[:, list(axes)].astype(np.float64), grid, exact=False)
    on_plane = tri.copy()
    on_plane[2, 0] = 0.0
    mesh = lambda t: jv.Mesh(t[:, list(axes)], np.array([[0, 1, 2]], np.int32))
    for mode in MODES:
        np.testing.assert_array_equal(
            jv.voxelize(mesh(tri), grid, mode=mode).to_numpy(), jv.voxelize(mesh(on_plane), grid, mode=mode).to_numpy()
        )


@pytest.mark.parametrize("axes", [(0, 1, 2), (1, 2, 0), (2, 0, 1), (1, 0, 2)])
@pytest.mark.parametrize("offset", [2.0**-52, 1e-30, -(2.0**-40)])
def test_a_corner_offset_lost_in_float32_keeps_every_projection_inward(axes, offset):
    """A corner whose tiny offset rounds away in the edge differences (found by
    hypothesis): the 3D normal's component along that axis rounds to 0, while the
    projected edges keep the offset; the projection's half-planes must still point
    inwards (here voxel (1, 0, 0) was missing, 0.45 voxel inside the triangle)."""
    tri = np.array([[2.0, 1.0, 0.0], [0.0, 0.0, 0.0], [0.0, offset, 1.0]])[:, list(axes)]
    _check_triangle(tri, _unit_grid(R_FLOAT), exact=False)


@pytest.mark.parametrize("voxel_size", [1.0, 1.28125, 0.3])
def test_six_separating_repeated_vertex_sets_nothing(voxel_size):
    """A triangle with a repeated vertex has zero area in any arithmetic: no 6-separating voxel.

    (A float32 cross product evaluated with fused multiply-adds, ``a*b - fma(b, a, .)``, is
    not exactly zero for ``cross(e, e)``, so an area test must not rely on it.)
    """
    h = np.float32(voxel_size)
    tri = np.array([[0.0, 0.0, 0.0], [1.28125, 0.0, 1.0], [1.28125, 0.0, 1.0]], np.float32) * h
    grid = jv.Grid(origin=(0.0, 0.0, 0.0), voxel_size=float(h), resolution=16)
    for faces in ([[0, 1, 2]], [[1, 2, 0]], [[0, 0, 1]]):
        got = _impl(tri, faces, grid, SIX_SEP)
        assert len(got) == 0, f"faces {faces}, voxel size {h}: {got.tolist()}"
        assert len(_reference(tri, faces, grid, SIX_SEP).voxels) == 0
