"""Point-query methods shared by `bench_points.py` and `sign_failures.py`: jaxvox and its peers.

``METHODS[name] = (setup, query)``: ``setup(V, F)`` builds what the method needs (its index,
scene or tree) from float64 vertices ``[V, 3]`` and int64 faces ``[F, 3]``; ``query(state, P)``
answers float32 points ``[N, 3]`` with ``(kind, values)``, where kind is ``"signed"``
(negative inside), ``"unsigned"``, ``"winding"`` (inside where > 1/2) or ``"occupancy"``
(bool). Peers are imported inside the functions, so a missing one fails only its own method.
"""

from __future__ import annotations

import numpy as np


def _jaxvox_setup(V, F):
    import jax

    import jaxvox as jv
    import jaxvox.points as jp

    return jax.block_until_ready(jp.mesh_index(jv.Mesh(V.astype(np.float32), F.astype(np.int32))))


def _jaxvox(kind, call):
    def query(idx, P):
        import jax

        import jaxvox.points as jp

        return kind, np.asarray(jax.block_until_ready(call(jp, idx, P)))

    return _jaxvox_setup, query


def _igl(sign):
    def query(VF, P):
        import igl

        s = getattr(igl, f"SIGNED_DISTANCE_TYPE_{sign}")
        return "signed", igl.signed_distance(P.astype(np.float64), *VF, sign_type=s)[0]

    # libigl builds its AABB tree inside every call: the setup only converts the arrays
    return (lambda V, F: (V.astype(np.float64), F.astype(np.int64))), query


def _igl_fwn_setup(V, F):
    import igl

    bvh = igl.FastWindingNumberBVH()
    bvh.init(V.astype(np.float64), F.astype(np.int64))
    return bvh


def _o3d_setup(V, F):
    import open3d as o3d

    scene = o3d.t.geometry.RaycastingScene()
    scene.add_triangles(o3d.core.Tensor(V.astype(np.float32)), o3d.core.Tensor(F.astype(np.uint32)))
    return scene


def _o3d(fn, kind):
    def query(scene, P):
        import open3d as o3d

        out = getattr(scene, fn)(o3d.core.Tensor(P.astype(np.float32))).numpy()
        return kind, out.astype(bool) if kind == "occupancy" else out

    return _o3d_setup, query


def _warp_setup(V, F):
    import warp as wp

    wp.config.quiet = True
    wp.init()

    @wp.kernel
    def sd_winding(mesh: wp.uint64, pts: wp.array(dtype=wp.vec3), out: wp.array(dtype=float)):
        tid = wp.tid()
        q = wp.mesh_query_point_sign_winding_number(mesh, pts[tid], 1.0e6, 2.0, 0.5)
        if q.result:
            out[tid] = q.sign * wp.length(pts[tid] - wp.mesh_eval_position(mesh, q.face, q.u, q.v))

    @wp.kernel
    def sd_normal(mesh: wp.uint64, pts: wp.array(dtype=wp.vec3), out: wp.array(dtype=float)):
        tid = wp.tid()
        q = wp.mesh_query_point_sign_normal(mesh, pts[tid], 1.0e6)
        if q.result:
            out[tid] = q.sign * wp.length(pts[tid] - wp.mesh_eval_position(mesh, q.face, q.u, q.v))

    mesh = wp.Mesh(
        points=wp.array(V.astype(np.float32), dtype=wp.vec3, device="cpu"),
        indices=wp.array(F.astype(np.int32).ravel(), dtype=wp.int32, device="cpu"),
    )
    return dict(mesh=mesh, winding=sd_winding, normal=sd_normal)


def _warp(which):
    def query(state, P):
        import warp as wp

        pts = wp.array(P.astype(np.float32), dtype=wp.vec3, device="cpu")
        out = wp.zeros(len(P), dtype=float, device="cpu")
        wp.launch(state[which], dim=len(P), inputs=[state["mesh"].id, pts, out], device="cpu")
        wp.synchronize_device("cpu")
        return "signed", out.numpy()

    return _warp_setup, query


def _fcpw_setup(V, F):
    import fcpw

    scene = fcpw.scene_3D()
    scene.set_object_count(1)
    scene.set_object_vertices(np.asfortranarray(V, np.float32), 0)
    scene.set_object_triangles(np.asfortranarray(F, np.int32), 0)
    scene.build(fcpw.aggregate_type.bvh_surface_area, True)
    return scene


def _fcpw_query(scene, P):
    import fcpw

    hits = fcpw.interaction_3D_list()
    scene.find_closest_points(np.asfortranarray(P, np.float32), np.full(len(P), np.inf, np.float32), hits)
    return "unsigned", np.fromiter((h.d for h in hits), np.float64, len(P))  # read-back included


def _pysdf_setup(V, F):
    import pysdf

    return pysdf.SDF(V.astype(np.float32), F.astype(np.uint32))


def _mesh_to_sdf_setup(V, F):
    import trimesh

    return trimesh.Trimesh(V, F, process=False)


def _mesh_to_sdf_query(mesh, P):
    import mesh_to_sdf

    try:  # the default surface sampling renders scans with pyrender (an OpenGL context)
        return "signed", mesh_to_sdf.mesh_to_sdf(mesh, P)
    except Exception as e:  # no headless context: sample the surface instead (no rendering)
        _mesh_to_sdf_query.scan_error = f"{type(e).__name__}: {e}"[:300]
        return "signed", mesh_to_sdf.mesh_to_sdf(mesh, P, surface_point_method="sample")


METHODS = {
    "jaxvox closest_points": _jaxvox("unsigned", lambda jp, i, P: jp.closest_points(i, P).distance),
    "jaxvox SD winding": _jaxvox("signed", lambda jp, i, P: jp.signed_distance(i, P, sign="winding")),
    "jaxvox SD pseudonormal": _jaxvox("signed", lambda jp, i, P: jp.signed_distance(i, P, sign="pseudonormal")),
    "jaxvox occupancy winding": _jaxvox("occupancy", lambda jp, i, P: jp.occupancy(i, P, sign="winding")),
    "libigl SD fast winding": _igl("FAST_WINDING_NUMBER"),
    "libigl SD pseudonormal": _igl("PSEUDONORMAL"),
    "libigl fast_winding_number": (
        _igl_fwn_setup,
        lambda bvh, P: ("winding", bvh.winding_number(P.astype(np.float64))),
    ),
    "Open3D distance": _o3d("compute_distance", "unsigned"),
    "Open3D signed distance": _o3d("compute_signed_distance", "signed"),
    "Open3D occupancy": _o3d("compute_occupancy", "occupancy"),
    "Warp winding sign": _warp("winding"),
    "Warp normal sign": _warp("normal"),
    "fcpw closest points": (_fcpw_setup, _fcpw_query),
    "pysdf": (_pysdf_setup, lambda f, P: ("signed", -f(P.astype(np.float32)))),  # pysdf: positive inside
    "mesh_to_sdf": (_mesh_to_sdf_setup, _mesh_to_sdf_query),
}


def inside_of(kind, values):
    """The method's inside/outside (None for unsigned distances)."""
    values = np.asarray(values)
    return {
        "signed": lambda: values < 0,
        "winding": lambda: values > 0.5,
        "occupancy": lambda: values.astype(bool),
    }.get(kind, lambda: None)()
