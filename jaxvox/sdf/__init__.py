"""Signed distance functions (SDFs): primitives, transforms and CSG as jittable pytrees.

A *scene* is a tree of frozen dataclass nodes (`SDF` subclasses) built with the lower
case constructor functions below. Float parameters (radii, centres, blend factors) are
float32 array leaves and the node kinds and children are the tree structure, so a scene
can be passed to `jax.jit` (retraced only when the structure changes), evaluated under
`jax.vmap`, and differentiated with respect to its parameters by `jax.grad`. Calling a
scene on points ``f32[..., 3]`` returns signed distances ``f32[...]`` in world units:
negative inside, positive outside, zero on the surface (Hart 1996; Quilez, "Distance
functions").

Exact or bound. A node's value is either the *exact* Euclidean signed distance or only a
*bound*: a function with the same zero set whose magnitude never exceeds the true
distance as long as its Lipschitz constant is at most 1 (sphere tracing with it is
safe, only slower). Each class documents which; `is_exact` computes it for a tree and
`lipschitz_bound` bounds its Lipschitz constant (sphere tracing a scene whose bound is
above 1 can step through surfaces).

Sampled fields. `sampled(field)` wraps a sparse narrow-band distance field
(`jaxvox.SparseField`) as a node: its distance is the trilinear interpolation
`jaxvox.sample`, whose Lipschitz constant is up to sqrt(3) (see `Sampled`).

Parameter checks (shapes, NaN, signs) raise `JaxvoxError` when a constructor is called;
the value checks are skipped for traced values, so scenes can be built inside `jit` and
`grad`.
"""

from jaxvox.sdf.base import SDF
from jaxvox.sdf.operations import (
    Complement,
    Difference,
    Intersection,
    Mix,
    Rotate,
    Scale,
    SmoothIntersection,
    SmoothUnion,
    Translate,
    Union,
    complement,
    difference,
    intersection,
    mix,
    rotate,
    rotation,
    scale,
    smooth_intersection,
    smooth_union,
    translate,
    union,
)
from jaxvox.sdf.primitives import (
    Box,
    Capsule,
    Cylinder,
    Plane,
    RoundedBox,
    Sphere,
    Torus,
    box,
    capsule,
    cylinder,
    plane,
    rounded_box,
    sphere,
    torus,
)
from jaxvox.sdf.queries import (
    MAX_MESH_RESOLUTION,
    NORMAL_METHODS,
    is_exact,
    lipschitz_bound,
    normal,
    to_mesh,
)
from jaxvox.sdf.sampled import Sampled, sampled

__all__ = [
    "Box",
    "Capsule",
    "Complement",
    "Cylinder",
    "Difference",
    "Intersection",
    "MAX_MESH_RESOLUTION",
    "Mix",
    "NORMAL_METHODS",
    "Plane",
    "Rotate",
    "RoundedBox",
    "SDF",
    "Sampled",
    "Scale",
    "SmoothIntersection",
    "SmoothUnion",
    "Sphere",
    "Torus",
    "Translate",
    "Union",
    "box",
    "capsule",
    "complement",
    "cylinder",
    "difference",
    "intersection",
    "is_exact",
    "lipschitz_bound",
    "mix",
    "normal",
    "plane",
    "rotate",
    "rotation",
    "rounded_box",
    "sampled",
    "scale",
    "smooth_intersection",
    "smooth_union",
    "sphere",
    "to_mesh",
    "torus",
    "translate",
    "union",
]
